"""The Bingham normaliser N(lam) (paper eq. 14) and the likelihood (eq. 19).

Quaternions are scalar LAST. N is taken over the uniform probability measure on S^3 (package
docstring, `rotlearn.bingham`), computed by Talbot inversion of its Laplace transform on a fixed
node set, batched on any device; its gradient (the second moments) comes from the same nodes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from rotlearn.bingham.descriptors import (
    MAX_DISPERSION,
    _check_A,
    _check_lam,
    _check_q,
    _check_spread,
    _decompose,
    _symmetric,
    dispersion_from_eigenvalues,
)
from rotlearn.geometry.autocast import float32_under_autocast, valued_as
from rotlearn.geometry.shapes import promoted

__all__ = ["log_normalizer", "log_prob", "moments", "nll", "normalizer"]

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
    """log N(lam) for (B, 3) valid coefficients; backward multiplies by the saved moments.

    New-style Function (`setup_context`, an explicit `vmap` rule: the vmapped dimension joins the
    rows), so torch.func and torch.compile trace it. `need_moments`: whether a gradient will be
    asked for (the moments are then computed with the values, from the same nodes).
    """

    @staticmethod
    def forward(lam: Tensor, need_moments: bool) -> tuple[Tensor, Tensor]:
        log_n, mom = _talbot(lam, need_moments=need_moments)
        return log_n, mom if mom is not None else lam.new_empty(0)

    @staticmethod
    def setup_context(ctx, inputs: tuple, output: tuple[Tensor, Tensor]) -> None:
        ctx.mark_non_differentiable(output[1])
        ctx.save_for_backward(output[1])

    @staticmethod
    def vmap(info, in_dims: tuple, lam: Tensor, need_moments: bool):
        lam = (
            lam.expand(info.batch_size, *lam.shape)
            if in_dims[0] is None
            else lam.movedim(in_dims[0], 0)
        )
        n = lam.shape[0]
        log_n, mom = _LogNormalizer.apply(lam.reshape(-1, 3), need_moments)
        mom = mom.unflatten(0, (n, -1)) if mom.numel() else mom.expand(n, 0)
        return (log_n.unflatten(0, (n, -1)), mom), (0, 0)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor, _grad_mom: Tensor | None = None) -> tuple[Tensor, None]:
        (mom,) = ctx.saved_tensors
        return grad.unsqueeze(-1) * mom, None


def _working_dtype(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype in _HALF_NODES else torch.float32


def _log_normalizer3(lam: Tensor) -> Tensor:
    """`log_normalizer` of (..., 3) coefficients (autograd-aware), each taken within the
    supported [-MAX_DISPERSION, 0]: the identity on checked ones (values and gradients), the
    bound beyond it. Past the bound the normaliser no longer rewards concentration while the fit
    term q^T A q - l1 still grows with it, so a likelihood loss of unchecked beliefs stops
    sharpening such a belief instead of failing the run."""
    work = _working_dtype(lam.dtype)
    flat = lam.reshape(-1, 3).to(work).clamp(-MAX_DISPERSION, 0.0)
    if flat.shape[0] == 0:
        return lam.new_zeros(lam.shape[:-1])
    need_moments = torch.is_grad_enabled() and flat.requires_grad
    log_n, _ = _LogNormalizer.apply(flat, need_moments)
    return log_n.reshape(lam.shape[:-1]).to(lam.dtype)


def log_normalizer(lam: Tensor, check: bool = True) -> Tensor:
    """log N(lam), N = E_mu[exp(sum_i lam_i x_i^2)] over the uniform probability measure on S^3.

    N is the normaliser of paper eq. (14) (Talbot inversion, see the module docstring).

    Args:
        lam: (..., 3) dispersion coefficients in [-MAX_DISPERSION, 0] (any order; the fourth
            coefficient is 0), or (..., 4) any real coefficients with spread
            max - min <= MAX_DISPERSION, for which N(lam + c) = e^c N(lam).
        check: validate lam first (one host sync). False, for a loss's hot path: no check
            and no sync; NaN/Inf propagate, and a coefficient beyond the range is taken at its
            bound (-MAX_DISPERSION, or 0 for a positive (..., 3) one).

    Returns:
        (...,) log N in lam's dtype; N(0) = 1. Differentiable once: the gradient is the vector
        of second moments E[x_i^2] (`moments`).

    Raises:
        ValueError: (with `check`) NaN/Inf, a positive (..., 3) coefficient, or one out of
            range; the message names the first offending batch index.
    """
    if check:
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


def _fit(S: Tensor, q: Tensor, l1: Tensor, mode: Tensor) -> Tensor:
    """The fit term q^T A q - l1 >= 0 of eq. (19), (...,), with S the symmetric part of A, l1
    its smallest eigenvalue and `mode` the unit eigenvector of l1 (both from the solver).

    Its value is taken in float64 as q^T (S - r I) q, with r = mode^T S mode / |mode|^2 the
    Rayleigh quotient of the solver's mode: in S's dtype, q^T S q and l1 are each of the size
    of A's entries and cancel, so float32 would leave some 1e-7 (l4 - l1) nats of rounding
    (0.16 nats at a spread of 1e6, ~10 at 1e8); r is exact to second order in the mode's
    error. The gradient is the exact one of q^T S q - l1 |q|^2 (for A: q q^T - v1 v1^T; for q:
    2 (S - l1 I) q), taken in S's dtype: the function the value is, also off the unit sphere
    (with - l1 alone, the q-gradient had a radial part 2 l1 q that the value lacks, which moved
    under A + cI).
    """
    fit = _quad_form(S, q) - l1 * (q * q).sum(-1)
    with torch.no_grad():
        S64, m64 = S.double(), mode.double()
        r = _quad_form(S64, m64) / (m64 * m64).sum(-1)
        eye = torch.eye(4, dtype=torch.float64, device=S.device)
        exact = _quad_form(S64 - r[..., None, None] * eye, q.double()).clamp_min(0.0)
    return valued_as(fit, exact)


@float32_under_autocast
def log_prob(A: Tensor, q: Tensor, check: bool = True) -> Tensor:
    """log p(q; A) = -q^T A q + l1 - log N(lam) w.r.t. the uniform probability measure on S^3.

    Args:
        A: (..., 4, 4) symmetric matrices (their symmetric part is used), finite, eigenvalue
            spread l4 - l1 <= MAX_DISPERSION.
        q: (..., 4) unit quaternions (x, y, z, w), batch shape broadcast against A's; not
            renormalised.
        check: validate the values of A and q first (finite, the spread in range: host
            syncs). False, for a training loss's hot path (`rotlearn.losses.BinghamNLLLoss`):
            dtypes and shapes only, no sync; NaN/Inf propagate (training's finiteness guard,
            `rotlearn.lit.finite`, names them), and a dispersion beyond MAX_DISPERSION is
            taken at that bound (the loss then stops sharpening the belief).

    Returns:
        (...,) log densities, in the promoted dtype of A and q (float32 with float64 is
        float64); exp integrates to 1 against the uniform probability measure
        (subtract `LOG_AREA_S3` for the surface measure). Invariant to q -> -q and A -> A + cI.
        Differentiable in A (through eigenvalues only, well defined at repeated ones) and q.
        Under autocast computed in float32 and returned in float32. The fit term q^T A q - l1
        is valued in float64 (`_fit`), so a float32 result stays within 1e-3 nats of the
        float64 one of the same A even for the sharpest supported beliefs.

    Raises:
        TypeError: A or q not floating.
        ValueError: a shape; with `check`, also NaN/Inf in A or q or a spread beyond
            MAX_DISPERSION, naming the first batch index.
    """
    _check_A(A, values=check)
    _check_q(q, values=check)
    A, q = promoted(A, q)
    ev, mode = _decompose(A)
    if check:
        _check_spread(ev)
    lam = dispersion_from_eigenvalues(ev)
    return -_fit(_symmetric(A).to(A.dtype), q, ev[..., 0], mode) - _log_normalizer3(lam)


def nll(A: Tensor, q: Tensor, check: bool = True) -> Tensor:
    """Negative log-likelihood q^T A q - l1 + log N(lam) (paper eq. 19 with log N and the sign).

    Args and returns as `log_prob` (this is its negative).
    """
    return -log_prob(A, q, check=check)
