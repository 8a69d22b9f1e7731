"""rotlearn.geometry.eigen4: the batched Jacobi eigensolver for symmetric 4x4 matrices.

Every path that runs on this machine is held to the same bounds: the fused C kernel ("cpu") and the
eager tensor operations ("eager"); the Triton kernels under Triton's interpreter in
test_eigen4_triton.py, on CUDA in test_cuda_matches_cpu.

Reference: float64 `torch.linalg.eigh` of the very matrix the solver sees (the float32 input is
upcast, so the reference is exact to ~1e-16 for it). "No worse than eigh" compares, case by case,
the solver's largest error over the batch with that of `torch.linalg.eigh` run in the same dtype,
allowing a factor 1.5 on errors that are already at rounding level (a few ulps), where the maxima
of two correct methods differ by chance.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import warnings

import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from rotlearn.geometry import (
    a_from_quat,
    a_from_vec,
    angle_deg,
    quat_canonical,
    quat_multiply,
    quat_to_rotmat,
    random_quat,
    random_unit_vectors,
    so3_exp_quat,
)
from rotlearn.geometry.eigen4 import (
    DEFAULT_ROUNDS,
    EIGH_BELOW,
    ops,
    sym4_eigh_min,
    validate_sym4,
)
from rotlearn.geometry.eigen4 import cpu as cpu_kernel
from rotlearn.geometry.eigen4.eager import canonical_sign as _canonical_sign
from rotlearn.geometry.eigen4.eager import chunk_size as _chunk_size
from tests.conftest import gen

F32, F64 = torch.float32, torch.float64
DTYPES = [F32, F64]


def _upper_triangles(bound: float, width: int):
    """Hypothesis: the 10 upper-triangle entries of a symmetric 4x4 (`a_from_vec`), each a
    finite float of `width` bits in [-bound, bound]."""
    entry = st.floats(min_value=-bound, max_value=bound, allow_nan=False, width=width)
    return st.lists(entry, min_size=10, max_size=10)


# The CPU paths: the fused kernel needs a C compiler (test_cpu_kernel_builds_where_a_compiler_is
# fails where one exists and the build does not).
NO_CPU_KERNEL = pytest.mark.skipif(not cpu_kernel.available(), reason="no CPU kernel here")
PATHS = [pytest.param("cpu", marks=NO_CPU_KERNEL), "eager"]
NO_TRITON = pytest.mark.skipif(not ops.triton_available(), reason="triton is not installed")
# (method, kernel): both forwards with every CPU backward
SOLVERS = [
    pytest.param(m, k, marks=NO_CPU_KERNEL if k == "cpu" else (), id=f"{m}-{k}")
    for m in ("jacobi", "eigh")
    for k in ("cpu", "eager")
]
# Every forward (method, kernel): both CPU Jacobi paths, eigh, the Triton kernels (interpreter).
FORWARDS = [
    pytest.param("jacobi", "cpu", marks=NO_CPU_KERNEL, id="jacobi-cpu"),
    pytest.param("jacobi", "eager", id="jacobi-eager"),
    pytest.param("eigh", "eager", id="eigh"),
    pytest.param("jacobi", "triton", marks=NO_TRITON, id="jacobi-triton"),
]
EPS = {F32: torch.finfo(F32).eps, F64: torch.finfo(F64).eps}
N = 20000  # matrices per accuracy case


def sym_randn(n: int, seed: int) -> torch.Tensor:
    x = torch.randn(n, 4, 4, generator=gen(seed), dtype=F64)
    return (x + x.mT) / 2


def rotated_diag(eigenvalues: torch.Tensor, seed: int) -> torch.Tensor:
    """Q diag(eigenvalues) Q^T with Haar-random orthogonal Q: (n, 4) -> (n, 4, 4), float64."""
    x = torch.randn(eigenvalues.shape[0], 4, 4, generator=gen(seed), dtype=F64)
    Q, _ = torch.linalg.qr(x)
    return (Q * eigenvalues.unsqueeze(-2)) @ Q.mT


def quat_left_right(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Matrices of q -> p (x) q and q -> q (x) p (Hamilton, scalar last), each (..., 4, 4)."""
    eye = torch.eye(4, dtype=p.dtype).expand(*p.shape[:-1], 4, 4)
    pe = p.unsqueeze(-2).expand_as(eye)
    left = quat_multiply(pe, eye).mT  # column k = p (x) e_k
    right = quat_multiply(eye, pe).mT  # column k = e_k (x) p
    return left, right


def wahba_a(n: int, seed: int, sigma: float = 0.01, matches: int = 20) -> torch.Tensor:
    """Paper eq. 5: A = sum_i (|u_i|^2 + |v_i|^2) I + 2 Omega_l(v_i^) Omega_r(u_i^), float64."""
    g = gen(seed)  # the synthetic data of paper eq. 27 (as rotlearn.data.synthetic.wahba_batch)
    q_true = random_quat((n,), generator=g, dtype=F64)
    u = random_unit_vectors((n, matches), generator=g, dtype=F64)
    noise = torch.randn(u.shape, generator=g, dtype=F64)
    v = u @ quat_to_rotmat(q_true).mT + sigma * noise
    zero = torch.zeros(*u.shape[:-1], 1, dtype=F64)
    left_v, _ = quat_left_right(torch.cat((v, zero), -1))
    _, right_u = quat_left_right(torch.cat((u, zero), -1))
    sq = (u.square().sum(-1) + v.square().sum(-1))[..., None, None]
    A = (sq * torch.eye(4, dtype=F64) + 2 * left_v @ right_u).sum(-3)
    return A, q_true


