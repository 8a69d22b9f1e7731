"""Batched eigensolver for symmetric 4x4 matrices: cyclic Jacobi, vectorised over the batch.

(One module of about 480 lines on purpose: the Jacobi forward, the sorting network, the input
checks and the analytic backward share one memory layout, rows of a (k, B) tensor, which splitting
them would spread over several modules.)

`sym4_eigh_min` returns the four eigenvalues (ascending) and the unit eigenvector of the smallest
one with canonical sign, which is what the A head needs (paper eqs. 9, 11), with an analytic
backward that stays finite where eigenvalues coincide (torch.linalg.eigh's is NaN/Inf there).

Layout. The batch is flattened to B matrices; each of the 10 entries of the upper triangle of A,
and each of the 16 entries of the eigenvector matrix V, is a row of a (rows, B) tensor, so every
step is an elementwise operation on a few contiguous rows: no Python loop over samples, no
small-matrix kernels, no host synchronisation, the same code on CPU and CUDA.

Algorithm. A (its upper triangle) is scaled by a power of two so that its largest entry lies in
[0.5, 1) (exact; squares then neither overflow nor underflow for any finite input). Then a fixed
number of Jacobi *rounds*: a round applies two rotations on disjoint index pairs at once, cycling
through the three perfect matchings {01, 23}, {02, 13}, {03, 12} (three rounds = one cyclic sweep
over all six pairs). Each rotation zeroes its off-diagonal entry with the stable small-angle
formula (|angle| <= 45 degrees); V accumulates the rotations and is orthogonal to working
precision. A 3-layer sorting network then orders the eigenvalues, moving the columns of V along.

Round counts, chosen by measurement (maximum over 10^6 Gaussian matrices, and the cases of
tests/test_eigen4.py): float32 needs 12 rounds (11 leave residuals |A q - l1 q| up to
4e-6 ||A||, 4x eigh's), float64 14 (13 leave 5e-14 ||A||).

Below EIGH_BELOW matrices (`method="auto"`) the forward is torch.linalg.eigh instead: the Jacobi
loop launches ~450 elementwise kernels per call whatever the batch size, a fixed cost that only
pays off for large batches (the crossover is measured by `bench/rep_layers.py --crossover`).
That path (`_Sym4EighMinLapack`) keeps eigh's (B, 4, 4) layout and has its own short backward of
batched products; the formula and the gap clamp are those of the Jacobi path's backward.

Measured accuracy (max over 20000 matrices per case: Gaussian, I - q q^T with and without 1e-3
noise, Wahba data matrices (paper eq. 5), clustered -sum q_k q_k^T, Gaussian scaled by 1e-6 and
1e6; against float64 eigh of the same matrices; angle of R(q) over spectra with
l2 - l1 >= 0.01 (l4 - l1)):
    float32: angle <= 3e-4 deg, eigenvalues within 4e-7 ||A||_2, |A q - l1 q| <= 6e-7 ||A||_2
             (float32 eigh: 1.1e-3 deg, 1.1e-6, 1.1e-6);
    float64: angle <= 3e-12 deg, eigenvalues within 3e-15 ||A||_2, |A q - l1 q| <= 1.3e-15 ||A||_2
             (float64 eigh's residual: up to 2.6e-15).
With l2 - l1 = 1e-6 (l4 - l1) the residual bound still holds; q itself is then determined only
up to ~eps / 1e-6 (float32: 10 deg for this solver, 27 deg for eigh).

Kernels. Only ATen's own elementwise kernels: no op that ATen hands to MKL's vector math library
(VML: sqrt, exp, log, ... of contiguous CPU tensors). VML's first call in a process races between
intra-op threads on Intel CPUs and returned wrong square roots for one thread's share of the batch
(issue 27: 0.1 degree eigenvectors for half the batch in about 4 % of fresh processes after a
LAPACK call); the root below is x * rsqrt(x). tests/geometry/test_eigen4_first_call.py guards it.

Speed: see `make bench` (bench/a_layer.py, bench/rep_layers.py; results in bench/results and
docs/results.md). The cost is ~20 elementwise kernels per round on (2..8, B) rows, about 70 row
passes per round and 850 per matrix, bound by memory traffic and per-kernel overhead (the
eigenvector rotations are half of it); torch.compile of the loop (inductor, CPU) was slower than
eager, so it is not used.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from rotlearn.errors import batch_index
from rotlearn.geometry.autocast import float32_under_autocast

__all__ = [
    "DEFAULT_GAP_EPS",
    "DEFAULT_ROUNDS",
    "EIGH_BELOW",
    "METHODS",
    "sym4_eigh_min",
    "validate_sym4",
]

DEFAULT_GAP_EPS = 1e-6
DEFAULT_ROUNDS = {torch.float32: 12, torch.float64: 14}
METHODS = ("auto", "jacobi", "eigh")  # sym4_eigh_min's forward (also the A head's rep.solver)
# method="auto": the torch.linalg.eigh forward below this many matrices, Jacobi from there on.
# Measured by `bench/rep_layers.py --crossover` (the batch size from which Jacobi's forward +
# backward is faster than eigh's; bench/results/solver_crossover.json).
EIGH_BELOW = 1024
# Matrices per pass on CPU (`_chunk_size`): 16384 per thread, at least 32768; the working set
# (~2 MB per 16384 in float32) then stays in the last-level cache. Measured: 32768 best with 2
# threads (an earlier, quiet session) and, with 1 thread, 32768 took 0.90-0.94x the time of 16384
# (three interleaved runs, issue 16; 65536: 1.10x). On CUDA the batch is not split.
_CHUNK_PER_THREAD = 16384
_CHUNK_MIN = 32768


def _chunk_size(batch: int, device: torch.device) -> int:
    """Matrices per Jacobi pass: the whole batch on CUDA, cache-sized chunks on CPU (>= 1)."""
    if device.type != "cpu":
        return max(batch, 1)
    return max(_CHUNK_MIN, _CHUNK_PER_THREAD * torch.get_num_threads())


# Rows of the working tensor S (10, B): the diagonal d0..d3, then the off-diagonal entries in
# row-major upper-triangle order o01 o02 o03 o12 o13 o23 (positions 4..9).
_UPPER = (0, 5, 10, 15, 1, 2, 3, 6, 7, 11)  # flat (row-major) index in A of each row of S
_LOWER = (0, 5, 10, 15, 4, 8, 12, 9, 13, 14)  # the mirrored entries (validate_sym4)


@functools.lru_cache(maxsize=16)
def _constants(dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
    """Small constant tensors, made once per dtype and device (never written to)."""
    return {
        "tiny": torch.tensor(torch.finfo(dtype).tiny, dtype=dtype, device=device),
        "zero": torch.zeros((), dtype=dtype, device=device),
        "one": torch.ones((), dtype=dtype, device=device),
        "sign_weights": torch.tensor([[8.0, 4.0, 2.0, 16.0]], dtype=dtype, device=device),
        "upper": torch.tensor(_UPPER, device=device),
        "lower": torch.tensor(_LOWER, device=device),
        "first_entries": torch.tensor([0, 12, 6, 18, 1, 13, 5, 17], device=device),
    }


def _rotate(p: Tensor, q: Tensor, c: Tensor, t: Tensor) -> None:
    """In place: (p, q) <- (c (p - t q), c (q + t p)), a plane rotation with tan = t, cos = c."""
    u = torch.addcmul(p, q, t, value=-1.0)
    q.addcmul_(p, t).mul_(c)
    torch.mul(u, c, out=p)


def _jacobi(S: Tensor, W: Tensor, rounds: int) -> None:
    """Diagonalise in place.

    S: (10, B) the entries of A (rows as `_UPPER`); on return its first 4 rows are the eigenvalues
    and the rest is small but stale (the last round does not update the off-diagonal entries,
    which nothing reads after it). W: (4 columns, 5 rows, B), zero on entry; on return W[:, :4]
    holds the eigenvectors as columns (W[j, :4] is the eigenvector of eigenvalue S[j]).
    """
    B = S.shape[1]
    D, off = S[:4], S[4:]
    V = W[:, :4]
    const = _constants(S.dtype, S.device)
    tiny, zero, one = const["tiny"], const["zero"], const["one"]
    tan = torch.empty(2, B, dtype=S.dtype, device=S.device)  # tan and cos of the two rotations
    cos = torch.empty(2, B, dtype=S.dtype, device=S.device)
    c0, c1, t0, t1 = cos[0], cos[1], tan[0], tan[1]
    c01, t01 = cos.unsqueeze(1), tan.unsqueeze(1)
    # Views for the three matchings: app, aqq, apq (2, B) for the pairs (p1, q1), (p2, q2) of the
    # round; the 2x2 block coupling the pairs, as rows p1 / q1 and columns p2 / q2 (2, B each).
    matchings = (
        # pairs (0, 1), (2, 3)
        (D[0::2], D[1::2], off[0::5], off[1:3], off[3:5], off[1:4:2], off[2:5:2]),
        # pairs (0, 2), (1, 3)
        (D[0:2], D[2:4], off[1::3], off[0:3:2], off[3:6:2], off[0:4:3], off[2:6:3]),
        # pairs (0, 3), (1, 2): the q-diagonal (d3, d2) is not a strided view, see below
        (D[0:2], None, off[2:4], off[0:2], off[4:6], off[0:5:4], off[1:6:4]),
    )
    d3, d2 = D[3], D[2]
    apq2_0, apq2_1 = off[2], off[3]
    V_flat = W.view(20, B)  # row 5 j + i holds V[j, i] (column j, row i); rows 5 j + 4: l_j
    # After the first round (pairs (0,1), (2,3)) from V = I: V[p, p] = V[q, q] = c,
    # V[p, q] = -c t, V[q, p] = c t; in the order of torch.cat((c, c, -ct, ct)) below.
    first_entries = const["first_entries"]
    vp = (V[0::2], V[0:2])  # eigenvector columns (p1, p2) and (q1, q2) of matchings 0 and 1
    vq = (V[1::2], V[2:4])
    v0, v1, v2, v3 = V.unbind(0)
    for k in range(rounds):
        m = k % 3
        app, aqq, apq, xp1, xq1, xp2, xq2 = matchings[m]
        if m == 2:
            aqq = torch.stack((d3, d2))
        d = aqq - app
        # r = sqrt(tiny + d^2 + 4 apq^2) as x * rsqrt(x): torch.sqrt of a contiguous CPU
        # tensor calls MKL VML (vsSqrt) from every intra-op thread, and VML's first call in a
        # process races on Intel CPUs (wrong roots for part of the batch, issue 27). rsqrt and
        # mul are ATen's own kernels, bit-identical for any thread count.
        r = torch.addcmul(tiny, d, d).addcmul_(apq, apq, value=4.0)
        r = r.mul_(r.rsqrt())
        den = torch.copysign(r, d).add_(d)  # sign(d) (|d| + sqrt(d^2 + 4 apq^2)), never 0
        t = torch.addcdiv(zero, apq, den, value=2.0, out=tan)  # |t| <= 1
        c = torch.addcmul(one, t, t, out=cos).rsqrt_()
        app.addcmul_(t, apq, value=-1.0)
        if m == 2:
            d3.addcmul_(t0, apq2_0)
            d2.addcmul_(t1, apq2_1)
        else:
            aqq.addcmul_(t, apq)
        if k < rounds - 1:  # the off-diagonal entries are not read after the last round
            apq.zero_()
            # The coupling block: rows by the first rotation, columns by the second.
            _rotate(xp1, xq1, c0, t0)
            _rotate(xp2, xq2, c1, t1)
        # Eigenvector columns.
        if k == 0:  # V = I: V becomes the rotation itself, written entry by entry
            ct = c * t
            V_flat.index_copy_(0, first_entries, torch.cat((c, c, ct.neg(), ct)))
        elif m < 2:
            _rotate(vp[m], vq[m], c01, t01)
        else:
            _rotate(v0, v3, c0, t0)
            _rotate(v1, v2, c1, t1)
    W[:, 4] = D


def _sort(W: Tensor) -> None:
    """Sort the columns of W (4 columns, 5 rows, B) in place by row 4 (eigenvalues), ascending.

    A sorting network (0,1)(2,3) | (0,2)(1,3) | (1,2); each compare-exchange is a blend with a 0/1
    mask, so whole columns (eigenvector and eigenvalue) move together. Ties keep their order.
    """
    for a, b in ((W[0::2], W[1::2]), (W[0:2], W[2:4]), (W[1], W[2])):
        swap = torch.gt(a[..., 4:5, :], b[..., 4:5, :]).to(W.dtype)
        diff = b - a
        a.addcmul_(swap, diff)
        b.addcmul_(swap, diff, value=-1.0)


def _canonical_sign(q: Tensor) -> Tensor:
    """The sign making q canonical, exactly as `rotlearn.geometry.quat_canonical` picks it.

    q is (4, B) with rows x, y, z, w. quat_canonical makes the first nonzero component in the
    order w, x, y, z positive (+1 for the zero vector). The same rule as one weighted sum:
    sign(2 (8 sign w + 4 sign x + 2 sign y + sign z) + 1) (each weight exceeds the sum of the
    later ones; the +1 maps the all-zero key to +1).
    """
    const = _constants(q.dtype, q.device)
    key = torch.addmm(const["one"], const["sign_weights"], torch.sign(q))
    return torch.sign(key)  # (1, B)


def validate_sym4(A: Tensor, rtol: float = 1e-6) -> None:
    """Raise ValueError unless A is a batch of finite symmetric 4x4 float32/float64 matrices.

    Checks, in this order: shape (..., 4, 4) and dtype; then, per matrix, NaN or Inf entries and
    asymmetry max|A - A^T| > rtol * max|A|. The message names the problem(s) of the FIRST offending
    matrix (row-major order of the batch) and its batch index. Synchronises with the device.

    Args:
        A: the tensor to check.
        rtol: allowed asymmetry relative to the largest entry of the same matrix.

    Raises:
        ValueError: as above.
    """
    if A.dim() < 2 or A.shape[-2:] != (4, 4):
        raise ValueError(f"expected a tensor of shape (..., 4, 4), got {tuple(A.shape)}")
    if A.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"expected float32 or float64, got {A.dtype}")
    batch = A.shape[:-2]
    flat = A.reshape(-1, 16)
    if flat.shape[0] == 0:
        return
    # Entry-major layout (rows = entries, reductions over rows are fast): the upper and the
    # mirrored lower triangle.
    const = _constants(A.dtype, A.device)
    upper = flat.t().index_select(0, const["upper"])
    lower = flat.t().index_select(0, const["lower"])
    finite = torch.isfinite(upper).all(0) & torch.isfinite(lower).all(0)
    asym = (upper - lower).abs_().amax(0)
    scale = torch.maximum(upper.abs().amax(0), lower.abs().amax(0))
    nonsym = asym > rtol * scale  # False where NaN/Inf made the comparison meaningless
    bad = nonsym | ~finite
    if not bool(bad.any()):
        return
    first = int(torch.argmax(bad.to(torch.uint8)))
    problems = []
    if bool(torch.isnan(flat[first]).any()):
        problems.append("NaN entries")
    if bool(torch.isinf(flat[first]).any()):
        problems.append("Inf entries")
    if bool(nonsym[first]):
        problems.append(
            f"not symmetric: max|A - A^T| = {float(asym[first]):.3g} > {rtol:g} * max|A| "
            f"= {rtol * float(scale[first]):.3g}"
        )
    raise ValueError(
        f"A at batch index {batch_index(first, batch)} (first of {int(bad.sum())} bad "
        f"matrices of {flat.shape[0]}): {'; '.join(problems)}"
    )


def _solve(A: Tensor, W: Tensor, rounds: int) -> None:
    """Eigen-decompose A (b, 4, 4) into W (4 columns, 5 rows, b), zero on entry.

    On return column j of W holds (v_j, l_j), sorted by l_j ascending, v_0 with canonical sign.
    """
    b = A.shape[0]
    S = A.reshape(b, 16).t().index_select(0, _constants(A.dtype, A.device)["upper"])
    # Scale by a power of two 2^e >= max |entry| (exact; 1 for the zero matrix).
    _, e = torch.frexp(S.abs().amax(0))
    e = e.to(A.dtype)
    S.mul_(torch.exp2(e.neg()))
    _jacobi(S, W, rounds)
    _sort(W)
    W[:, 4].mul_(torch.exp2(e))
    W[0, :4].mul_(_canonical_sign(W[0, :4]))


class _Sym4EighMin(torch.autograd.Function):
    """(B, 4, 4) -> eigenvalues (B, 4) ascending, minimum eigenvector q (B, 4), w >= 0, by the
    Jacobi solver (the third output, the (4, 5, B) buffer W, is for the backward only).

    Backward, with l1 <= ... <= l4 and orthonormal eigenvectors v1 = q, v2, v3, v4:
        grad_A = sym(-u q^T + sum_i g_li v_i v_i^T),   u = sum_{i>=2} v_i (v_i . g_q) / gap_i,
        gap_i = max(l_i - l1, gap_eps ||A||_2)  (gap_i = 1 for A = 0),   sym(X) = (X + X^T) / 2.
    The first term is dq = -(A - l1 I)^+ dA q (paper eq. 9), the second dl_i = v_i^T dA v_i.
    Only the projector onto each eigenspace above l1 enters u, so repeated l2 = l3 = l4 is
    harmless; the clamp keeps l1 = l2 (and A = cI) finite. grad_A is exactly symmetric: the
    gradient along symmetric perturbations, so that a mirrored A (a_from_vec) gets the right
    gradient in both triangles.

    New-style Function (forward without ctx, `setup_context`, an explicit `vmap` rule), so
    torch.func (vmap of grad) and torch.compile trace it.
    """

    @staticmethod
    def forward(A: Tensor, gap_eps: float, rounds: int) -> tuple[Tensor, ...]:
        B = A.shape[0]
        W = torch.zeros(4, 5, B, dtype=A.dtype, device=A.device)  # columns (v_i, l_i)
        chunk = _chunk_size(B, A.device)
        for start in range(0, B, chunk):
            _solve(A[start : start + chunk], W[..., start : start + chunk], rounds)
        # (B, 4) views of W's rows: no copy, and q.unbind(-1) gives contiguous components. W
        # itself is the third output (not differentiable), for setup_context to save.
        return W[:, 4].t(), W[0, :4].t(), W

    @staticmethod
    def setup_context(ctx, inputs: tuple, output: tuple[Tensor, ...]) -> None:
        W = output[2]
        ctx.mark_non_differentiable(W)
        ctx.save_for_backward(W)
        ctx.gap_eps = inputs[1]
        ctx.set_materialize_grads(False)

    @staticmethod
    def vmap(info, in_dims: tuple, A: Tensor, gap_eps: float, rounds: int):
        """torch.func.vmap rule: the vmapped dimension joins the batch of matrices (one call)."""
        A = _vmap_batch_first(info, in_dims, A)
        eigenvalues, q, W = _Sym4EighMin.apply(A.reshape(-1, 4, 4), gap_eps, rounds)
        split = (A.shape[0], -1)
        outputs = (eigenvalues.unflatten(0, split), q.unflatten(0, split), W.unflatten(-1, split))
        return outputs, (0, 0, 2)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_l: Tensor | None, grad_q: Tensor | None, _grad_W: None = None):
        (W,) = ctx.saved_tensors
        V, lam = W[:, :4], W[:, 4]  # (4 columns, 4 rows, B), (4, B)
        if grad_q is None and grad_l is None:
            return None, None, None, None
        G = None  # the gradient before symmetrisation, (4, 4, B)
        if grad_q is not None:
            norm = lam.abs().amax(0)  # ||A||_2
            floor = torch.eq(norm, 0).to(W.dtype).add_(norm, alpha=ctx.gap_eps)  # 1 for A = 0
            gaps = torch.maximum(lam[1:] - lam[0], floor)  # (3, B)
            coef = (V[1:] * grad_q.t()).sum(1).div_(gaps)  # (v_i . g_q) / gap_i, (3, B)
            u = (V[1:] * coef.unsqueeze(1)).sum(0)  # (A - l1 I)^+ g_q, (4, B)
            G = u.unsqueeze(1) * V[0].neg().unsqueeze(0)  # -u q^T
        if grad_l is not None:
            Vg = V * grad_l.t().unsqueeze(1)  # g_i v_i
            # Out of place: addcmul_ has no torch.func.vmap batching rule (per-sample fallback).
            if G is None:
                G = Vg[0].unsqueeze(1) * V[0].unsqueeze(0)
            else:
                G = torch.addcmul(G, Vg[0].unsqueeze(1), V[0].unsqueeze(0))
            for i in range(1, 4):
                G = torch.addcmul(G, Vg[i].unsqueeze(1), V[i].unsqueeze(0))  # + g_i v_i v_i^T
        # (G + G^T) / 2: exactly symmetric.
        G = torch.add(G, G.transpose(0, 1)).mul_(0.5)
        return G.permute(2, 0, 1), None, None


def _vmap_batch_first(info, in_dims: tuple, A: Tensor) -> Tensor:
    """A with the vmapped dimension first (expanded when A is not vmapped), for a vmap rule."""
    if in_dims[0] is None:
        return A.expand(info.batch_size, *A.shape)
    return A.movedim(in_dims[0], 0)


class _Sym4EighMinLapack(torch.autograd.Function):
    """As `_Sym4EighMin` (same outputs, same backward formula and gap clamp), forward by
    torch.linalg.eigh: the path of small batches (`method="eigh"`, or "auto" below EIGH_BELOW).

    Everything stays in eigh's (B, 4, 4) layout (columns of V are the eigenvectors): the forward
    only fixes the sign of q, the backward is a handful of batched products, so the fixed cost
    per call stays close to that of eigh with plain autograd (issue 16: never slower at any B).
    """

    @staticmethod
    def forward(A: Tensor, gap_eps: float) -> tuple[Tensor, ...]:
        eigenvalues, V = torch.linalg.eigh(A, UPLO="U")
        q = V[..., 0]  # (B, 4) view: canonical sign in place, so V stays the saved basis
        q.mul_(_canonical_sign(q.t()).t())
        return eigenvalues, q, V

    @staticmethod
    def setup_context(ctx, inputs: tuple, output: tuple[Tensor, ...]) -> None:
        ctx.mark_non_differentiable(output[2])
        ctx.save_for_backward(output[0], output[2])
        ctx.gap_eps = inputs[1]
        ctx.set_materialize_grads(False)

    @staticmethod
    def vmap(info, in_dims: tuple, A: Tensor, gap_eps: float):
        """torch.func.vmap rule: the vmapped dimension joins the batch of matrices (one call)."""
        A = _vmap_batch_first(info, in_dims, A)
        outputs = _Sym4EighMinLapack.apply(A.reshape(-1, 4, 4), gap_eps)
        split = (A.shape[0], -1)
        return tuple(x.unflatten(0, split) for x in outputs), (0, 0, 0)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_l: Tensor | None, grad_q: Tensor | None, _grad_V: None = None):
        lam, V = ctx.saved_tensors  # (B, 4), (B, 4, 4)
        if grad_q is None and grad_l is None:
            return None, None
        G = None  # the gradient before symmetrisation, (B, 4, 4); all out of place (vmap)
        if grad_q is not None:
            norm = lam.abs().amax(-1, keepdim=True)  # ||A||_2, (B, 1)
            floor = torch.add(torch.eq(norm, 0).to(V.dtype), norm, alpha=ctx.gap_eps)
            gaps = torch.maximum(lam[:, 1:] - lam[:, :1], floor)  # (B, 3)
            upper = V[..., 1:]  # v2, v3, v4 as columns, (B, 4, 3)
            coef = torch.matmul(grad_q.unsqueeze(-2), upper).div(gaps.unsqueeze(-2))  # (B, 1, 3)
            u = torch.matmul(upper, coef.mT)  # (A - l1 I)^+ g_q, (B, 4, 1)
            G = u * V[..., 0].neg().unsqueeze(-2)  # -u q^T
        if grad_l is not None:
            Vg = V * grad_l.unsqueeze(-2)  # columns g_i v_i
            G = torch.matmul(Vg, V.mT) if G is None else torch.baddbmm(G, Vg, V.mT)
        return torch.add(G, G.mT).mul(0.5), None  # exactly symmetric


@float32_under_autocast
def sym4_eigh_min(
    A: Tensor,
    *,
    gap_eps: float = DEFAULT_GAP_EPS,
    check: bool = True,
    rounds: int | None = None,
    method: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Eigenvalues and minimum eigenvector of symmetric 4x4 matrices (a fast `eigh` for the A head).

    Differentiable: the analytic backward of `_Sym4EighMin` (`_Sym4EighMinLapack` on the eigh
    path; paper eq. 9 for q, v_i^T dA v_i for the eigenvalues), finite for repeated eigenvalues.
    Device-agnostic; no host synchronisation when `check=False`. Every output element depends on
    its own matrix only. Works under
    torch.func.vmap/grad and torch.compile (with `check=False`). Under autocast (CPU or CUDA)
    float16/bfloat16 input is cast to float32 and the solver runs in float32 with autocast off.

    Args:
        A: (..., 4, 4) symmetric matrices, float32 or float64, any batch shape (also () and
            empty). Only the upper triangle is read (as torch.linalg.eigh(A, UPLO="U")); the
            gradient returned for A is symmetric (see `_Sym4EighMin`).
        gap_eps: lower bound on the eigenvalue gaps l_i - l1 (i >= 2) in the backward, RELATIVE to
            the spectral norm ||A||_2 = max_i |l_i|: gaps below gap_eps * ||A||_2 are replaced by
            it. With the default 1e-6 the q-gradient never exceeds about |grad_q| /
            (1e-6 ||A||_2), and it is exact wherever l2 - l1 >= 1e-6 ||A||_2 (in float32 that is
            about 10 ulps, below which q is not determined by A anyway). Repeated upper eigenvalues
            (l2 = l3, l2 = l3 = l4) need no clamp.
        check: run `validate_sym4` first (NaN/Inf entries, asymmetry beyond 1e-6 relative: raise
            ValueError with the first offending batch index). This synchronises with the device;
            pass False in training loops. With False there is no check at all.
        rounds: Jacobi rounds (two disjoint rotations each; 3 rounds = 1 sweep). Default: 12 for
            float32, 14 for float64 (`DEFAULT_ROUNDS`), measured to converge.
        method: "jacobi" (this module's solver), "eigh" (torch.linalg.eigh forward, this
            module's backward) or "auto": eigh below `EIGH_BELOW` matrices, where its lower
            per-call overhead wins, jacobi from there on. With "eigh" and check=False, NaN/Inf
            input makes torch.linalg.eigh raise; jacobi propagates NaN.

    Returns:
        eigenvalues: (..., 4), ascending, in A's dtype (float32 under autocast).
        q: (..., 4), the unit eigenvector of the smallest eigenvalue as a quaternion (x, y, z, w),
            sign exactly as `quat_canonical` (w > 0; ties by the first nonzero of w, x, y, z).
            Both are kept by the backward (q is a strided view of the saved eigenvectors).

    Determinism: each output element is a function of its own matrix, the dtype, the device and
    the solver alone. On the CPU both solvers give bit-identical results across runs and
    processes (the first call included), thread counts and batch splits (any slice, chunk or
    single matrix of a batch; tests/geometry/test_eigen4_first_call.py). With `method="auto"`
    the solver itself depends on the batch size (eigh below `EIGH_BELOW`), so the same matrix in
    batches of different sizes can differ in the last bits (within the accuracy below): pass
    "jacobi" or "eigh" for results that do not depend on the batch. CPU and CUDA results agree
    to the accuracy below, not bit for bit.

    Accuracy (against float64 torch.linalg.eigh; guaranteed by tests/test_eigen4.py, measured
    values in the module docstring): float32: rotation angle of q <= 1e-3 degrees where
    l2 - l1 >= 0.01 (l4 - l1), eigenvalues within 1e-6 ||A||_2, |A q - l1 q| <= 2e-6 ||A||_2;
    float64: angle <= 1e-9 degrees, eigenvalues and residual within 1e-14 ||A||_2; in every case
    no worse than torch.linalg.eigh in the same dtype.

    Raises:
        ValueError: wrong shape, dtype, method or rounds (always); NaN/Inf or asymmetric entries
            (only with `check=True`).
    """
    if A.dim() < 2 or A.shape[-2:] != (4, 4):
        raise ValueError(f"expected a tensor of shape (..., 4, 4), got {tuple(A.shape)}")
    if A.dtype not in DEFAULT_ROUNDS:
        raise ValueError(f"expected float32 or float64, got {A.dtype}")
    if check:
        validate_sym4(A)
    if rounds is not None and rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    batch = A.shape[:-2]
    if method not in METHODS:
        raise ValueError(f"method must be 'auto', 'jacobi' or 'eigh', got {method!r}")
    A = A.reshape(-1, 4, 4)
    use_eigh = method == "eigh" or (method == "auto" and A.shape[0] < EIGH_BELOW)
    n_rounds = DEFAULT_ROUNDS[A.dtype] if rounds is None else int(rounds)
    if use_eigh:
        eigenvalues, q, _ = _Sym4EighMinLapack.apply(A, float(gap_eps))
    else:
        eigenvalues, q, _ = _Sym4EighMin.apply(A, float(gap_eps), n_rounds)
    return eigenvalues.reshape(*batch, 4), q.reshape(*batch, 4)
