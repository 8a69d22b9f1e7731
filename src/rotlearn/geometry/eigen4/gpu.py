"""The A layer's eigensolver as two Triton kernels: one launch forward, one launch backward.

`forward`: each program loads BLOCK matrices (the 10 numbers of each upper triangle, any strides),
keeps every matrix in registers through the Jacobi rounds, the sorting network and the canonical
sign, and stores its eigenvalues (B, 4), q (B, 4) and V (B, 4, 4). `backward`: each program loads
the saved eigenpairs and the output gradients of BLOCK matrices and stores grad_A (B, 4, 4). The
algorithm, the round counts and the backward formula are those of the other paths
(`rotlearn.geometry.eigen4`); float32 math uses IEEE-rounded square roots and divisions
(`sqrt_rn`, `div_rn`: Triton's default ones are approximate), float64 Triton's float64 ones.

Needs `triton` >= 3.0 (`pip install rotlearn[gpu]`; tested with 3.7 in the interpreter and
compiled for sm_90 without a GPU, and with 3.6 on an H200: docs/results.md). On CUDA tensors the
kernels are compiled by Triton on first use per dtype (cached by Triton). On CPU tensors the
same kernels run in Triton's interpreter (a second copy of this module whose kernels
`triton.jit` wrapped with TRITON_INTERPRET=1; so the kernels call only Triton builtins, none of
triton.language's own jit functions such as tl.zeros, which the interpreter cannot call when
triton was imported without it): slow, and only for the tests of this machine without a GPU.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import threading

import torch
import triton
import triton.language as tl
from torch import Tensor

__all__ = ["backward", "forward"]

INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"  # how this copy's kernels were wrapped
BLOCK = {torch.float32: 128, torch.float64: 64}  # matrices per program (one per thread)
_INTERPRETER_MODULE = f"{__name__}_interpreted"
_lock = threading.Lock()


@triton.jit
def _sqrt(x, IS64: tl.constexpr):
    if IS64:
        return tl.sqrt(x)
    else:
        return tl.sqrt_rn(x)


@triton.jit
def _div(x, y, IS64: tl.constexpr):
    if IS64:
        return x / y
    else:
        return tl.div_rn(x, y)


@triton.jit
def _pow2(k, IS64: tl.constexpr):
    """2^k for integer k in the normal range, exactly."""
    if IS64:
        return ((k + 1023).to(tl.int64) << 52).to(tl.float64, bitcast=True)
    else:
        return ((k + 127).to(tl.int32) << 23).to(tl.float32, bitcast=True)


@triton.jit
def _tiny(k, IS64: tl.constexpr):
    """The smallest normal number (shaped like the int tensor k), exactly, whatever Triton makes
    of a float constant."""
    if IS64:
        return _pow2(k * 0 - 1022, IS64)
    else:
        return _pow2(k * 0 - 126, IS64)


@triton.jit
def _shift(m, IS64: tl.constexpr):
    """The power-of-two exponents (k1, k2) with m 2^(k1 + k2) in [0.5, 1) for m > 0 (2^k1 and
    2^-k1 both normal; k2 > 0 only for a subnormal m); (0, 0) for m = 0."""
    big = m * 18446744073709551616.0  # 2^64: a subnormal m becomes normal, exactly
    if IS64:
        bias = 1023
        e = ((m.to(tl.int64, bitcast=True) >> 52) & 0x7FF).to(tl.int32)
        e_big = ((big.to(tl.int64, bitcast=True) >> 52) & 0x7FF).to(tl.int32)
    else:
        bias = 127
        e = (m.to(tl.int32, bitcast=True) >> 23) & 0xFF
        e_big = (big.to(tl.int32, bitcast=True) >> 23) & 0xFF
    k = tl.where(e == 0, bias - 1 - e_big + 64, bias - 1 - e)
    k = tl.where(m == 0, 0, k)
    k1 = tl.minimum(tl.maximum(k, 1 - bias), bias - 1)  # 2^-k1 normal too (2^-bias is not)
    k2 = tl.where(k > bias - 1, k - (bias - 1), 0)
    return k1, k2


@triton.jit
def _scale(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, IS64: tl.constexpr):
    """The upper triangle scaled by the power of two that puts its largest entry in [0.5, 1)
    (exact), and the exponents (k1, k2) of `_shift` that undo it."""
    m = tl.maximum(tl.maximum(tl.abs(a00), tl.abs(a01)), tl.maximum(tl.abs(a02), tl.abs(a03)))
    m = tl.maximum(m, tl.maximum(tl.maximum(tl.abs(a11), tl.abs(a12)), tl.abs(a13)))
    m = tl.maximum(m, tl.maximum(tl.maximum(tl.abs(a22), tl.abs(a23)), tl.abs(a33)))
    k1, k2 = _shift(m, IS64)
    # One factor after the other, as the C kernel: 2^(k1 + k2) itself overflows for a subnormal m
    s1, s2 = _pow2(k1, IS64), _pow2(k2, IS64)
    return (
        a00 * s1 * s2, a01 * s1 * s2, a02 * s1 * s2, a03 * s1 * s2,
        a11 * s1 * s2, a12 * s1 * s2, a13 * s1 * s2,
        a22 * s1 * s2, a23 * s1 * s2, a33 * s1 * s2,
        k1, k2,
    )  # fmt: skip


@triton.jit
def _angle(app, aqq, apq, tiny, IS64: tl.constexpr):
    """cos and tan of the rotation zeroing apq (|tan| <= 1, the stable small-angle root)."""
    d = aqq - app
    root = _sqrt(tiny + d * d + 4.0 * (apq * apq), IS64)
    den = tl.where(d < 0, -root, root) + d  # sign(d) (|d| + root), never 0
    t = _div(2.0 * apq, den, IS64)
    c = _div(1.0, _sqrt(1.0 + t * t, IS64), IS64)
    return c, t


@triton.jit
def _rot(x, y, c, t):
    return c * (x - t * y), c * (y + t * x)


@triton.jit
def _round(
    pp1, qq1, pq1, pp2, qq2, pq2, x11, x12, x21, x22,
    p10, p11, p12, p13, q10, q11, q12, q13, p20, p21, p22, p23, q20, q21, q22, q23,
    tiny, IS64: tl.constexpr, LAST: tl.constexpr,
):  # fmt: skip
    """One round: rotations of the disjoint pairs (p1, q1), (p2, q2); pp/qq/pq their diagonal and
    off-diagonal entries, x the 2x2 block coupling them (rows p1, q1; columns p2, q2), p1*, q1*,
    p2*, q2* the four eigenvector columns. A <- J^T A J, V <- V J."""
    c1, t1 = _angle(pp1, qq1, pq1, tiny, IS64)
    c2, t2 = _angle(pp2, qq2, pq2, tiny, IS64)
    pp1, qq1 = pp1 - t1 * pq1, qq1 + t1 * pq1
    pp2, qq2 = pp2 - t2 * pq2, qq2 + t2 * pq2
    if not LAST:  # after the last round the off-diagonal entries are not read
        pq1 = tl.full(pq1.shape, 0.0, pq1.dtype)
        pq2 = tl.full(pq2.shape, 0.0, pq2.dtype)
        y11, y21 = _rot(x11, x21, c1, t1)  # rows by the first rotation
        y12, y22 = _rot(x12, x22, c1, t1)
        x11, x12 = _rot(y11, y12, c2, t2)  # columns by the second
        x21, x22 = _rot(y21, y22, c2, t2)
    p10, q10 = _rot(p10, q10, c1, t1)
    p11, q11 = _rot(p11, q11, c1, t1)
    p12, q12 = _rot(p12, q12, c1, t1)
    p13, q13 = _rot(p13, q13, c1, t1)
    p20, q20 = _rot(p20, q20, c2, t2)
    p21, q21 = _rot(p21, q21, c2, t2)
    p22, q22 = _rot(p22, q22, c2, t2)
    p23, q23 = _rot(p23, q23, c2, t2)
    return (
        pp1, qq1, pq1, pp2, qq2, pq2, x11, x12, x21, x22,
        p10, p11, p12, p13, q10, q11, q12, q13, p20, p21, p22, p23, q20, q21, q22, q23,
    )  # fmt: skip


@triton.jit
def _exchange(la, lb, a0, a1, a2, a3, b0, b1, b2, b3):
    """Compare-exchange of two eigenpairs by eigenvalue, ascending (ties and NaN keep order)."""
    s = la > lb
    return (
        tl.where(s, lb, la), tl.where(s, la, lb),
        tl.where(s, b0, a0), tl.where(s, b1, a1), tl.where(s, b2, a2), tl.where(s, b3, a3),
        tl.where(s, a0, b0), tl.where(s, a1, b1), tl.where(s, a2, b2), tl.where(s, a3, b3),
    )  # fmt: skip


@triton.jit
def _sign(x):
    return (x > 0).to(x.dtype) - (x < 0).to(x.dtype)


@triton.jit
def _forward_kernel(
    A, L, Q, V, n, sb, sr, sc,
    ROUNDS: tl.constexpr, IS64: tl.constexpr, BLOCK: tl.constexpr,
):  # fmt: skip
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    mask = offs < n
    base = A + offs * sb
    a00 = tl.load(base, mask=mask, other=0.0)
    a01 = tl.load(base + sc, mask=mask, other=0.0)
    a02 = tl.load(base + 2 * sc, mask=mask, other=0.0)
    a03 = tl.load(base + 3 * sc, mask=mask, other=0.0)
    a11 = tl.load(base + sr + sc, mask=mask, other=0.0)
    a12 = tl.load(base + sr + 2 * sc, mask=mask, other=0.0)
    a13 = tl.load(base + sr + 3 * sc, mask=mask, other=0.0)
    a22 = tl.load(base + 2 * sr + 2 * sc, mask=mask, other=0.0)
    a23 = tl.load(base + 2 * sr + 3 * sc, mask=mask, other=0.0)
    a33 = tl.load(base + 3 * sr + 3 * sc, mask=mask, other=0.0)
    # Scale (exact), subtract the mean diagonal c (the eigenvectors stay, the eigenvalues move by
    # c, the rounding becomes relative to their spread), scale again; as the C kernel's `load`.
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, k1, k2 = _scale(
        a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, IS64
    )
    shift = ((a00 + a11) + (a22 + a33)) * 0.25
    a00, a11, a22, a33 = a00 - shift, a11 - shift, a22 - shift, a33 - shift
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, k3, k4 = _scale(
        a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, IS64
    )
    tiny = _tiny(k1, IS64)
    one = tl.full(a00.shape, 1.0, a00.dtype)
    zero = tl.full(a00.shape, 0.0, a00.dtype)
    v00, v01, v02, v03 = one, zero, zero, zero  # v_ij: component i of eigenvector j
    v10, v11, v12, v13 = zero, one, zero, zero
    v20, v21, v22, v23 = zero, zero, one, zero
    v30, v31, v32, v33 = zero, zero, zero, one
    for k in tl.static_range(ROUNDS):  # three perfect matchings: one cyclic sweep per 3 rounds
        if k % 3 == 0:  # pairs (0, 1), (2, 3)
            (
                a00, a11, a01, a22, a33, a23, a02, a03, a12, a13,
                v00, v10, v20, v30, v01, v11, v21, v31, v02, v12, v22, v32, v03, v13, v23, v33,
            ) = _round(
                a00, a11, a01, a22, a33, a23, a02, a03, a12, a13,
                v00, v10, v20, v30, v01, v11, v21, v31, v02, v12, v22, v32, v03, v13, v23, v33,
                tiny, IS64, k == ROUNDS - 1,
            )  # fmt: skip
        elif k % 3 == 1:  # pairs (0, 2), (1, 3)
            (
                a00, a22, a02, a11, a33, a13, a01, a03, a12, a23,
                v00, v10, v20, v30, v02, v12, v22, v32, v01, v11, v21, v31, v03, v13, v23, v33,
            ) = _round(
                a00, a22, a02, a11, a33, a13, a01, a03, a12, a23,
                v00, v10, v20, v30, v02, v12, v22, v32, v01, v11, v21, v31, v03, v13, v23, v33,
                tiny, IS64, k == ROUNDS - 1,
            )  # fmt: skip
        else:  # pairs (0, 3), (1, 2)
            (
                a00, a33, a03, a11, a22, a12, a01, a02, a13, a23,
                v00, v10, v20, v30, v03, v13, v23, v33, v01, v11, v21, v31, v02, v12, v22, v32,
            ) = _round(
                a00, a33, a03, a11, a22, a12, a01, a02, a13, a23,
                v00, v10, v20, v30, v03, v13, v23, v33, v01, v11, v21, v31, v02, v12, v22, v32,
                tiny, IS64, k == ROUNDS - 1,
            )  # fmt: skip
    # Sorting network (0,1)(2,3) | (0,2)(1,3) | (1,2), eigenvector columns moving along.
    l0, l1, l2, l3 = a00, a11, a22, a33
    l0, l1, v00, v10, v20, v30, v01, v11, v21, v31 = _exchange(
        l0, l1, v00, v10, v20, v30, v01, v11, v21, v31
    )
    l2, l3, v02, v12, v22, v32, v03, v13, v23, v33 = _exchange(
        l2, l3, v02, v12, v22, v32, v03, v13, v23, v33
    )
    l0, l2, v00, v10, v20, v30, v02, v12, v22, v32 = _exchange(
        l0, l2, v00, v10, v20, v30, v02, v12, v22, v32
    )
    l1, l3, v01, v11, v21, v31, v03, v13, v23, v33 = _exchange(
        l1, l3, v01, v11, v21, v31, v03, v13, v23, v33
    )
    l1, l2, v01, v11, v21, v31, v02, v12, v22, v32 = _exchange(
        l1, l2, v01, v11, v21, v31, v02, v12, v22, v32
    )
    # Canonical sign of q = column 0 (x, y, z, w): the first nonzero of w, x, y, z positive.
    key = 8.0 * _sign(v30) + 4.0 * _sign(v00) + 2.0 * _sign(v10) + _sign(v20)
    sign = tl.where(key < 0, -1.0, 1.0).to(v00.dtype)
    v00, v10, v20, v30 = v00 * sign, v10 * sign, v20 * sign, v30 * sign
    # Undo the second scaling, add c back, undo the first (each pair of factors in turn:
    # 2^-(k1 + k2) may underflow).
    b4, b3, b2, b1 = _pow2(-k4, IS64), _pow2(-k3, IS64), _pow2(-k2, IS64), _pow2(-k1, IS64)
    lbase = L + offs * 4
    tl.store(lbase, (l0 * b4 * b3 + shift) * b2 * b1, mask=mask)
    tl.store(lbase + 1, (l1 * b4 * b3 + shift) * b2 * b1, mask=mask)
    tl.store(lbase + 2, (l2 * b4 * b3 + shift) * b2 * b1, mask=mask)
    tl.store(lbase + 3, (l3 * b4 * b3 + shift) * b2 * b1, mask=mask)
    qbase = Q + offs * 4
    tl.store(qbase, v00, mask=mask)
    tl.store(qbase + 1, v10, mask=mask)
    tl.store(qbase + 2, v20, mask=mask)
    tl.store(qbase + 3, v30, mask=mask)
    vbase = V + offs * 16
    tl.store(vbase, v00, mask=mask)
    tl.store(vbase + 1, v01, mask=mask)
    tl.store(vbase + 2, v02, mask=mask)
    tl.store(vbase + 3, v03, mask=mask)
    tl.store(vbase + 4, v10, mask=mask)
    tl.store(vbase + 5, v11, mask=mask)
    tl.store(vbase + 6, v12, mask=mask)
    tl.store(vbase + 7, v13, mask=mask)
    tl.store(vbase + 8, v20, mask=mask)
    tl.store(vbase + 9, v21, mask=mask)
    tl.store(vbase + 10, v22, mask=mask)
    tl.store(vbase + 11, v23, mask=mask)
    tl.store(vbase + 12, v30, mask=mask)
    tl.store(vbase + 13, v31, mask=mask)
    tl.store(vbase + 14, v32, mask=mask)
    tl.store(vbase + 15, v33, mask=mask)


@triton.jit
def _max_nan(x, m):
    """max(x, m) that returns NaN when x is NaN (as torch.maximum)."""
    return tl.where((x > m) | (x != x), x, m)


@triton.jit
def _gap_coef(lj, l0, clamp, a0, a1, a2, a3, g0, g1, g2, g3, IS64: tl.constexpr):
    """(v_j . g_q) / max(l_j - l_0, clamp), NaN-propagating."""
    gap = _max_nan(lj - l0, clamp)
    return _div(a0 * g0 + a1 * g1 + a2 * g2 + a3 * g3, gap, IS64)


@triton.jit
def _backward_kernel(
    GL, GQ, L, V, G, n,
    GAP_EPS: tl.constexpr, HAS_GL: tl.constexpr, HAS_GQ: tl.constexpr, IS64: tl.constexpr,
    BLOCK: tl.constexpr,
):  # fmt: skip
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    mask = offs < n
    lbase = L + offs * 4
    l0 = tl.load(lbase, mask=mask, other=0.0)
    l1 = tl.load(lbase + 1, mask=mask, other=0.0)
    l2 = tl.load(lbase + 2, mask=mask, other=0.0)
    l3 = tl.load(lbase + 3, mask=mask, other=0.0)
    vb = V + offs * 16
    v00 = tl.load(vb, mask=mask, other=0.0)
    v01 = tl.load(vb + 1, mask=mask, other=0.0)
    v02 = tl.load(vb + 2, mask=mask, other=0.0)
    v03 = tl.load(vb + 3, mask=mask, other=0.0)
    v10 = tl.load(vb + 4, mask=mask, other=0.0)
    v11 = tl.load(vb + 5, mask=mask, other=0.0)
    v12 = tl.load(vb + 6, mask=mask, other=0.0)
    v13 = tl.load(vb + 7, mask=mask, other=0.0)
    v20 = tl.load(vb + 8, mask=mask, other=0.0)
    v21 = tl.load(vb + 9, mask=mask, other=0.0)
    v22 = tl.load(vb + 10, mask=mask, other=0.0)
    v23 = tl.load(vb + 11, mask=mask, other=0.0)
    v30 = tl.load(vb + 12, mask=mask, other=0.0)
    v31 = tl.load(vb + 13, mask=mask, other=0.0)
    v32 = tl.load(vb + 14, mask=mask, other=0.0)
    v33 = tl.load(vb + 15, mask=mask, other=0.0)
    zero = tl.full(l0.shape, 0.0, l0.dtype)
    if HAS_GL:
        glb = GL + offs * 4
        g0 = tl.load(glb, mask=mask, other=0.0)
        g1 = tl.load(glb + 1, mask=mask, other=0.0)
        g2 = tl.load(glb + 2, mask=mask, other=0.0)
        g3 = tl.load(glb + 3, mask=mask, other=0.0)
    else:
        g0, g1, g2, g3 = zero, zero, zero, zero
    if HAS_GQ:
        gqb = GQ + offs * 4
        h0 = tl.load(gqb, mask=mask, other=0.0)
        h1 = tl.load(gqb + 1, mask=mask, other=0.0)
        h2 = tl.load(gqb + 2, mask=mask, other=0.0)
        h3 = tl.load(gqb + 3, mask=mask, other=0.0)
    else:
        h0, h1, h2, h3 = zero, zero, zero, zero
    spread = l3 - l0  # l4 - l1: as the gaps, free of A's trace
    clamp = (spread == 0).to(l0.dtype) + GAP_EPS * spread  # 1 for A = cI
    c1 = _gap_coef(l1, l0, clamp, v01, v11, v21, v31, h0, h1, h2, h3, IS64)
    c2 = _gap_coef(l2, l0, clamp, v02, v12, v22, v32, h0, h1, h2, h3, IS64)
    c3 = _gap_coef(l3, l0, clamp, v03, v13, v23, v33, h0, h1, h2, h3, IS64)
    u0 = c1 * v01 + c2 * v02 + c3 * v03  # u = (A - l1 I)^+ g_q
    u1 = c1 * v11 + c2 * v12 + c3 * v13
    u2 = c1 * v21 + c2 * v22 + c3 * v23
    u3 = c1 * v31 + c2 * v32 + c3 * v33
    gb = G + offs * 16
    # grad[r, c] = sum_j g_j v_rj v_cj - (u_r q_c + u_c q_r) / 2 (q = column 0), both triangles.
    for r in tl.static_range(4):
        for c in tl.static_range(r, 4):
            vr0, vr1, vr2, vr3, ur = v00, v01, v02, v03, u0
            if r == 1:
                vr0, vr1, vr2, vr3, ur = v10, v11, v12, v13, u1
            if r == 2:
                vr0, vr1, vr2, vr3, ur = v20, v21, v22, v23, u2
            if r == 3:
                vr0, vr1, vr2, vr3, ur = v30, v31, v32, v33, u3
            vc0, vc1, vc2, vc3, uc = v00, v01, v02, v03, u0
            if c == 1:
                vc0, vc1, vc2, vc3, uc = v10, v11, v12, v13, u1
            if c == 2:
                vc0, vc1, vc2, vc3, uc = v20, v21, v22, v23, u2
            if c == 3:
                vc0, vc1, vc2, vc3, uc = v30, v31, v32, v33, u3
            x = g0 * vr0 * vc0 + g1 * vr1 * vc1 + g2 * vr2 * vc2 + g3 * vr3 * vc3
            x = x - 0.5 * (ur * vc0 + uc * vr0)
            tl.store(gb + 4 * r + c, x, mask=mask)
            if c != r:
                tl.store(gb + 4 * c + r, x, mask=mask)


def _interpreted():
    """This module again, its kernels wrapped by triton.jit under TRITON_INTERPRET=1."""
    module = sys.modules.get(_INTERPRETER_MODULE)
    if module is not None:
        return module
    with _lock:
        module = sys.modules.get(_INTERPRETER_MODULE)
        if module is None:
            spec = importlib.util.spec_from_file_location(_INTERPRETER_MODULE, __file__)
            module = importlib.util.module_from_spec(spec)
            before = os.environ.get("TRITON_INTERPRET")
            os.environ["TRITON_INTERPRET"] = "1"
            try:
                spec.loader.exec_module(module)
            finally:
                if before is None:
                    del os.environ["TRITON_INTERPRET"]
                else:
                    os.environ["TRITON_INTERPRET"] = before
            sys.modules[_INTERPRETER_MODULE] = module
    return module


def _launch(kernel, grid: tuple[int], device: torch.device, *args, **meta) -> None:
    if device.type == "cuda":
        with torch.cuda.device(device):
            kernel[grid](*args, **meta)
    else:
        kernel[grid](*args, **meta)


def forward(A: Tensor, rounds: int) -> tuple[Tensor, Tensor, Tensor]:
    """A (B, 4, 4) float32/float64 (any strides; only the upper triangle is read) -> eigenvalues
    (B, 4) ascending, q (B, 4) canonical, V (B, 4, 4) (eigenvectors as columns). One launch."""
    if A.device.type == "cpu" and not INTERPRETED:
        return _interpreted().forward(A, rounds)
    B = A.shape[0]
    eigenvalues = A.new_empty(B, 4)
    q = A.new_empty(B, 4)
    V = A.new_empty(B, 4, 4)
    if B:
        block = BLOCK[A.dtype]
        _launch(
            _forward_kernel, (triton.cdiv(B, block),), A.device,
            A, eigenvalues, q, V, B, *A.stride(),
            ROUNDS=rounds, IS64=A.dtype == torch.float64, BLOCK=block,
        )  # fmt: skip
    return eigenvalues, q, V


def backward(
    grad_l: Tensor | None, grad_q: Tensor | None, eigenvalues: Tensor, V: Tensor, gap_eps: float
) -> Tensor:
    """grad_A (B, 4, 4), exactly symmetric, from the output gradients (B, 4) (None: zero) and the
    saved eigenvalues (B, 4) and V (B, 4, 4). One launch."""
    if V.device.type == "cpu" and not INTERPRETED:
        return _interpreted().backward(grad_l, grad_q, eigenvalues, V, gap_eps)
    B = V.shape[0]
    grad = V.new_empty(B, 4, 4)
    if B:
        lam, vec = eigenvalues.contiguous(), V.contiguous()
        gl = lam if grad_l is None else grad_l.to(V.dtype).contiguous()
        gq = lam if grad_q is None else grad_q.to(V.dtype).contiguous()
        block = BLOCK[V.dtype]
        _launch(
            _backward_kernel, (triton.cdiv(B, block),), V.device,
            gl, gq, lam, vec, grad, B,
            GAP_EPS=float(gap_eps), HAS_GL=grad_l is not None, HAS_GQ=grad_q is not None,
            IS64=V.dtype == torch.float64, BLOCK=block,
        )  # fmt: skip
    return grad