def clustered_a(n: int, seed: int, spread: float = 0.05, k: int = 10) -> torch.Tensor:
    """-sum_k q_k q_k^T for k unit quaternions clustered (rotation angle ~spread) around one."""
    g = gen(seed)
    centre = random_quat((n, 1), generator=g, dtype=F64)
    jitter = so3_exp_quat(spread * torch.randn(n, k, 3, generator=g, dtype=F64))
    qs = quat_multiply(centre.expand(n, k, 4), jitter)
    return -(qs.unsqueeze(-1) * qs.unsqueeze(-2)).sum(-3)


def case_matrices(name: str) -> torch.Tensor:
    """(N, 4, 4) float64 matrices of one accuracy case."""
    if name == "gauss":
        return sym_randn(N, 1)
    if name == "i_minus_qqT":
        return a_from_quat(random_quat((N,), generator=gen(2), dtype=F64))
    if name == "i_minus_qqT_noise":
        return a_from_quat(random_quat((N,), generator=gen(3), dtype=F64)) + 1e-3 * sym_randn(N, 4)
    if name == "wahba":
        return wahba_a(N, 5)[0]
    if name == "clustered":
        return clustered_a(N, 6)
    if name == "scaled_1e-6":
        return 1e-6 * sym_randn(N, 7)
    if name == "scaled_1e6":
        return 1e6 * sym_randn(N, 8)
    if name == "near_degenerate":  # l2 - l1 = 1e-6 (l4 - l1)
        r = torch.rand(N, 1, generator=gen(9), dtype=F64)
        lam = torch.cat((torch.zeros(N, 1, dtype=F64), torch.full((N, 1), 1e-6, dtype=F64)), -1)
        lam = torch.cat((lam, 0.1 + 0.9 * r, torch.ones(N, 1, dtype=F64)), -1)
        return rotated_diag(lam, 10)
    raise KeyError(name)


CASES = [
    "gauss",
    "i_minus_qqT",
    "i_minus_qqT_noise",
    "wahba",
    "clustered",
    "scaled_1e-6",
    "scaled_1e6",
    "near_degenerate",
]


def errors(A64: torch.Tensor, eigenvalues: torch.Tensor, q: torch.Tensor) -> dict[str, float]:
    """Largest errors over the batch against float64 eigh of A64 (the matrices as solved).

    eig: max_i |l_i - l_i*| / ||A||_2. residual: |A q - l1 q| / ||A||_2. angle: rotation angle
    between R(q) and R(q*) in degrees, over the matrices with l2* - l1* >= 0.01 (l4* - l1*)
    (elsewhere q is ill-determined and the residual is the meaningful measure). The reference
    solves A64 - cI (c = trace / 4, so that its own rounding is relative to l4 - l1, not to c).
    """
    shift = A64.diagonal(dim1=-2, dim2=-1).mean(-1)
    L, V = torch.linalg.eigh(A64 - shift[..., None, None] * torch.eye(4, dtype=F64))
    L = L + shift[..., None]
    norm = L.abs().amax(-1)
    lam, q = eigenvalues.to(F64), q.to(F64)
    eig = ((lam - L).abs().amax(-1) / norm).max().item()
    resid = (A64 @ q.unsqueeze(-1)).squeeze(-1) - lam[..., :1] * q
    residual = (resid.norm(dim=-1) / norm).max().item()
    separated = (L[..., 1] - L[..., 0]) >= 0.01 * (L[..., 3] - L[..., 0])
    ang = angle_deg(quat_to_rotmat(q[separated]), quat_to_rotmat(V[separated][..., 0]))
    return {"eig": eig, "residual": residual, "angle": ang.max().item() if ang.numel() else 0.0}


# ---------------------------------------------------------------------------------------------
# accuracy
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def case_data() -> dict[str, torch.Tensor]:
    return {name: case_matrices(name) for name in CASES}


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", CASES)
def test_no_worse_than_eigh(case_data, case, dtype, kernel):
    A = case_data[case].to(dtype)
    A64 = A.to(F64)
    eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
    assert eigenvalues.dtype == dtype and q.dtype == dtype
    ours = errors(A64, eigenvalues, q)
    L, V = torch.linalg.eigh(A)
    ref = errors(A64, L, quat_canonical(V[..., 0]))
    floor = 4 * EPS[dtype]  # rounding of the error measurement itself
    assert ours["residual"] <= 1.5 * ref["residual"] + floor, (ours, ref)
    if dtype == F32:  # in float64 the reference IS eigh: only the residual and the bounds below
        assert ours["eig"] <= 1.5 * ref["eig"] + floor, (ours, ref)
        assert ours["angle"] <= 1.5 * ref["angle"] + 1e-5, (ours, ref)


# Documented bounds (module docstring of eigen4): float32 angle <= 1e-3 deg, eigenvalues within
# 1e-6 ||A||_2; float64 angle <= 1e-9 deg, eigenvalues within 1e-14 ||A||_2; residual likewise.
BOUNDS = {
    F32: {"angle": 1e-3, "eig": 1e-6, "residual": 2e-6},
    F64: {"angle": 1e-9, "eig": 1e-14, "residual": 1e-14},
}


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", CASES)
def test_absolute_bounds(case_data, case, dtype, kernel):
    A = case_data[case].to(dtype)
    eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
    ours = errors(A.to(F64), eigenvalues, q)
    for key, bound in BOUNDS[dtype].items():
        assert ours[key] <= bound, (key, ours)


def plus_identity(n: int, seed: int) -> torch.Tensor:
    """(4 n, 4, 4) float64, exactly symmetric: spectra (0, 0.3, 0.6, 1) plus c I for c = 1e2,
    -1e4, 1e4, and Gaussian matrices plus 1e6 I: the accuracy of q must not depend on c."""
    lam = torch.tensor([0.0, 0.3, 0.6, 1.0], dtype=F64).expand(3 * n, 4)
    A = torch.cat((rotated_diag(lam, seed), sym_randn(n, seed + 1)))
    A = (A + A.mT) / 2
    c = torch.tensor([1e2, -1e4, 1e4, 1e6], dtype=F64).repeat_interleave(n)
    return A + c[:, None, None] * torch.eye(4, dtype=F64)


