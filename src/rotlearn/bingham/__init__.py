"""The Bingham belief over unit quaternions that the symmetric matrix A encodes (paper III-C).

Floor 1: torch only. `descriptors` (mode, dispersion, DT, eigen-gap, each defined once from A's
eigenvalues), `normalizer` (N(lam), its moments, `log_prob`, `nll`), `sampling` (`sample`); the
training loss built on `nll` is `rotlearn.losses.BinghamNLLLoss` (floor 2).
Quaternions are scalar LAST, x = (x, y, z, w), like everywhere in rotlearn.

Convention
----------
A (..., 4, 4) symmetric (paper eq. 8) defines the density on the unit sphere S^3

    p(x; A) = exp(-x^T A x) / Z(A),

the paper's eqs. (14)-(15) up to a constant shift of the exponent. With A's eigenvalues in
ascending order l1 <= l2 <= l3 <= l4 and unit eigenvectors v1..v4,

    -x^T A x = -l1 + x^T (-A + l1 I) x = -l1 + sum_i lam_i (d_i^T x)^2,

so p is the paper's BINGHAM(D, Lambda) with

* dispersion coefficients lam = (l1 - l4, l1 - l3, l1 - l2), ascending, all <= 0
  (`dispersion`; the paper's lambda^dc_1 <= lambda^dc_2 <= lambda^dc_3 <= 0, section III-C);
* their directions (d1, d2, d3) = (v4, v3, v2) (`bingham_parameters` returns D = [v4 v3 v2 v1]);
* the mode d4 = v1, the eigenvector of the smallest eigenvalue: the A head's quaternion
  (eq. 11; `mode`);
* p(x) = exp(sum_i lam_i (d_i^T x)^2) / N(lam) and Z(A) = exp(-l1) N(lam).

Another convention in use writes the density as exp(+x^T M x) / N, with the mode at M's LARGEST
eigenvector; it is this one with M = -A. The paper's loss (19) prints
`q^T D Lambda D^T q + N(Lambda)`; the negative log-likelihood is
`-q^T D Lambda D^T q + log N(Lambda)` = `q^T A q - l1 + log N(lam)` (`nll`).

Measure
-------
N is taken w.r.t. the UNIFORM PROBABILITY MEASURE mu on S^3 (total mass 1), so N(0) = 1 and
N(lam) = E_{x ~ mu}[exp(sum_i lam_i x_i^2)] = 1F1(1/2; 2; diag(lam, 0)), the confluent
hypergeometric function of matrix argument. `log_prob` is a log density w.r.t. mu: it integrates
to 1 against mu. For the density w.r.t. the surface (Hausdorff) measure, whose total is
|S^3| = 2 pi^2, subtract `LOG_AREA_S3`.

The normalising constant
------------------------
N(lam) (with the fourth coefficient 0, or any four real coefficients) is the value at t = 1 of
the inverse Laplace transform of prod_i (p - lam_i)^(-1/2) (integrate exp(y^T diag(lam) y - p |y|^2)
over R^4 in polar coordinates):

    N(lam) = 1 / (2 pi i) int_C e^z prod_{i=1..4} (z - lam_i)^(-1/2) dz.

It is evaluated by Talbot's method on Weideman's (2006) optimised contour with the
midpoint rule, a FIXED node set (12 complex nodes in float64, 8 in float32), valid uniformly for
any coefficients on the negative real axis: the relative error of N is about 1e-12 in float64
and a few 1e-6 in float32 for every lam in [-MAX_DISPERSION, 0]^3 (measured against adaptive
quadrature of the Bessel form in the tests). The moments E[(d_i^T x)^2] = d log N / d lam_i
come from the same nodes and are the exact gradient of log N (custom autograd function, first
order only).

Why not the 1-D Hopf/Bessel integral N = int_0^1 e^{s(l1+l2)/2} I0(s(l1-l2)/2) e^{(1-s)(l3+l4)/2}
I0((1-s)(l3-l4)/2) ds (the tests' reference): with boundary layers of width ~1/|lam| it needs
about 100 graded Gauss-Legendre nodes for 1e-8, each with two Bessel evaluations, and
torch.special.i0e costs 30-70 ns per element on a CPU, some 20x the time budget; the Talbot sum
needs 8-12 nodes of elementary arithmetic and has no endpoint layers to resolve.

Every function takes any leading batch shape, works on any device, in float32 and float64, and
returns its input's dtype (the functions of lam also take float16 and bfloat16, computed in
float32). Bad input (NaN or Inf, a positive dispersion coefficient, a coefficient or eigenvalue
spread beyond MAX_DISPERSION) raises ValueError naming the problem and the first offending batch
index.
"""

from rotlearn.bingham.calibration import (
    CREDIBLE_LEVELS,
    coverage,
    credible_radius_deg,
    expected_calibration_error,
    hpd_level,
)
from rotlearn.bingham.descriptors import (
    LOG_AREA_S3,
    MAX_DISPERSION,
    bingham_parameters,
    dispersion,
    dispersion_from_eigenvalues,
    dt_from_eigenvalues,
    dt_score,
    eigengap,
    eigengap_from_eigenvalues,
    mode,
)
from rotlearn.bingham.normalizer import log_normalizer, log_prob, moments, nll, normalizer
from rotlearn.bingham.sampling import sample
from rotlearn.bingham.temperature import TemperatureFit, fit_temperature

__all__ = [
    "CREDIBLE_LEVELS",
    "LOG_AREA_S3",
    "MAX_DISPERSION",
    "TemperatureFit",
    "bingham_parameters",
    "coverage",
    "credible_radius_deg",
    "dispersion",
    "dispersion_from_eigenvalues",
    "dt_from_eigenvalues",
    "dt_score",
    "eigengap",
    "eigengap_from_eigenvalues",
    "expected_calibration_error",
    "fit_temperature",
    "hpd_level",
    "log_normalizer",
    "log_prob",
    "mode",
    "moments",
    "nll",
    "normalizer",
    "sample",
]
