"""The matrix Fisher belief on SO(3) (Mohlin, Sullivan & Bianchi, NeurIPS 2020), as a Bingham one.

Floor 1: torch only, like `rotlearn.bingham`, on which it is built. `parameters` (the linear maps
F <-> A, the proper SVD, A's eigenvalues in closed form, the mode), `density` (the normaliser
c(F), `log_prob`, `nll`, `sample`); the training loss built on `nll` is
`rotlearn.losses.FisherNLLLoss` (floor 2) and the head `rotlearn.heads.FisherHead` (`rep=fisher`).
Quaternions are scalar LAST, q = (x, y, z, w), Hamilton convention (`rotlearn.geometry`).

The density
-----------
F (..., 3, 3), any real matrix, defines the matrix Fisher density on SO(3)

    p(R; F) = exp(tr(F^T R)) / c(F),   c(F) = int_SO(3) exp(tr(F^T R)) dR,

w.r.t. the HAAR PROBABILITY MEASURE dR (total mass 1), so c(0) = 1. Its mode is the rotation
closest to F, the SVD-9D map (`mode`, `rotlearn.geometry.special_orthogonalize`); Mohlin et al.
train a network to output the 9 entries of F by this negative log-likelihood.

It is exactly a Bingham density
-------------------------------
For R = R(q) (`rotlearn.geometry.quat_to_rotmat`) the exponent is a quadratic form in q,

    tr(F^T R(q)) = q^T K(F) q,

with K(F) the symmetric, traceless 4 x 4 (Davenport) matrix, LINEAR in F; in the order (x, y, z, w)

    K = [[F11-F22-F33, F12+F21,      F13+F31,      F32-F23    ],
         [F12+F21,     F22-F11-F33,  F23+F32,      F13-F31    ],
         [F13+F31,     F23+F32,      F33-F11-F22,  F21-F12    ],
         [F32-F23,     F13-F31,      F21-F12,      F11+F22+F33]].

The uniform probability measure on S^3 pushes forward to the Haar probability measure on SO(3)
(q -> R(q) is 2:1, q and -q give the same R, and the density is antipodally symmetric). So
p(R(q); F) is the Bingham density p(q) ~ exp(-q^T A q) of `rotlearn.bingham` with

    A = -K(F)   (`bingham_from_fisher`; `fisher_from_bingham` inverts it up to A's trace),

and c(F) = Z(A) = exp(-l1) N(lam), the Bingham normaliser over the uniform probability measure
on S^3 (`rotlearn.bingham.log_normalizer`: one normaliser for both beliefs, no second formula).

Its singular values play the eigen-gaps' role
---------------------------------------------
With the proper SVD F = U diag(s) V^T (`proper_svd`: det U = det V = +1, s1 >= s2 >= |s3|, s3
carrying the sign of det F), the ascending eigenvalues of A are, in closed form,

    l1 = -(s1 + s2 + s3),  l2 = -s1 + s2 + s3,  l3 = s1 - s2 + s3,  l4 = s1 + s2 - s3

(`eigenvalues_from_fisher`; K(F) and K(diag(s)) are similar through the rotations U, V). So the
Bingham descriptors of `rotlearn.bingham.descriptors`, each defined once from these eigenvalues,
apply unchanged: the DT score 3 l1 - l2 - l3 - l4 = -4 (s1 + s2 + s3), the eigen-gap
l2 - l1 = 2 (s2 + s3), the dispersion coefficients (-2(s1+s2), -2(s1+s3), -2(s2+s3)).

Accuracy
--------
log c(F) inherits the Bingham normaliser's accuracy (relative error of N about 1e-12 in float64,
a few 1e-6 in float32) plus the rounding of the singular values (about eps * s1 absolute in
log c). Measured against an independent quadrature of Mohlin et al.'s 1-D Bessel integral
(tests/fisher/test_fisher.py: 422 cases, s from 0 and 1e-6 to 4e7, both signs of det F,
repeated values, F = U diag(s) V^T with random rotations U, V), the relative error of c in
float64 is at most 2.3e-12 up to s1 = 1e3, 7e-12 at 1e4 and 1.2e-10 at 1e5 (rounding F's entries
to float64 alone moves log c by ~eps s1; for diagonal F 1.5e-11 at 1e5); in float32 at most
5e-7 (1 + s1): 7e-6 for s1 <= 100, 3e-3 at s1 = 1e4 (log c is of the size of s1, so float32
holds it to about that).
Supported range: s1 + s2 <= MAX_SINGULAR_SUM = MAX_DISPERSION / 2 = 5e7 (A's eigenvalue spread
l4 - l1 = 2 (s1 + s2) is the Bingham normaliser's range). The NLL's fit term
s1 + s2 + s3 - tr(F^T R) is valued in float64, so a float32 NLL stays within 1e-3 nats of the
float64 one of the same F across the range (tested).

Every public function takes any leading batch shape, float32 and float64, any device; under
autocast (mixed precision) it computes and returns float32. Bad input (NaN or Inf, F out of
range) raises ValueError naming the problem and the first offending batch index.
"""

from rotlearn.fisher.density import log_normalizer, log_prob, nll, sample
from rotlearn.fisher.parameters import (
    MAX_SINGULAR_SUM,
    bingham_from_fisher,
    eigenvalues_from_fisher,
    fisher_from_bingham,
    mode,
    proper_svd,
)

__all__ = [
    "MAX_SINGULAR_SUM",
    "bingham_from_fisher",
    "eigenvalues_from_fisher",
    "fisher_from_bingham",
    "log_normalizer",
    "log_prob",
    "mode",
    "nll",
    "proper_svd",
    "sample",
]