@pytest.mark.parametrize(("method", "kernel"), FORWARDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_accuracy_bounds_hold_for_a_large_multiple_of_the_identity(method, kernel, dtype):
    """A + cI has A's eigenvectors; the solver subtracts trace / 4 before the rotations, so q is
    as accurate as for A (before: float32 q off by 0.43 deg for c = 1e4, eigh's by 1.95 deg,
    against the bound of 1e-3 deg; the A head's losses do not depend on the trace, which can
    drift). The reference is float64 eigh of the rounded matrices as solved (rounding A + cI to
    float32 changes its eigenvectors by itself)."""
    A = plus_identity(32 if kernel == "triton" else 400, 51).to(dtype)
    eigenvalues, q = sym4_eigh_min(A, check=False, method=method, kernel=kernel)
    ours = errors(A.to(F64), eigenvalues, q)
    for key, bound in BOUNDS[dtype].items():
        assert ours[key] <= bound, (key, ours)


@settings(max_examples=60, deadline=None)
@given(
    entries=_upper_triangles(1.0, width=32),
    shift=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
    dtype=st.sampled_from(DTYPES),
)
@example(entries=[0.25, 0.5, 0.0, -0.125, 0.0, 0.75, 0.0, 0.5, 0.25, 1.0], shift=1e4, dtype=F32)
@example(entries=[0.25, 0.5, 0.0, -0.125, 0.0, 0.75, 0.0, 0.5, 0.25, 1.0], shift=-1e6, dtype=F64)
def test_property_q_error_is_relative_to_the_spread(entries, shift, dtype):
    """The angle of q (radians) stays below 30 eps (l4 - l1) / (l2 - l1) for any A + cI (observed:
    up to 10 eps (l4 - l1) / (l2 - l1), every path and case of this file), i.e. independent of c
    and ||A||_2 (before the shift: eps (|c| + ||A||_2) / (l2 - l1))."""
    A = (a_from_vec(torch.tensor(entries, dtype=F64)) + shift * torch.eye(4, dtype=F64)).to(dtype)
    eigenvalues, q = sym4_eigh_min(A)
    A64 = A.to(F64)
    c = A64.diagonal().mean()
    L, V = torch.linalg.eigh(A64 - c * torch.eye(4, dtype=F64))
    gap, spread = (L[1] - L[0]).item(), (L[3] - L[0]).item()
    if gap <= 0:
        return  # q is any vector of the eigenspace
    angle = math.radians(angle_deg(quat_to_rotmat(q.to(F64)), quat_to_rotmat(V[:, 0])).item())
    assert angle <= 30 * EPS[dtype] * spread / gap, (angle, gap, spread)
    assert (eigenvalues.to(F64) - L - c).abs().max() <= 30 * EPS[dtype] * L.add(c).abs().max()


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_wahba_recovers_the_rotation(dtype, kernel):
    A, q_true = wahba_a(2000, 11, sigma=0.0)
    _, q = sym4_eigh_min(A.to(dtype), method="jacobi", kernel=kernel)
    err = angle_deg(quat_to_rotmat(q.to(F64)), quat_to_rotmat(q_true))
    assert err.max() <= (1e-3 if dtype == F32 else 1e-9)


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_exactly_degenerate_l1_eq_l2(dtype, kernel):
    """l1 == l2: q is any unit vector of the eigenplane; check A q = l1 q and finiteness."""
    lam = torch.tensor(
        [[-1.0, -1.0, 0.5, 2.0], [3.0, 3.0, 3.0, 4.0], [0.0, 0.0, 0.0, 0.0]], dtype=F64
    )
    A = torch.cat((rotated_diag(lam.repeat(100, 1), 12), torch.diag_embed(lam)), 0).to(dtype)
    eigenvalues, q = sym4_eigh_min(A, method="jacobi", kernel=kernel)
    assert torch.isfinite(eigenvalues).all() and torch.isfinite(q).all()
    norm = eigenvalues.abs().amax(-1).clamp_min(1.0)
    resid = (A @ q.unsqueeze(-1)).squeeze(-1) - eigenvalues[..., :1] * q
    assert (resid.norm(dim=-1) / norm).max() <= 50 * EPS[dtype]
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(len(q), dtype=dtype))


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_eigenvalues_ascending_and_match_eigh(dtype, kernel):
    A = sym_randn(1000, 13).to(dtype)
    eigenvalues, _ = sym4_eigh_min(A, method="jacobi", kernel=kernel)
    assert (eigenvalues[..., 1:] >= eigenvalues[..., :-1]).all()
    L = torch.linalg.eigh(A.to(F64)).eigenvalues
    tol = 2e-6 if dtype == F32 else 1e-14
    assert ((eigenvalues.to(F64) - L).abs() / L.abs().amax(-1, keepdim=True)).max() <= tol


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("shape", [(), (5,), (2, 3), (0,), (3, 0, 2)])
@pytest.mark.parametrize("dtype", DTYPES)
def test_batch_shapes(shape, dtype, kernel):
    A = sym_randn(max(math.prod(shape), 1), 14)[: math.prod(shape)].reshape(*shape, 4, 4)
    A = A.to(dtype)
    eigenvalues, q = sym4_eigh_min(A, method="jacobi", kernel=kernel)
    assert eigenvalues.shape == (*shape, 4) and q.shape == (*shape, 4)
    L, V = torch.linalg.eigh(A)
    tol = 1e-5 if dtype == F32 else 1e-12
    torch.testing.assert_close(eigenvalues, L, atol=tol, rtol=tol)
    torch.testing.assert_close(q, quat_canonical(V[..., 0]), atol=10 * tol, rtol=0)


