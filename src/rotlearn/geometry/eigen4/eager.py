"""The eager paths of the A layer's eigensolver: PyTorch tensor operations only.

The fallback where no fused kernel runs (a CPU without a C compiler, CUDA without Triton) and the
reference the fused kernels are tested against. Three functions, each in the layout of the op
(`rotlearn.geometry.eigen4.ops`): `jacobi_forward` and `eigh_forward` map A (B, 4, 4) to its
eigenvalues (B, 4) ascending, q (B, 4) (the eigenvector of the smallest, canonical sign) and V
(B, 4, 4) (eigenvectors as columns, column 0 = q); `backward` maps output gradients to grad_A.

Jacobi layout. Each of the 10 entries of the upper triangle of A, and each of the 16 entries of the
eigenvector matrix, is a row of a (rows, B) tensor, so every step is an elementwise operation on a
few contiguous rows: no Python loop over samples and the same code on CPU and CUDA, but ~20 kernels
per round (~450 per call) and ~850 passes over rows of the batch per matrix, bound by memory
traffic; the fused kernels keep each matrix in registers instead.

Kernels. Only ATen's own elementwise kernels: no op that ATen hands to MKL's vector math library
(VML: sqrt, exp, log, ... of contiguous CPU tensors). VML's first call in a process races between
intra-op threads on Intel CPUs and returned wrong square roots for one thread's share of the batch
(issue 27); the root below is x * rsqrt(x). tests/geometry/test_eigen4_first_call.py guards it.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from rotlearn.geometry import linalg

# Matrices per pass on CPU (`chunk_size`): 16384 per thread, at least 32768; the working set
# (~2 MB per 16384 in float32) then stays in the last-level cache. Measured: 32768 best with 2
# threads (an earlier, quiet session) and, with 1 thread, 32768 took 0.90-0.94x the time of 16384
# (three interleaved runs, issue 16; 65536: 1.10x). On CUDA the batch is not split.
_CHUNK_PER_THREAD = 16384
_CHUNK_MIN = 32768

# Rows of the working tensor S (10, B): the diagonal d0..d3, then the off-diagonal entries in
# row-major upper-triangle order o01 o02 o03 o12 o13 o23 (positions 4..9).
UPPER = (0, 5, 10, 15, 1, 2, 3, 6, 7, 11)  # flat (row-major) index in A of each row of S


def chunk_size(batch: int, device: torch.device) -> int:
    """Matrices per Jacobi pass: the whole batch on CUDA, cache-sized chunks on CPU (>= 1)."""
    if device.type != "cpu":
        return max(batch, 1)
    return max(_CHUNK_MIN, _CHUNK_PER_THREAD * torch.get_num_threads())


@functools.lru_cache(maxsize=16)
def _constants(dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
    """Small constant tensors, made once per dtype and device (never written to)."""
    return {
        "tiny": torch.tensor(torch.finfo(dtype).tiny, dtype=dtype, device=device),
        "zero": torch.zeros((), dtype=dtype, device=device),
        "one": torch.ones((), dtype=dtype, device=device),
        "eye": torch.eye(4, dtype=dtype, device=device),
        "sign_weights": torch.tensor([[8.0, 4.0, 2.0, 16.0]], dtype=dtype, device=device),
        "upper": torch.tensor(UPPER, device=device),
        "first_entries": torch.tensor([0, 12, 6, 18, 1, 13, 5, 17], device=device),
    }


def _rotate(p: Tensor, q: Tensor, c: Tensor, t: Tensor) -> None:
    """In place: (p, q) <- (c (p - t q), c (q + t p)), a plane rotation with tan = t, cos = c."""
    u = torch.addcmul(p, q, t, value=-1.0)
    q.addcmul_(p, t).mul_(c)
    torch.mul(u, c, out=p)


def _jacobi(S: Tensor, W: Tensor, rounds: int) -> None:
    """Diagonalise in place.

    S: (10, B) the entries of A (rows as `UPPER`); on return its first 4 rows are the eigenvalues
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


def canonical_sign(q: Tensor) -> Tensor:
    """The sign making q canonical, exactly as `rotlearn.geometry.quat_canonical` picks it.

    q is (4, B) with rows x, y, z, w. quat_canonical makes the first nonzero component in the
    order w, x, y, z positive (+1 for the zero vector). The same rule as one weighted sum:
    sign(2 (8 sign w + 4 sign x + 2 sign y + sign z) + 1) (each weight exceeds the sum of the
    later ones; the +1 maps the all-zero key to +1). Returns (1, B).
    """
    const = _constants(q.dtype, q.device)
    key = torch.addmm(const["one"], const["sign_weights"], torch.sign(q))
    return torch.sign(key)


def _pow2(k: Tensor, dtype: torch.dtype) -> Tensor:
    """2^k for integer k (int32) in the normal range of dtype, exactly (built from its bits)."""
    if dtype == torch.float64:
        return k.to(torch.int64).add_(1023).bitwise_left_shift_(52).view(torch.float64)
    return k.add(127).bitwise_left_shift_(23).view(torch.float32)


