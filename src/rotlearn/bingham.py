"""The Bingham belief over unit quaternions that the symmetric matrix A encodes (paper III-C).

Floor 1: torch only. Quaternions are scalar LAST, x = (x, y, z, w), like everywhere in rotlearn.

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

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from rotlearn.errors import ConfigValueError, batch_index
from rotlearn.geometry import quat_canonical, rotmat_to_quat
from rotlearn.heads import HEADS, RotationPrediction
from rotlearn.trust import config_target

__all__ = [
    "LOG_AREA_S3",
    "MAX_DISPERSION",
    "BinghamNLLLoss",
    "bingham_parameters",
    "dispersion",
    "dispersion_from_eigenvalues",
    "dt_score",
    "eigengap",
    "log_normalizer",
    "log_prob",
    "mode",
    "moments",
    "nll",
    "normalizer",
    "sample",
]

MAX_DISPERSION = 1e6
"""Largest supported |dispersion coefficient| (eigenvalue spread l4 - l1 of A).

Chosen well above the 1e4 of the specification: a belief with a 1 degree error already has
|lam| ~ 2 / theta^2 ~ 6.6e3, and the normaliser is verified up to 1e6 in both dtypes."""

LOG_AREA_S3 = math.log(2.0 * math.pi**2)
"""log |S^3|: subtract from `log_prob` for a density w.r.t. the surface measure."""


# ----------------------------------------------------------------------------- eigen-decomposition


def _eigh(A: Tensor, eigenvectors: bool = True) -> tuple[Tensor, Tensor | None]:
    """The ONE place that decomposes A (swap in a faster 4x4 solver here).

    Reads the symmetric part (A + A^T) / 2, which defines the same density as A.

    Returns:
        ascending eigenvalues (..., 4) and, if asked, unit eigenvectors as columns (..., 4, 4)
        (else None). Without eigenvectors the gradient is well defined at repeated eigenvalues.
    """
    A = 0.5 * (A + A.mT)
    if eigenvectors:
        return torch.linalg.eigh(A)
    return torch.linalg.eigvalsh(A), None


# ----------------------------------------------------------------------------------- validation


def _raise_first(bad: Tensor, what: str) -> None:
    """Raise ValueError naming the first True of `bad` (batch-shaped), if any (one argmax)."""
    if bad.numel() and bool(bad.any()):
        flat = int(bad.reshape(-1).to(torch.uint8).argmax())
        raise ValueError(f"{what} at batch index {batch_index(flat, tuple(bad.shape))}")


def _float_dtype(t: Tensor, name: str) -> None:
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got {t.dtype}")


def _check_A(A: Tensor) -> None:
    _float_dtype(A, "A")
    if A.dim() < 2 or A.shape[-2:] != (4, 4):
        raise ValueError(f"A must have shape (..., 4, 4), got {tuple(A.shape)}")
    _raise_first(~torch.isfinite(A).flatten(-2).all(-1), "A has NaN or Inf")


def _check_lam(lam: Tensor) -> None:
    _float_dtype(lam, "lam")
    if lam.dim() < 1 or lam.shape[-1] not in (3, 4):
        raise ValueError(f"lam must have shape (..., 3) or (..., 4), got {tuple(lam.shape)}")
    finite = torch.isfinite(lam).all(-1)
    if lam.shape[-1] == 3:
        ok = finite & (lam <= 0).all(-1) & (lam >= -MAX_DISPERSION).all(-1)
    else:
        ok = finite & (lam.amax(-1) - lam.amin(-1) <= MAX_DISPERSION)
    if bool(ok.all()):
        return
    _raise_first(~finite, "lam has NaN or Inf")
    if lam.shape[-1] == 3:
        _raise_first((lam > 0).any(-1), "dispersion coefficients must be <= 0; lam has one > 0")
        _raise_first(
            (lam < -MAX_DISPERSION).any(-1),
            f"dispersion coefficient below -MAX_DISPERSION = {-MAX_DISPERSION:g} (unsupported)",
        )
    _raise_first(
        lam.amax(-1) - lam.amin(-1) > MAX_DISPERSION,
        f"coefficient spread max(lam) - min(lam) above MAX_DISPERSION = {MAX_DISPERSION:g}",
    )


def _check_spread(eigenvalues: Tensor) -> None:
    spread = eigenvalues[..., 3] - eigenvalues[..., 0]
    _raise_first(
        spread > MAX_DISPERSION,
        f"eigenvalue spread l4 - l1 of A above MAX_DISPERSION = {MAX_DISPERSION:g} (unsupported)",
    )


# ----------------------------------------------------------------------- descriptors of A (eq. 26)


def mode(A: Tensor) -> Tensor:
    """The mode of the belief: A's minimum eigenvector (paper eq. 11; d4 in eq. 15).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (..., 4) unit quaternions (x, y, z, w) with canonical sign (w >= 0). The gradient is that
        of `torch.linalg.eigh` (NaN where l1 == l2).
    """
    _check_A(A)
    return quat_canonical(_eigh(A)[1][..., 0])


def dispersion_from_eigenvalues(eigenvalues: Tensor) -> Tensor:
    """`dispersion` from the ascending eigenvalues (..., 4) of A (as the A head gives them)."""
    return eigenvalues[..., :1] - eigenvalues[..., [3, 2, 1]]


def dispersion(A: Tensor) -> Tensor:
    """Dispersion coefficients (l1 - l4, l1 - l3, l1 - l2) of the belief A (paper III-C).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (..., 3) ascending coefficients lam_1 <= lam_2 <= lam_3 <= 0, attached to the
        eigenvectors (v4, v3, v2); more negative = more concentrated. Invariant to A -> A + cI.
    """
    _check_A(A)
    return dispersion_from_eigenvalues(_eigh(A, eigenvectors=False)[0])


def bingham_parameters(A: Tensor) -> tuple[Tensor, Tensor]:
    """The paper's (D, Lambda) of eq. (15): D Lambda D^T = -A + l1 I.

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        D (..., 4, 4) orthogonal, columns (d1, d2, d3, d4) = (v4, v3, v2, v1) with d4 the mode
        (sign as returned by the solver), and lam (..., 3) = `dispersion(A)`, so that
        Lambda = diag(lam_1, lam_2, lam_3, 0).
    """
    _check_A(A)
    ev, V = _eigh(A)
    return V[..., [3, 2, 1, 0]], dispersion_from_eigenvalues(ev)


def dt_score(A: Tensor) -> Tensor:
    """Dispersion-thresholding score tr(Lambda) = 3 l1 - l2 - l3 - l4 (paper eq. 26).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (...,) the sum of the dispersion coefficients, <= 0; MORE NEGATIVE = MORE CONFIDENT
        (the paper keeps the samples below a quantile of the training scores). Invariant to
        A -> A + cI.
    """
    return dispersion(A).sum(-1)


def eigengap(A: Tensor) -> Tensor:
    """l2 - l1 >= 0: the gap that makes the mode well defined (= -lam_3, the weakest dispersion).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (...,) the gap between A's two smallest eigenvalues; 0 means the mode is not unique.
    """
    _check_A(A)
    ev = _eigh(A, eigenvectors=False)[0]
    return ev[..., 1] - ev[..., 0]


# ------------------------------------------------------------------- normalising constant N(lam)

# Weideman (2006), "Optimizing Talbot's contours for the inversion of the Laplace transform":
# z(theta) = n (SIGMA + MU theta cot(ALPHA theta) + i NU theta), error ~ 3.89^-n for n nodes.
_SIGMA, _MU, _ALPHA, _NU = -0.6122, 0.5017, 0.6407, 0.2645
# Nodes in the upper half plane (half of n by conjugate symmetry), per working dtype.
_HALF_NODES = {torch.float32: 8, torch.float64: 12}
_NODE_CACHE: dict[tuple[torch.dtype, torch.device], tuple[Tensor, Tensor, Tensor, Tensor]] = {}
_CPU_CHUNK_ELEMENTS = 1 << 17  # (rows x nodes) per CPU block: the temporaries stay in cache


def _talbot_nodes(
    dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(Re z_k, Im z_k, Re c_k, Im c_k) with N(lam) ~ Re sum_k c_k prod_i (z_k - lam_i)^(-1/2).

    c_k includes the midpoint weight, the contour derivative, e^{z_k} and the factor
    z_k^(-1/2) of the implicit fourth coefficient 0; computed once in float64 and cached.
    """
    key = (dtype, device)
    if key not in _NODE_CACHE:
        m = _HALF_NODES[dtype]
        n = 2 * m
        h = 2.0 * math.pi / n
        theta = (torch.arange(m, dtype=torch.float64) + 0.5) * h
        at = _ALPHA * theta
        z = torch.complex(n * (_SIGMA + _MU * theta / torch.tan(at)), n * _NU * theta)
        dz = torch.complex(
            n * _MU * (1.0 / torch.tan(at) - at / torch.sin(at) ** 2),
            torch.full_like(theta, n * _NU),
        )
        # (1 / 2 pi i) * h * 2 (conjugate half) = h / (pi i)
        c = (h / math.pi) * torch.exp(z) * dz / (1j * torch.sqrt(z))
        _NODE_CACHE[key] = tuple(
            t.to(device=device, dtype=dtype) for t in (z.real, z.imag, c.real, c.imag)
        )
    return _NODE_CACHE[key]