@pytest.mark.parametrize("kernel", PATHS)
def test_batch_splits_give_the_same_numbers(kernel):
    """Large batches are split (eager: cache-sized chunks; cpu: one range per thread): the same
    numbers as any slice solved alone."""
    chunk = _chunk_size(10**9, torch.device("cpu"))
    A = sym_randn(2 * chunk + 100, 15).to(F32)
    eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
    for part in (slice(0, 7), slice(chunk - 4, chunk + 6), slice(2 * chunk + 90, 2 * chunk + 100)):
        l_part, q_part = sym4_eigh_min(A[part], method="jacobi", kernel=kernel)
        assert torch.equal(l_part, eigenvalues[part]) and torch.equal(q_part, q[part])


def test_chunk_size_by_device():
    """CPU batches go through the eager Jacobi loop in cache-sized chunks (at least 32768, 16384
    per thread); on other devices the whole batch is one pass."""
    cpu = _chunk_size(10, torch.device("cpu"))
    assert cpu >= 32768 and cpu >= 16384 * torch.get_num_threads()
    assert _chunk_size(5, torch.device("cuda")) == 5
    assert _chunk_size(0, torch.device("cuda")) == 1


@pytest.mark.parametrize("dtype", DTYPES)
def test_methods_agree_and_auto_switches_on_the_eager_path(dtype):
    """method="eigh" (LAPACK forward, same backward) and "jacobi" agree; on the eager path "auto"
    picks eigh for batches below EIGH_BELOW, where its per-call cost is lower, and jacobi above."""
    A = sym_randn(EIGH_BELOW, 34).to(dtype)
    l_j, q_j = sym4_eigh_min(A, method="jacobi", kernel="eager")
    l_e, q_e = sym4_eigh_min(A, method="eigh", kernel="eager")
    tol = 1e-5 if dtype == F32 else 1e-12
    torch.testing.assert_close(l_j, l_e, atol=tol, rtol=tol)
    torch.testing.assert_close(q_j, q_e, atol=1e-3 if dtype == F32 else 1e-9, rtol=0)
    l_a, q_a = sym4_eigh_min(A, method="auto", kernel="eager")
    assert torch.equal(l_a, l_j) and torch.equal(q_a, q_j)
    l_a, q_a = sym4_eigh_min(A[:-1], method="auto", kernel="eager")
    assert torch.equal(l_a, l_e[:-1]) and torch.equal(q_a, q_e[:-1])


@NO_CPU_KERNEL
@pytest.mark.parametrize("dtype", DTYPES)
def test_auto_is_the_fused_jacobi_at_every_batch_size(dtype):
    """Where the fused kernel runs, method="auto" and kernel="auto" are its Jacobi at any batch
    size (faster than eigh from B = 1 on), so results do not depend on the batch."""
    A = sym_randn(EIGH_BELOW, 34).to(dtype)
    l_j, q_j = sym4_eigh_min(A, method="jacobi", kernel="cpu")
    for part in (slice(None), slice(0, 1), slice(3, 100)):
        l_a, q_a = sym4_eigh_min(A[part])
        assert torch.equal(l_a, l_j[part]) and torch.equal(q_a, q_j[part])


def test_cpu_kernel_builds_where_a_compiler_is():
    """Where a C compiler exists the fused kernel must build: else every CPU call silently takes
    the slower eager path."""
    compilers = [os.environ.get("CC"), "cc", "gcc", "clang"]
    if os.environ.get(cpu_kernel.DISABLE_ENV) == "0" or not any(
        c and shutil.which(c) for c in compilers
    ):
        pytest.skip("no C compiler here, or the kernel is disabled")
    cpu_kernel.library()  # raises KernelUnavailableError with the compiler's complaint


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_both_methods_share_the_finite_backward(method, kernel):
    A = a_from_quat(random_quat((6,), generator=gen(35), dtype=F64)).requires_grad_()
    eigenvalues, q = sym4_eigh_min(A, method=method, kernel=kernel)
    (grad,) = torch.autograd.grad(q.sum() + eigenvalues.sum(), A)
    assert torch.isfinite(grad).all()
    theta = torch.randn(3, 10, generator=gen(36), dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: sym4_eigh_min(a_from_vec(t), method=method, kernel=kernel), (theta,)
    )