def _scale(S: Tensor) -> tuple[Tensor, Tensor]:
    """Scale S (10, b) in place by the power of two that puts each column's largest |entry| in
    [0.5, 1) (exact; as the C kernel's `scale`), and return the two factors (b,) that undo it, to
    be applied in turn (the second first).

    The factor 2^k is applied as 2^k1 2^k2, both normal numbers: 2^k itself overflows for a
    subnormal largest entry (k > BIAS - 1), and 2^-k is no normal number for a huge one.
    """
    bias = 1023 if S.dtype == torch.float64 else 127  # the exponent bias
    _, e = torch.frexp(S.abs().amax(0))  # max = f 2^e, f in [0.5, 1); e = 0 for max = 0
    k = e.neg_()
    k1 = k.clamp(1 - bias, bias - 1)
    k2 = k.sub(bias - 1).clamp_(min=0)
    S.mul_(_pow2(k1, S.dtype)).mul_(_pow2(k2, S.dtype))
    return _pow2(k1.neg_(), S.dtype), _pow2(k2.neg_(), S.dtype)


def _solve(A: Tensor, W: Tensor, rounds: int) -> None:
    """Eigen-decompose A (b, 4, 4) into W (4 columns, 5 rows, b), zero on entry.

    On return column j of W holds (v_j, l_j), sorted by l_j ascending, v_0 with canonical sign.
    As the fused kernels: scale (exact), subtract the mean diagonal c = trace / 4 (the
    eigenvectors stay, the eigenvalues move by c, and the rounding of the rotations becomes
    relative to the spread of the eigenvalues), scale again, rotate, sort, and undo it all.
    """
    b = A.shape[0]
    S = A.reshape(b, 16).t().index_select(0, _constants(A.dtype, A.device)["upper"])
    back0, back1 = _scale(S)
    D = S[:4]
    shift = torch.add(D[0], D[1]).add_(torch.add(D[2], D[3])).mul_(0.25)
    D.sub_(shift)
    back2, back3 = _scale(S)
    _jacobi(S, W, rounds)
    _sort(W)
    W[:, 4].mul_(back3).mul_(back2).add_(shift).mul_(back1).mul_(back0)
    W[0, :4].mul_(canonical_sign(W[0, :4]))


def jacobi_forward(A: Tensor, rounds: int) -> tuple[Tensor, Tensor, Tensor]:
    """The cyclic Jacobi solver, eagerly: A (B, 4, 4) -> eigenvalues (B, 4), q (B, 4), V."""
    B = A.shape[0]
    W = torch.zeros(4, 5, B, dtype=A.dtype, device=A.device)  # columns (v_i, l_i)
    chunk = chunk_size(B, A.device)
    for start in range(0, B, chunk):
        _solve(A[start : start + chunk], W[..., start : start + chunk], rounds)
    eigenvalues = W[:, 4].t().contiguous()
    return eigenvalues, W[0, :4].t().contiguous(), W[:, :4].permute(2, 1, 0).contiguous()


def eigh_forward(A: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """torch.linalg.eigh (LAPACK on CPU, cuSOLVER on CUDA) with q's sign made canonical.

    As the Jacobi paths, eigh solves A - cI (c added back to the eigenvalues), so that its
    rounding is relative to the spread of the eigenvalues rather than to ||A||_2; here c is the
    midpoint of A's diagonal, (min + max) / 2, rather than trace / 4 (as good: the diagonal lies
    within [l1, l4]): A - cI cannot overflow for any finite A, where A - (trace / 4) I can
    (the Jacobi paths subtract after a power-of-two scaling), and it takes fewer operations.
    """
    low, high = torch.aminmax(A.diagonal(dim1=-2, dim2=-1), dim=-1, keepdim=True)
    shift = low.mul_(0.5).add_(high, alpha=0.5)  # no overflow
    eye = _constants(A.dtype, A.device)["eye"]
    A = torch.addcmul(A, shift.unsqueeze(-1), eye, value=-1.0)  # off the diagonal: exact
    eigenvalues, V = linalg.eigh(A, UPLO="U")
    q = V[..., 0]  # (B, 4) view: canonical sign in place, so V keeps q as its column 0
    q.mul_(canonical_sign(q.t()).t())
    # row-major, as every path (LAPACK's is not)
    return eigenvalues.add_(shift), q.clone(), V.contiguous()


def backward(
    grad_l: Tensor | None, grad_q: Tensor | None, eigenvalues: Tensor, V: Tensor, gap_eps: float
) -> Tensor:
    """grad_A (B, 4, 4) from the output gradients (B, 4) (either may be None) and the saved
    eigenvalues (B, 4), V (B, 4, 4); the formula of `rotlearn.geometry.eigen4.sym4_eigh_min`'s
    backward, as batched products. All out of place (torch.func.vmap has no rule for in-place
    addcmul_)."""
    G = None  # the gradient before symmetrisation, (B, 4, 4)
    if grad_q is not None:
        spread = eigenvalues[:, 3:] - eigenvalues[:, :1]  # l4 - l1, (B, 1)
        floor = torch.add(torch.eq(spread, 0).to(V.dtype), spread, alpha=gap_eps)
        gaps = torch.maximum(eigenvalues[:, 1:] - eigenvalues[:, :1], floor)  # (B, 3)
        upper = V[..., 1:]  # v2, v3, v4 as columns, (B, 4, 3)
        coef = torch.matmul(grad_q.unsqueeze(-2), upper).div(gaps.unsqueeze(-2))  # (B, 1, 3)
        u = torch.matmul(upper, coef.mT)  # (A - l1 I)^+ g_q, (B, 4, 1)
        G = u * V[..., 0].neg().unsqueeze(-2)  # -u q^T
    if grad_l is not None:
        Vg = V * grad_l.unsqueeze(-2)  # columns g_i v_i
        G = torch.matmul(Vg, V.mT) if G is None else torch.baddbmm(G, Vg, V.mT)
    if G is None:
        return torch.zeros_like(V)
    return torch.add(G, G.mT).mul(0.5)  # exactly symmetric