def _talbot(lam: Tensor, need_moments: bool) -> tuple[Tensor, Tensor | None]:
    """log N and E[x_i^2] for (B, 3) coefficients in [-MAX_DISPERSION, 0], in lam's dtype.

    Each factor (z - lam_i)^(1/2) is the principal root of a number in the upper half plane,
    taken without cancellation; their product is continuous along the contour. Blocks of rows
    on the CPU keep every (rows, nodes) temporary in cache.
    """
    zr, zi, cr, ci = _talbot_nodes(lam.dtype, lam.device)
    half_zi = 0.5 * zi
    zi2 = zi * zi
    rows = lam.shape[0]
    block = rows if lam.device.type != "cpu" else max(1, _CPU_CHUNK_ELEMENTS // zr.numel())
    log_n = torch.empty(rows, dtype=lam.dtype, device=lam.device)
    mom = torch.empty(rows, 3, dtype=lam.dtype, device=lam.device) if need_moments else None
    for start in range(0, rows, block):
        part = lam[start : start + block]
        qr = qi = None
        xs, m2s = [], []
        for i in range(3):
            x = zr - part[:, i : i + 1]  # Re(z - lam_i); Im is zi > 0
            m2 = torch.addcmul(zi2, x, x)  # |z - lam_i|^2
            r = torch.sqrt(0.5 * (torch.sqrt(m2) + x.abs()))  # the larger root component
            s = half_zi / r  # the smaller one: r s = Im / 2
            right = x >= 0
            a, b = torch.where(right, r, s), torch.where(right, s, r)  # sqrt(z - lam_i) = a + ib
            if qr is None:
                qr, qi = a, b
            else:
                qr, qi = qr * a - qi * b, qr * b + qi * a
            xs.append(x)
            m2s.append(m2)
        den = torch.addcmul(qr * qr, qi, qi)
        fr = (cr * qr + ci * qi) / den  # c / Q = c conj(Q) / |Q|^2
        value = fr.sum(-1)
        log_n[start : start + block] = torch.log(value)
        if mom is not None:
            fi = (ci * qr - cr * qi) / den
            half_inv = 0.5 / value
            for i in range(3):  # d/d lam_i: factor 1 / (2 (z - lam_i))
                re = torch.addcmul(fr * xs[i], fi, zi) / m2s[i]
                mom[start : start + block, i] = re.sum(-1) * half_inv
    return log_n, mom


class _LogNormalizer(torch.autograd.Function):
    """log N(lam) for (B, 3) valid coefficients; backward multiplies by the saved moments."""

    @staticmethod
    def forward(ctx, lam: Tensor) -> Tensor:
        log_n, mom = _talbot(lam, need_moments=ctx.needs_input_grad[0])
        ctx.save_for_backward(mom if mom is not None else lam.new_empty(0))
        return log_n

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> Tensor:
        (mom,) = ctx.saved_tensors
        return grad.unsqueeze(-1) * mom


def _working_dtype(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype in _HALF_NODES else torch.float32


def _log_normalizer3(lam: Tensor) -> Tensor:
    """`log_normalizer` of validated (..., 3) coefficients (autograd-aware)."""
    work = _working_dtype(lam.dtype)
    flat = lam.reshape(-1, 3).to(work)
    if flat.shape[0] == 0:
        return lam.new_zeros(lam.shape[:-1])
    return _LogNormalizer.apply(flat).reshape(lam.shape[:-1]).to(lam.dtype)


def log_normalizer(lam: Tensor) -> Tensor:
    """log N(lam), N = E_mu[exp(sum_i lam_i x_i^2)] over the uniform probability measure on S^3.

    N is the normaliser of paper eq. (14) (Talbot inversion, see the module docstring).

    Args:
        lam: (..., 3) dispersion coefficients in [-MAX_DISPERSION, 0] (any order; the fourth
            coefficient is 0), or (..., 4) any real coefficients with spread
            max - min <= MAX_DISPERSION, for which N(lam + c) = e^c N(lam).

    Returns:
        (...,) log N in lam's dtype; N(0) = 1. Differentiable once: the gradient is the vector
        of second moments E[x_i^2] (`moments`).

    Raises:
        ValueError: NaN/Inf, a positive (..., 3) coefficient, or one out of range; the message
            names the first offending batch index.
    """
    _check_lam(lam)
    if lam.shape[-1] == 3:
        return _log_normalizer3(lam)
    # The top coefficient from the sort, not amax: at ties amax would split its gradient.
    ordered = torch.sort(lam, dim=-1, descending=True).values
    top = ordered[..., :1]
    return top.squeeze(-1) + _log_normalizer3(ordered[..., 1:] - top)


def normalizer(lam: Tensor) -> Tensor:
    """exp(`log_normalizer`(lam)): N w.r.t. the uniform probability measure (N(0) = 1).

    For large |lam| N underflows long before log N does; prefer `log_normalizer`.
    """
    return torch.exp(log_normalizer(lam))


def moments(lam: Tensor) -> Tensor:
    """Second moments E[x_i^2] = d log N / d lam_i of the Bingham density with coefficients lam.

    Args:
        lam: as in `log_normalizer`.

    Returns:
        (..., 3) or (..., 4), like lam, in lam's dtype; for (..., 4) input they sum to 1, for
        (..., 3) the implicit zero coefficient has 1 - sum. No autograd through this function.
    """
    _check_lam(lam)
    work = _working_dtype(lam.dtype)
    with torch.no_grad():
        if lam.shape[-1] == 3:
            flat = lam.reshape(-1, 3).to(work)
            mom = _talbot(flat, need_moments=True)[1]
            return mom.reshape(lam.shape).to(lam.dtype)
        ordered, order = torch.sort(lam, dim=-1, descending=True)
        rest = (ordered[..., 1:] - ordered[..., :1]).reshape(-1, 3).to(work)
        m3 = _talbot(rest, need_moments=True)[1].reshape(*lam.shape[:-1], 3)
        m4 = torch.cat((1.0 - m3.sum(-1, keepdim=True), m3), dim=-1)
        return torch.empty_like(m4).scatter_(-1, order, m4).to(lam.dtype)


# -------------------------------------------------------------------------- likelihood (eq. 19)


def _quad_form(A: Tensor, q: Tensor) -> Tensor:
    return (q.unsqueeze(-2) @ A @ q.unsqueeze(-1)).squeeze(-1).squeeze(-1)


def log_prob(A: Tensor, q: Tensor) -> Tensor:
    """log p(q; A) = -q^T A q + l1 - log N(lam) w.r.t. the uniform probability measure on S^3.

    Args:
        A: (..., 4, 4) symmetric matrices (their symmetric part is used), finite, eigenvalue
            spread l4 - l1 <= MAX_DISPERSION.
        q: (..., 4) unit quaternions (x, y, z, w), batch shape broadcast against A's; not
            renormalised.

    Returns:
        (...,) log densities; exp integrates to 1 against the uniform probability measure
        (subtract `LOG_AREA_S3` for the surface measure). Invariant to q -> -q and A -> A + cI.
        Differentiable in A (through eigenvalues only, well defined at repeated ones) and q.
    """
    _check_A(A)
    _float_dtype(q, "q")
    if q.shape[-1] != 4:
        raise ValueError(f"q must have shape (..., 4), got {tuple(q.shape)}")
    _raise_first(~torch.isfinite(q).all(-1), "q has NaN or Inf")
    A = 0.5 * (A + A.mT)
    ev = _eigh(A, eigenvectors=False)[0]
    _check_spread(ev)
    lam = (ev[..., :1] - ev[..., [3, 2, 1]]).clamp_max(0.0)
    return ev[..., 0] - _quad_form(A, q) - _log_normalizer3(lam)


def nll(A: Tensor, q: Tensor) -> Tensor:
    """Negative log-likelihood q^T A q - l1 + log N(lam) (paper eq. 19 with log N and the sign).

    Args and returns as `log_prob` (this is its negative).
    """
    return -log_prob(A, q)


def _guess_rep(prediction: RotationPrediction) -> str:
    size = prediction.raw.shape[-1]
    names = [name for name, cls in sorted(HEADS.items()) if cls.out_dim == size]
    return names[0] if len(names) == 1 else f"<head with out_dim {size}>"


@config_target
class BinghamNLLLoss(nn.Module):
    """Mean Bingham negative log-likelihood `nll(prediction.A, batch["q"])` (paper eq. 19).

    The targets are batch["q"] (..., 4), or the quaternions of batch["R"] where the batch has no
    "q" (the sign does not matter: the likelihood is antipodally symmetric).

    Args:
        rep: the representation's name (the config's `rep.name`), optional. If given and that
            head defines no belief, construction fails with a ConfigValueError on key "rep".
    """

    def __init__(self, rep: str | None = None) -> None:
        super().__init__()
        if rep is not None and rep in HEADS and not HEADS[rep].defines_belief:
            raise ConfigValueError("rep", self._message(rep))
        self.rep = rep

    @staticmethod
    def _message(rep: str) -> str:
        return f"loss=bingham needs a head that defines a belief (rep=a); rep={rep} does not"

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        if prediction.A is None:
            raise ValueError(self._message(self.rep or _guess_rep(prediction)))
        q = batch["q"] if "q" in batch else rotmat_to_quat(batch["R"])
        return nll(prediction.A, q).mean()

    def extra_repr(self) -> str:
        return "" if self.rep is None else f"rep={self.rep!r}"


# ------------------------------------------------------------------------------------- sampling

_MAX_ROUNDS = 64


def _acg_b(shifted: Tensor, iterations: int = 40) -> Tensor:
    """b in [1, 4] with sum_i 1 / (b + 2 l_i) = 1 (Kent et al. 2013), by monotone Newton from 1.

    Any b in (0, 4] gives a valid envelope; this one maximises the acceptance rate.
    """
    b = torch.ones_like(shifted[..., 0])
    for _ in range(iterations):
        t = 1.0 / (b.unsqueeze(-1) + 2.0 * shifted)
        b = b + (t.sum(-1) - 1.0) / (t * t).sum(-1)
    return b.clamp(1.0, 4.0)


def _round_size(remaining: int, rate: float) -> int:
    """Proposals per matrix for the next round: enough for all `remaining` with high chance."""
    expect = remaining / rate
    return math.ceil(expect + 4.0 * math.sqrt(expect) + 16)


def sample(
    A: Tensor, n: int, generator: torch.Generator | None = None, max_rounds: int = _MAX_ROUNDS
) -> Tensor:
    """Draw n quaternions from each Bingham density p(x) ~ exp(-x^T A x).

    Kent, Ganeiber & Mardia (2013) rejection sampling with an angular central Gaussian envelope
    ACG(Omega), Omega = I + 2 (A - l1 I) / b, vectorised: each round draws proposals for the whole
    batch; accepted ones fill the output in order until every matrix has n.

    Args:
        A: (..., 4, 4) symmetric matrices (finite).
        n: samples per matrix, >= 0.
        generator: random source (its device must be A's).
        max_rounds: cap on the rounds; exceeding it raises RuntimeError (not expected: the
            acceptance rate is at least about 0.45 in 4 dimensions, its high-concentration
            limit, and each round is sized from the exact rate N |Omega|^(1/2) / M).

    Returns:
        (..., n, 4) unit quaternions (x, y, z, w), A's dtype and device; both signs occur
        (the density is antipodally symmetric).
    """
    _check_A(A)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if max_rounds < 1:
        raise ValueError(f"max_rounds must be >= 1, got {max_rounds}")
    batch_shape = A.shape[:-2]
    with torch.no_grad():
        ev, V = _eigh(A.reshape(-1, 4, 4))
        shifted = (ev - ev[:, :1]).clamp_min(0.0)  # (B, 4), first 0
        b = _acg_b(shifted.double()).to(A.dtype)
        scale = torch.rsqrt(1.0 + 2.0 * shifted / b.unsqueeze(-1))  # std of z in the eigenbasis
        log_m = -(4.0 - b) / 2.0 + 2.0 * torch.log(4.0 / b)  # envelope bound, log
        # exact acceptance rate N(-shifted) |Omega|^(1/2) / M, for sizing the rounds only
        log_rate = (
            log_normalizer(-shifted.clamp_max(MAX_DISPERSION)) - torch.log(scale).sum(-1) - log_m
        )
        rate = float(torch.exp(log_rate).clamp(0.05, 1.0).min()) if ev.shape[0] else 1.0
        rows = ev.shape[0]
        out = A.new_empty(rows, n, 4)
        filled = torch.zeros(rows, dtype=torch.long, device=A.device)
        row_index = torch.arange(rows, device=A.device)
        for _ in range(max_rounds):
            remaining = int((n - filled).max()) if rows else 0
            if remaining <= 0:
                break
            m = _round_size(remaining, rate)
            g = torch.randn(rows, m, 4, generator=generator, device=A.device, dtype=A.dtype)
            y = g * scale.unsqueeze(1)
            y = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)
            u = (y * y * shifted.unsqueeze(1)).sum(-1)  # y^T (A - l1 I) y in the eigenbasis
            log_ratio = -u + 2.0 * torch.log1p(2.0 * u / b.unsqueeze(-1)) - log_m.unsqueeze(-1)
            unif = torch.rand(rows, m, generator=generator, device=A.device, dtype=A.dtype)
            accept = torch.log(unif) < log_ratio
            position = filled.unsqueeze(-1) + torch.cumsum(accept, dim=-1) - 1
            keep = accept & (position < n)
            r_idx = row_index.unsqueeze(-1).expand(rows, m)[keep]
            out[r_idx, position[keep]] = y[keep]
            filled = (filled + accept.sum(-1)).clamp_max(n)
        else:
            if rows and int(filled.min()) < n:
                raise RuntimeError(
                    f"Bingham rejection sampling did not produce {n} samples in {max_rounds} rounds"
                )
        x = out @ V.mT  # back from the eigenbasis: x = V y
    return x.reshape(*batch_shape, n, 4)