@pytest.mark.parametrize("spectrum", ["random", "near_l1_eq_l2", "l2_eq_l3_eq_l4"])
def test_eigh_and_jacobi_paths_have_the_same_gradient(spectrum):
    """Both forwards with every backward: the gradients must agree (float64), also near l1 = l2
    (gap 1e-5 ||A||, above the gap_eps clamp) and with l2 = l3 = l4 exactly."""
    n = 64
    g_l = torch.randn(n, 4, generator=gen(41), dtype=F64)
    g_q = torch.randn(n, 4, generator=gen(42), dtype=F64)
    if spectrum == "random":
        A = sym_randn(n, 43)
    elif spectrum == "near_l1_eq_l2":
        A = rotated_diag(torch.tensor([0.0, 1e-5, 0.5, 1.0], dtype=F64).expand(n, 4), 44)
    else:  # I - q q^T: eigenvalues (0, 1, 1, 1); only sums over the repeated ones are defined
        A = a_from_quat(random_quat((n,), generator=gen(45), dtype=F64))
        g_l[:, 2:] = g_l[:, 1:2]
    grads = []
    kernels = ["eager", *(["cpu"] if cpu_kernel.available() else [])]
    for method, kernel in [(m, k) for m in ("eigh", "jacobi") for k in kernels]:
        leaf = A.clone().requires_grad_()
        eigenvalues, q = sym4_eigh_min(leaf, method=method, kernel=kernel)
        (grad,) = torch.autograd.grad((eigenvalues * g_l).sum() + (q * g_q).sum(), leaf)
        assert torch.equal(grad, grad.mT)
        grads.append(grad)
    # Relative to the largest entry: near l1 = l2 the q-gradient is ~1 / gap = 1e5 and the two
    # solvers' q differ by ~eps / gap (observed: 6e-7 absolute).
    scale = grads[-1].abs().max()
    for grad in grads[:-1]:
        torch.testing.assert_close(grad, grads[-1], atol=1e-10 * scale, rtol=0)


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_vmap_of_grad_has_no_per_sample_fallback(method, kernel):
    """Every op of both backwards has a torch.func batching rule: vmap(grad) makes no
    "performance drop" warning (the per-sample fallback loop) and matches autograd."""
    A = sym_randn(6, 46)
    g = torch.randn(6, 4, generator=gen(47), dtype=F64)

    def loss(a: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        eigenvalues, q = sym4_eigh_min(a, method=method, check=False, kernel=kernel)
        return (q * w).sum() + eigenvalues.square().sum()

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vmapped = torch.func.vmap(torch.func.grad(loss))(A, g)
    leaf = A.clone().requires_grad_()
    (ref,) = torch.autograd.grad(loss(leaf, g), leaf)
    torch.testing.assert_close(vmapped, ref, atol=1e-12, rtol=0)


def test_unknown_method_raises():
    with pytest.raises(ValueError, match="method"):
        sym4_eigh_min(torch.eye(4), method="qr")


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_reads_the_upper_triangle_only(method, kernel):
    A = sym_randn(1500, 37)
    garbage = A + torch.randn(1500, 4, 4, generator=gen(38), dtype=F64).tril(-1)
    l1, q1 = sym4_eigh_min(A, method=method, kernel=kernel)
    l2, q2 = sym4_eigh_min(garbage, method=method, check=False, kernel=kernel)
    assert torch.equal(l1, l2) and torch.equal(q1, q2)


@pytest.mark.parametrize("kernel", PATHS)
def test_non_contiguous_input(kernel):
    A = sym_randn(64, 16)
    strided = A.transpose(-1, -2).contiguous().transpose(-1, -2)[::2]  # same values, odd strides
    l1, q1 = sym4_eigh_min(strided, method="jacobi", kernel=kernel)
    l2, q2 = sym4_eigh_min(A[::2].contiguous(), method="jacobi", kernel=kernel)
    assert torch.equal(l1, l2) and torch.equal(q1, q2)


# ---------------------------------------------------------------------------------------------
# sign convention
# ---------------------------------------------------------------------------------------------


def test_canonical_sign_is_quat_canonical():
    """The fused sign rule equals quat_canonical, ties (w = 0, ...) and the zero vector included."""
    q = torch.randn(4096, 4, generator=gen(17))
    q[::2, 3] = 0.0
    q[::4, 0] = 0.0
    q[::8, 1] = 0.0
    q[::16, 2] = 0.0
    q[1::16] = -0.0
    q[3::32] = torch.tensor([0.0, 0.0, -1.0, 0.0])
    for dtype in DTYPES:
        qd = q.to(dtype)
        sign = _canonical_sign(qd.t().contiguous()).t()
        assert torch.equal(qd * sign, quat_canonical(qd))


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_output_sign_is_canonical(method, kernel):
    A = torch.cat((sym_randn(500, 18), a_from_quat(torch.eye(4, dtype=F64))))  # w = 0 ties
    _, q = sym4_eigh_min(A, method=method, kernel=kernel)
    assert torch.equal(q, quat_canonical(q))
    assert (q[..., 3] >= 0).all()


# ---------------------------------------------------------------------------------------------
# gradients
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("output", [0, 1], ids=["eigenvalues", "q"])
def test_gradcheck_through_a_from_vec(output, kernel):
    theta = torch.randn(4, 10, generator=gen(19), dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: sym4_eigh_min(a_from_vec(t), method="jacobi", kernel=kernel)[output], (theta,)
    )


@pytest.mark.parametrize("kernel", PATHS)
def test_gradcheck_both_outputs(kernel):
    theta = torch.randn(3, 10, generator=gen(20), dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: sym4_eigh_min(a_from_vec(t), method="jacobi", kernel=kernel), (theta,)
    )


@pytest.mark.parametrize("kernel", PATHS)
def test_gradient_matches_eigh_and_is_symmetric(kernel):
    A = sym_randn(256, 21).requires_grad_()
    g_l = torch.randn(256, 4, generator=gen(22), dtype=F64)
    g_q = torch.randn(256, 4, generator=gen(23), dtype=F64)
    eigenvalues, q = sym4_eigh_min(A, method="jacobi", kernel=kernel)
    (grad,) = torch.autograd.grad((eigenvalues * g_l).sum() + (q * g_q).sum(), A)
    A2 = A.detach().requires_grad_()
    L, V = torch.linalg.eigh(A2)
    (ref,) = torch.autograd.grad((L * g_l).sum() + (quat_canonical(V[..., 0]) * g_q).sum(), A2)
    ref = (ref + ref.mT) / 2  # eigh's gradient, symmetrised
    torch.testing.assert_close(grad, ref, atol=1e-9, rtol=1e-9)
    assert torch.equal(grad, grad.mT)


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", ["l1_eq_l2", "c_identity", "zero", "i_minus_qqT", "near_l1_eq_l2"])
def test_gradient_finite_where_eigenvalues_coincide(kind, dtype, method, kernel):
    q0 = random_quat((8,), generator=gen(24), dtype=F64)
    if kind == "l1_eq_l2":
        lam = torch.tensor([1.0, 1.0, 2.0, 3.0], dtype=F64).expand(8, 4)
        A = torch.cat((rotated_diag(lam, 25), torch.diag_embed(lam)))
    elif kind == "c_identity":
        A = torch.eye(4, dtype=F64) * torch.tensor([2.0, -3.0, 1e-6, 1e6], dtype=F64)[:, None, None]
    elif kind == "zero":
        A = torch.zeros(3, 4, 4, dtype=F64)
    elif kind == "i_minus_qqT":
        A = a_from_quat(q0)
    else:  # l2 - l1 = 1e-12 ||A||, far below gap_eps
        lam = torch.tensor([0.0, 1e-12, 0.5, 1.0], dtype=F64).expand(8, 4)
        A = rotated_diag(lam, 26)
    A = A.to(dtype).requires_grad_()
    eigenvalues, q = sym4_eigh_min(A, method=method, kernel=kernel)
    loss = (q * torch.arange(1.0, 5.0, dtype=dtype)).sum() + eigenvalues.square().sum()
    (grad,) = torch.autograd.grad(loss, A)
    assert torch.isfinite(grad).all()
    # The clamp bounds the q-gradient by |g_q| / (gap_eps (l4 - l1)) (+ the eigenvalue part).
    spread = (eigenvalues[..., 3] - eigenvalues[..., 0]).detach()
    bound = torch.where(spread > 0, 30.0 / (1e-6 * spread), torch.full_like(spread, 30.0))
    bound = bound + 2 * eigenvalues.detach().abs().sum(-1)
    assert (grad.flatten(-2).norm(dim=-1) <= 1.01 * bound).all()


@pytest.mark.parametrize("kernel", PATHS)
def test_gap_eps_sets_the_clamp(kernel):
    """Near l1 = l2 the q-gradient scales as 1 / gap_eps once the gap falls below the clamp."""
    lam = torch.tensor([[0.0, 1e-12, 0.5, 1.0]], dtype=F64)
    A = rotated_diag(lam, 27).requires_grad_()
    g = torch.tensor([[0.3, -0.5, 0.2, 0.7]], dtype=F64)
    norms = []
    for eps in (1e-4, 1e-6):
        _, q = sym4_eigh_min(A, gap_eps=eps, method="jacobi", kernel=kernel)
        (grad,) = torch.autograd.grad((q * g).sum(), A)
        norms.append(grad.norm().item())
    assert norms[1] == pytest.approx(100 * norms[0], rel=1e-4)


@pytest.mark.parametrize(
    ("method", "kernel"),
    [*SOLVERS, pytest.param("jacobi", "triton", marks=NO_TRITON, id="jacobi-triton")],
)
def test_gradient_does_not_depend_on_a_multiple_of_the_identity(method, kernel):
    """A + cI has A's eigenvectors and gaps, so the same q-gradient (and eigenvalue gradient):
    the gap clamp is relative to l4 - l1, not to ||A||_2 (before: with c = 2^20 the clamp
    gap_eps ||A + cI||_2 ~ 1 replaced the gap 1e-4 and the q-gradient came out 1e4 times too
    small; the A head's losses do not depend on the trace, which can drift). gradcheck at A + cI.
    The diagonal is rounded to multiples of 2^-30, so that A + cI is exact in float64."""
    lam = torch.tensor([0.0, 1e-4, 0.5, 1.0], dtype=F64).expand(16, 4)  # l2 - l1 = 1e-4 (l4 - l1)
    A = rotated_diag(lam, 52)
    A = (A + A.mT) / 2
    A.diagonal(dim1=-2, dim2=-1).copy_(A.diagonal(dim1=-2, dim2=-1).mul(2**30).round() / 2**30)
    g_l = torch.randn(16, 4, generator=gen(53), dtype=F64)
    g_q = torch.randn(16, 4, generator=gen(54), dtype=F64)
    grads = []
    for c in (0.0, 2.0**10, -(2.0**20)):
        leaf = (A + c * torch.eye(4, dtype=F64)).requires_grad_()
        eigenvalues, q = sym4_eigh_min(leaf, method=method, kernel=kernel)
        (grad,) = torch.autograd.grad((eigenvalues * g_l).sum() + (q * g_q).sum(), leaf)
        grads.append(grad)
    # The saved eigenvalues of A + cI are rounded to eps c: the gaps, and so the q-gradient
    # (~1e4 here), carry a relative error up to ~eps c / 1e-4 = 2e-6 for c = 2^20.
    scale = grads[0].abs().max()
    for grad in grads[1:]:
        torch.testing.assert_close(grad, grads[0], atol=1e-5 * scale, rtol=0)
    if kernel != "triton":  # the interpreter is too slow for gradcheck's many calls
        theta = torch.randn(3, 10, generator=gen(55), dtype=F64).requires_grad_()
        eye = 1e3 * torch.eye(4, dtype=F64)
        assert torch.autograd.gradcheck(
            lambda t: sym4_eigh_min(a_from_vec(t) + eye, method=method, kernel=kernel), (theta,)
        )


def test_eigh_backward_is_nan_where_ours_is_finite():
    """Why the custom backward exists: eigh's gradient is NaN/Inf for A = I - q q^T (l2 = l3)."""
    A = a_from_quat(random_quat((4,), generator=gen(28), dtype=F64)).requires_grad_()
    L, V = torch.linalg.eigh(A)
    (ref,) = torch.autograd.grad(quat_canonical(V[..., 0]).sum() + L.sum(), A)
    eigenvalues, q = sym4_eigh_min(A)
    (grad,) = torch.autograd.grad(q.sum() + eigenvalues.sum(), A)
    assert not torch.isfinite(ref).all()
    assert torch.isfinite(grad).all()


@pytest.mark.parametrize("kernel", PATHS)
def test_first_order_only(kernel):
    """The backward is once-differentiable: with create_graph the gradient is a constant."""
    A = sym_randn(2, 29).requires_grad_()
    _, q = sym4_eigh_min(A, kernel=kernel)
    (grad,) = torch.autograd.grad(q.sum(), A, create_graph=True)
    assert torch.isfinite(grad).all() and not grad.requires_grad


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("poison", "word"),
    [("nan", "NaN"), ("inf", "Inf"), ("asym", "not symmetric")],
)
def test_check_names_problem_and_first_index(poison, word):
    A = sym_randn(6, 30).reshape(2, 3, 4, 4).clone()
    for index in ((1, 2), (1, 0)):  # the first offending index in row-major order is (1, 0)
        if poison == "nan":
            A[index][2, 1] = math.nan
        elif poison == "inf":
            A[index][0, 0] = -math.inf
        else:
            A[index][0, 3] += 1e-4 * A[index].abs().max()
    with pytest.raises(ValueError, match=re.escape(word)) as info:
        sym4_eigh_min(A)
    assert "(1, 0)" in str(info.value)
    with pytest.raises(ValueError, match=re.escape("(1, 0)")):
        validate_sym4(A)
    # With the check off there is no check: the Jacobi solver just propagates NaN/Inf.
    eigenvalues, _ = sym4_eigh_min(A, check=False, method="jacobi")
    assert eigenvalues.shape == (2, 3, 4)


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_nan_and_inf_propagate_to_their_matrix_only(kernel, dtype):
    """NaN in the upper triangle (the part that is read) makes that matrix's eigenvalues, q and
    gradient NaN; Inf gives that matrix no defined answer. Every other matrix of the batch is
    solved as if alone."""
    A = sym_randn(40, 48).to(dtype)
    nan, inf = [3, 39], [17, 18]
    A[3, 0, 2] = math.nan
    A[39, 3, 3] = math.nan
    A[17, 1, 1] = math.inf
    A[18, 2, 3] = -math.inf
    A = A.requires_grad_()
    eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
    good = torch.ones(40, dtype=torch.bool)
    good[nan + inf] = False
    assert torch.isnan(eigenvalues[nan]).all() and torch.isnan(q[nan]).all()
    clean_l, clean_q = sym4_eigh_min(A.detach()[good], method="jacobi", kernel=kernel)
    assert torch.equal(eigenvalues[good], clean_l) and torch.equal(q[good], clean_q)
    (grad,) = torch.autograd.grad(eigenvalues.sum() + q.sum(), A)
    assert torch.isnan(grad[nan]).all() and torch.isfinite(grad[good]).all()


def test_check_tolerates_rounding_asymmetry():
    A = sym_randn(5, 31)
    A[2, 0, 1] *= 1 + 1e-9
    validate_sym4(A)
    sym4_eigh_min(A)


def test_check_reports_the_first_of_mixed_problems():
    A = sym_randn(5, 32)
    A[3, 1, 1] = math.nan
    A[1, 0, 2] += 1.0
    with pytest.raises(ValueError, match=r"\(1,\).*not symmetric"):
        sym4_eigh_min(A)


@pytest.mark.parametrize(
    "bad",
    [
        torch.zeros(3, 3),
        torch.zeros(2, 4, 3),
        torch.zeros(4),
        torch.zeros(2, 4, 4, dtype=torch.float16),
    ],
)
def test_wrong_shape_or_dtype_raises_even_without_check(bad):
    with pytest.raises(ValueError, match="expected"):
        sym4_eigh_min(bad, check=False)


def test_rounds_must_be_positive():
    with pytest.raises(ValueError, match="rounds"):
        sym4_eigh_min(torch.eye(4), rounds=0)


@pytest.mark.parametrize("gap_eps", [0.0, -1.0, 1.0, float("nan")])
def test_gap_eps_must_lie_between_0_and_1(gap_eps):
    """gap_eps <= 0 let the backward divide by a zero gap: NaN gradients for diag(0, 0, 1, 1)."""
    with pytest.raises(ValueError, match=r"gap_eps must lie in \(0, 1\)"):
        sym4_eigh_min(torch.diag(torch.tensor([0.0, 0.0, 1.0, 1.0])), gap_eps=gap_eps)


def test_default_round_counts():
    assert DEFAULT_ROUNDS == {F32: 12, F64: 14}


# ---------------------------------------------------------------------------------------------
# properties
# ---------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    entries=_upper_triangles(1e3, width=64),
    dtype=st.sampled_from(DTYPES),
)
@example(entries=[0.0] * 9 + [3.348262739711181e-43], dtype=F32)  # found by CI: a subnormal
def test_property_eigenpair(entries, dtype):
    A = a_from_vec(torch.tensor(entries, dtype=F64)).to(dtype)
    eigenvalues, q = sym4_eigh_min(A)
    L = torch.linalg.eigh(A.to(F64)).eigenvalues
    norm = max(L.abs().max().item(), 1e-300)
    assert (eigenvalues[1:] >= eigenvalues[:-1]).all()
    assert ((eigenvalues.to(F64) - L).abs().max() / norm) <= 30 * EPS[dtype]
    assert abs(q.to(F64).norm().item() - 1) <= 10 * EPS[dtype]
    resid = A.to(F64) @ q.to(F64) - eigenvalues[0].to(F64) * q.to(F64)
    assert resid.norm().item() / norm <= 30 * EPS[dtype]
    assert torch.equal(q, quat_canonical(q))


# Below the smallest normal number of each dtype, and the smallest subnormal one.
SUBNORMAL = {F32: (2.0**-140, 2.0**-149), F64: (2.0**-1060, 2.0**-1074)}


@pytest.mark.parametrize(("method", "kernel"), FORWARDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_a_matrix_whose_largest_entry_is_subnormal_keeps_its_eigenvalues(method, kernel, dtype):
    """The kernels scale a matrix by a power of two before the rotations and back after; with a
    subnormal largest entry the factor back was 2^-BIAS, which is no normal number, and every
    eigenvalue came out 0 (found by the property test above); the eager Jacobi's single factor
    2^-e overflowed to Inf (NaN results). A diagonal matrix needs no rotation, so its
    eigenvalues come back exactly."""
    m, smallest = SUBNORMAL[dtype]
    diagonal = torch.tensor(
        [[3.0 * m, -m, 2.0 * m, 0.0], [0.0, 0.0, 0.0, m], [0.0, 0.0, 0.0, smallest]], dtype=F64
    )  # exactly representable in `dtype`
    A = torch.diag_embed(diagonal).to(dtype)
    eigenvalues, q = sym4_eigh_min(A, method=method, kernel=kernel)
    expected = diagonal.sort(-1).values.to(dtype)
    assert torch.equal(eigenvalues, expected) and bool((expected != 0).any(-1).all())
    modes = torch.tensor([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [1.0, 0, 0, 0]], dtype=dtype)
    assert torch.equal(q.abs(), modes)


def _power_of_two_scaling_is_exact(entries: list[int], s: int, dtype, kernel: str) -> None:
    """K and K 2^s (K integer, |K| <= 64: K 2^s exact, subnormal or near the largest finite
    number at the ends of s) in one call: the Jacobi paths scale each matrix by a power of two
    first, so the same q bit for bit, and the eigenvalues of K times 2^s rounded once (Inf
    where that overflows)."""
    K = a_from_vec(torch.tensor(entries, dtype=F64))
    A = torch.stack((K, K * 2.0**s)).to(dtype)
    assert torch.equal(A[1].to(F64), K * 2.0**s)  # exact
    eigenvalues, q = sym4_eigh_min(A, method="jacobi", kernel=kernel)
    assert torch.equal(q[1], q[0]), (q, s)
    expected = (eigenvalues[0].to(F64) * 2.0**s).to(dtype)
    assert torch.equal(eigenvalues[1], expected), (eigenvalues, expected, s)


# s with K 2^s exact and finite for |K| <= 64 = 2^6: the smallest subnormal up to 2^(max exp - 6)
SCALE_EXPONENTS = {F32: (-149, 121), F64: (-1074, 1017)}


@st.composite
def _scaled_integer_matrices(draw):
    dtype = draw(st.sampled_from(DTYPES))
    low, high = SCALE_EXPONENTS[dtype]
    edge = st.one_of(st.integers(low, low + 30), st.integers(high - 30, high))
    s = draw(st.one_of(edge, st.integers(low, high)))
    entries = draw(st.lists(st.integers(-64, 64), min_size=10, max_size=10))
    return entries, s, dtype


@settings(max_examples=50, deadline=None)
@given(case=_scaled_integer_matrices())
@example(case=([3, 0, 0, 0, -1, 0, 0, 2, 0, 0], -140, F32))  # the review's subnormal matrix
@example(case=([64, 1, -2, 3, 5, 0, 7, -64, 1, 64], 121, F32))  # largest entry 2^127
@example(case=([64, 1, -2, 3, 5, 0, 7, -64, 1, 64], -1074, F64))
@example(case=([64, 1, -2, 3, 5, 0, 7, -64, 1, 64], 1017, F64))
@pytest.mark.parametrize("kernel", PATHS)
def test_property_power_of_two_scaling_is_exact(kernel, case):
    """The docstring's "exact for any finite input": before, the eager Jacobi scaled by
    exp2(-e) and exp2(e), which overflow for a subnormal or a huge largest entry (NaN/Inf)."""
    _power_of_two_scaling_is_exact(*case, kernel)


@NO_TRITON
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # numpy: Inf, expected
@settings(max_examples=12, deadline=None)  # the interpreter: ~0.25 s per call
@given(case=_scaled_integer_matrices())
@example(case=([64, 1, -2, 3, 5, 0, 7, -64, 1, 64], 121, F32))
@example(case=([64, 1, -2, 3, 5, 0, 7, -64, 1, 64], -1074, F64))
def test_property_power_of_two_scaling_is_exact_triton(case):
    _power_of_two_scaling_is_exact(*case, "triton")


CUDA_PATHS = [
    pytest.param(
        "triton",
        marks=pytest.mark.skipif(not ops.triton_available(), reason="triton is not installed"),
    ),
    "eager",
]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("kernel", CUDA_PATHS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_cuda_matches_cpu(case_data, dtype, kernel):
    A = sym_randn(5000, 33).to(dtype)
    g_l = torch.randn(5000, 4, generator=gen(39), dtype=dtype)
    g_q = torch.randn(5000, 4, generator=gen(40), dtype=dtype)
    leaf = A.clone().requires_grad_()
    l_cpu, q_cpu = sym4_eigh_min(leaf, method="jacobi")
    (grad_cpu,) = torch.autograd.grad((l_cpu * g_l).sum() + (q_cpu * g_q).sum(), leaf)
    A_cuda = A.cuda().requires_grad_()
    l_gpu, q_gpu = sym4_eigh_min(A_cuda, method="jacobi", kernel=kernel)
    tol = 1e-5 if dtype == F32 else 1e-12
    torch.testing.assert_close(l_gpu.cpu(), l_cpu.detach(), atol=tol, rtol=tol)
    torch.testing.assert_close(q_gpu.cpu(), q_cpu.detach(), atol=100 * tol, rtol=0)
    (grad,) = torch.autograd.grad((l_gpu * g_l.cuda()).sum() + (q_gpu * g_q.cuda()).sum(), A_cuda)
    assert grad.is_cuda and torch.isfinite(grad).all()
    # Gaussian matrices: a few have l2 - l1 ~ 1e-3, where the q-gradient grows as 1 / gap.
    scale = grad_cpu.abs().max()
    torch.testing.assert_close(
        grad.cpu(), grad_cpu, atol=(1e-3 if dtype == F32 else 1e-10) * scale, rtol=0
    )
    for case in CASES:  # the accuracy bounds on CUDA too
        A = case_data[case][:5000].to(dtype)
        eigenvalues, q = sym4_eigh_min(A.cuda(), check=False, method="jacobi", kernel=kernel)
        ours = errors(A.to(F64), eigenvalues.cpu(), q.cpu())
        for key, bound in BOUNDS[dtype].items():
            assert ours[key] <= bound, (case, key, ours)
