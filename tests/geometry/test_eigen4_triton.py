"""rotlearn.geometry.eigen4.gpu: the Triton kernels of the A layer (issue 26).

On this CPU the kernels run in Triton's interpreter (`kernel="triton"` on CPU tensors): the same
kernel source as on CUDA, against float64 torch.linalg.eigh on the hard spectra of the eigen4 tests
(repeated eigenvalues, A = cI and A = 0, gaps of 1e-3, scales 1e-4 ... 1e4, NaN), forward and
gradient, and one launch per call each way. The interpreter runs the programs one after another,
so the batches are small (one or two programs of 128 matrices). With CUDA the same checks run on
the GPU, plus the launch count from torch.profiler and autocast. Skipped where triton is absent
(`pip install rotlearn[gpu]`; CI installs it).
"""

from __future__ import annotations

import collections
import math

import pytest
import torch

triton = pytest.importorskip("triton", reason="triton is not installed (pip install rotlearn[gpu])")

from rotlearn.geometry import a_from_quat, quat_canonical, random_quat, sym4_eigh_min  # noqa: E402
from rotlearn.geometry.eigen4 import cpu as cpu_kernel  # noqa: E402
from rotlearn.geometry.eigen4 import eager, gpu, ops  # noqa: E402
from tests.conftest import gen  # noqa: E402
from tests.geometry.test_eigen4 import BOUNDS, errors, rotated_diag, sym_randn, wahba_a  # noqa: E402

F32, F64 = torch.float32, torch.float64
DEVICES = [
    "cpu",
    pytest.param(
        "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
    ),
]
PER_CASE = 16


def hard_spectra() -> dict[str, torch.Tensor]:
    """(PER_CASE, 4, 4) float64 matrices per case."""
    n = PER_CASE
    diag = lambda *lam: torch.tensor(lam, dtype=F64).expand(n, 4)  # noqa: E731
    scales = torch.logspace(-4, 4, n, dtype=F64)[:, None, None]
    return {
        "l1_eq_l2": rotated_diag(diag(1.0, 1.0, 2.0, 3.0), 1),
        "l2_eq_l3_eq_l4": a_from_quat(random_quat((n,), generator=gen(2), dtype=F64)),
        "c_identity": torch.eye(4, dtype=F64) * torch.linspace(-3, 3, n, dtype=F64)[:, None, None],
        "zero_and_diagonal": torch.cat((torch.zeros(n // 2, 4, 4, dtype=F64),
                                        torch.diag_embed(diag(3.0, -1.0, 2.0, -1.0)[: n // 2]))),
        "gap_1e-3": rotated_diag(diag(0.0, 1e-3, 0.5, 1.0), 3),
        "scales_1e-4_1e4": scales * sym_randn(n, 4),
        "gauss": sym_randn(n, 5),
        "wahba": wahba_a(n, 6)[0],
    }  # fmt: skip


@pytest.fixture(scope="module")
def spectra() -> dict[str, torch.Tensor]:
    return hard_spectra()


def _solve(A: torch.Tensor, device: str, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    eigenvalues, q = sym4_eigh_min(A.to(device), method="jacobi", kernel="triton", **kw)
    return eigenvalues.cpu(), q.cpu()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_forward_against_float64_eigh_on_hard_spectra(spectra, dtype, device):
    """Every case within the accuracy bounds of sym4_eigh_min (angle where l2 - l1 >= 0.01
    (l4 - l1), else the residual), q canonical, eigenvalues ascending."""
    A = torch.cat(list(spectra.values())).to(dtype)  # 128 matrices: one program
    eigenvalues, q = _solve(A, device, check=False)
    assert eigenvalues.dtype == dtype and q.dtype == dtype
    assert (eigenvalues[:, 1:] >= eigenvalues[:, :-1]).all()
    assert torch.equal(q, quat_canonical(q))
    zero = A.flatten(-2).abs().amax(-1) == 0  # A = 0: eigenvalues 0, q = (1, 0, 0, 0)
    assert zero.any() and (eigenvalues[zero] == 0).all()
    assert torch.equal(
        q[zero], torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(int(zero.sum()), 4)
    )
    for i, case in enumerate(spectra):
        rows = torch.zeros_like(zero)
        rows[i * PER_CASE : (i + 1) * PER_CASE] = True
        rows &= ~zero
        ours = errors(A[rows].to(F64), eigenvalues[rows], q[rows])
        for key, bound in BOUNDS[dtype].items():
            assert ours[key] <= bound, (case, key, ours)


@pytest.mark.parametrize("device", DEVICES)
def test_matches_the_cpu_paths(spectra, device):
    """The Triton Jacobi computes the C kernel's and the eager solver's rotations: the same
    eigenpairs to rounding (float64)."""
    A = torch.cat(list(spectra.values()))
    l_t, q_t = _solve(A, device)
    l_e, q_e = sym4_eigh_min(A, method="jacobi", kernel="eager")
    norm = l_e.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    assert ((l_t - l_e).abs() / norm).max() <= 1e-14
    L = torch.linalg.eigh(A).eigenvalues
    separated = (L[:, 1] - L[:, 0]) >= 0.01 * (L[:, 3] - L[:, 0])
    assert (q_t[separated] - q_e[separated]).abs().max() <= 1e-12
    if device == "cpu" and cpu_kernel.available():
        # The interpreter computes with numpy's IEEE operations in the kernel's order, as the C
        # kernel does (no FMA contraction there): the same bits, in both dtypes.
        for dtype in (F32, F64):
            triton_out = _solve(A.to(dtype), device)
            c_out = sym4_eigh_min(A.to(dtype), method="jacobi", kernel="cpu")
            for x, y in zip(triton_out, c_out, strict=True):
                assert torch.equal(x, y)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_backward_kernel_is_the_eager_formula(spectra, dtype, device):
    """On the same saved eigenpairs the backward kernel gives eager.backward's gradient (the
    formula of sym4_eigh_min), also with one output's gradient absent."""
    A = torch.cat(list(spectra.values())).to(dtype)
    eigenvalues, _, V = eager.jacobi_forward(A, 12 if dtype == F32 else 14)
    g_l = torch.randn(A.shape[0], 4, generator=gen(7), dtype=dtype)
    g_q = torch.randn(A.shape[0], 4, generator=gen(8), dtype=dtype)
    tol = 2e-6 if dtype == F32 else 1e-14
    for gl, gq in ((g_l, g_q), (None, g_q), (g_l, None)):
        ref = eager.backward(gl, gq, eigenvalues, V, 1e-6)
        dev = lambda x: None if x is None else x.to(device)  # noqa: E731
        got = gpu.backward(dev(gl), dev(gq), eigenvalues.to(device), V.to(device), 1e-6).cpu()
        assert torch.equal(got, got.mT)
        scale = ref.flatten(-2).abs().amax(-1).clamp_min(1)[:, None, None]
        assert ((got - ref).abs() / scale).max() <= tol, (gl is None, gq is None)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_gradient_against_float64_eigh_and_finite_where_eigenvalues_coincide(
    spectra, dtype, device
):
    """Through sym4_eigh_min: finite everywhere (eigh's own gradient is NaN/Inf for repeated
    eigenvalues) and, where the spectrum is well separated, float64 eigh's gradient."""
    A = torch.cat(list(spectra.values())).to(dtype)
    g_l = torch.randn(A.shape[0], 4, generator=gen(9), dtype=dtype)
    g_q = torch.randn(A.shape[0], 4, generator=gen(10), dtype=dtype)
    leaf = A.to(device).requires_grad_()
    eigenvalues, q = sym4_eigh_min(leaf, method="jacobi", kernel="triton")
    (grad,) = torch.autograd.grad(
        (eigenvalues * g_l.to(device)).sum() + (q * g_q.to(device)).sum(), leaf
    )
    grad = grad.cpu()
    assert torch.isfinite(grad).all() and torch.equal(grad, grad.mT)
    A64 = A.to(F64).requires_grad_()
    L, V = torch.linalg.eigh(A64)
    ref_loss = (L * g_l.to(F64)).sum() + (quat_canonical(V[..., 0]) * g_q.to(F64)).sum()
    (ref,) = torch.autograd.grad(ref_loss, A64)
    ref = (ref + ref.mT) / 2
    gaps = (L[:, 1:] - L[:, :-1]).detach().min(-1).values
    spread = (L[:, 3] - L[:, 0]).detach()
    separated = (gaps >= 0.05 * spread) & (spread > 0)
    scale = ref[separated].flatten(-2).abs().amax(-1)[:, None, None]
    err = ((grad[separated].to(F64) - ref[separated]).abs() / scale).max()
    assert err <= (1e-3 if dtype == F32 else 1e-10), err


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_nan_propagates_to_its_matrix_only(dtype, device):
    A = sym_randn(40, 11).to(dtype)
    A[7, 1, 2] = math.nan
    A[31, 0, 0] = math.nan
    bad = torch.zeros(40, dtype=torch.bool)
    bad[[7, 31]] = True
    leaf = A.to(device).requires_grad_()
    eigenvalues, q = sym4_eigh_min(leaf, check=False, method="jacobi", kernel="triton")
    (grad,) = torch.autograd.grad(eigenvalues.sum() + q.sum(), leaf)
    eigenvalues, q, grad = eigenvalues.cpu(), q.cpu(), grad.cpu()
    assert torch.isnan(eigenvalues[bad]).all() and torch.isnan(q[bad]).all()
    assert torch.isnan(grad[bad]).all()
    assert torch.isfinite(eigenvalues[~bad]).all() and torch.isfinite(grad[~bad]).all()
    clean_l, clean_q = _solve(A[~bad], device)
    assert torch.equal(eigenvalues[~bad], clean_l) and torch.equal(q[~bad], clean_q)


@pytest.mark.parametrize("device", DEVICES)
def test_strided_input_and_batch_shapes(device):
    A = sym_randn(24, 12).to(F32)
    strided = A.transpose(-1, -2).contiguous().transpose(-1, -2)[::2]  # same values, odd strides
    l1, q1 = _solve(strided, device)
    l2, q2 = _solve(A[::2].contiguous(), device)
    assert torch.equal(l1, l2) and torch.equal(q1, q2)
    eigenvalues, q = _solve(A.reshape(2, 3, 4, 4, 4), device)
    assert eigenvalues.shape == (2, 3, 4, 4) and q.shape == (2, 3, 4, 4)
    empty_l, empty_q = _solve(A[:0], device)
    assert empty_l.shape == (0, 4) and empty_q.shape == (0, 4)


def test_one_launch_per_call_each_way(monkeypatch):
    """Forward+backward of the A layer on the Triton path: one forward launch, one backward
    launch, whatever the batch (in the interpreter; on CUDA the profiler test below)."""
    interpreted = gpu._interpreted()
    launches = collections.Counter()
    launch = interpreted._launch

    def counting(kernel, grid, device, *args, **meta):
        launches[kernel.__name__] += 1
        return launch(kernel, grid, device, *args, **meta)

    monkeypatch.setattr(interpreted, "_launch", counting)
    for batch in (1, 200):
        launches.clear()
        A = sym_randn(batch, 13).to(F32).requires_grad_()
        eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel="triton")
        torch.autograd.grad(eigenvalues.sum() + q.sum(), A)
        assert launches == {"_forward_kernel": 1, "_backward_kernel": 1}, (batch, launches)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("batch", [4096, 65536])
def test_cuda_two_kernel_launches_per_forward_backward(batch):
    """torch.profiler on CUDA: forward+backward of sym4_eigh_min is two kernel launches in all
    (the Triton forward and backward), where the eager Jacobi launches hundreds."""
    from torch.profiler import ProfilerActivity, profile

    A = sym_randn(batch, 14).to(F32).cuda().requires_grad_()
    g_l = torch.randn(batch, 4, device="cuda")
    g_q = torch.randn(batch, 4, device="cuda")

    def step(kernel):
        eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
        torch.autograd.grad((eigenvalues, q), A, (g_l, g_q))

    counts = {}
    for kernel in ("triton", "eager"):
        step(kernel)  # compile / warm up
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            step(kernel)
            torch.cuda.synchronize()
        names = [e.name for e in prof.events() if e.device_type.name == "CUDA"]
        counts[kernel] = names
    assert len(counts["triton"]) == 2, counts["triton"]
    assert sum("_forward_kernel" in n for n in counts["triton"]) == 1, counts["triton"]
    assert sum("_backward_kernel" in n for n in counts["triton"]) == 1, counts["triton"]
    assert len(counts["eager"]) > 100, len(counts["eager"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("reduced", [torch.bfloat16, torch.float16])
def test_cuda_autocast_runs_float32(reduced):
    """Under CUDA autocast the Triton kernels compute and return float32: the float32 result of
    the rounded input; gradients reach the reduced-precision input."""
    A = sym_randn(256, 15).to(reduced).cuda().requires_grad_()
    with torch.autocast("cuda", dtype=reduced):
        eigenvalues, q = sym4_eigh_min(A, check=False)
    assert eigenvalues.dtype == F32 and q.dtype == F32
    ref_l, ref_q = sym4_eigh_min(A.detach().float(), check=False)
    assert torch.equal(eigenvalues, ref_l) and torch.equal(q, ref_q)
    (grad,) = torch.autograd.grad(q.sum(), A)
    assert grad.dtype == reduced and torch.isfinite(grad).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("backend", ["aot_eager", pytest.param("inductor", marks=pytest.mark.slow)])
def test_cuda_compiles_to_one_graph(backend):
    from rotlearn.geometry import a_from_vec

    def layer(theta):
        return sym4_eigh_min(a_from_vec(theta), check=False)[1]

    torch._dynamo.reset()
    compiled = torch.compile(layer, backend=backend, fullgraph=True)
    theta = torch.randn(1024, 10, device="cuda", requires_grad=True)
    out = compiled(theta)
    (grad,) = torch.autograd.grad(out.sum(), theta)
    leaf = theta.detach().requires_grad_()
    ref = layer(leaf)
    (ref_grad,) = torch.autograd.grad(ref.sum(), leaf)
    torch.testing.assert_close(out, ref)
    torch.testing.assert_close(grad, ref_grad)


@pytest.mark.parametrize("method", ["jacobi", "eigh"])
def test_triton_path_compiles_to_one_graph_in_the_interpreter(method):
    """torch.compile(fullgraph=True, aot_eager) of the A layer on the Triton path, forward and
    backward (CPU tensors: the kernels in the interpreter), matches eager at two batch sizes."""
    from tests.geometry.test_eigen4_ops import _compiled_matches_eager

    _compiled_matches_eager(method, "triton", "aot_eager")


def _compile_for_sm90(kernel, signature: dict, constexprs: dict):
    """triton.compile for an sm_90 GPU (H100, H200) on this machine, which has none."""
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    source = ASTSource(fn=kernel, signature=signature, constexprs=constexprs)
    return triton.compile(source, target=GPUTarget("cuda", 90, 32))


@pytest.mark.parametrize("dtype", [F32, pytest.param(F64, marks=pytest.mark.slow)])
def test_kernels_compile_for_a_cuda_gpu_without_one(dtype):
    """The interpreter does not run Triton's compiler: compile both kernels to PTX and a cubin
    for sm_90 here (seconds, no GPU needed). float32 math must use IEEE-rounded sqrt and division
    (Triton's defaults are approximate), and the forward, all 4x4 in registers, must not spill."""
    import os
    import subprocess
    import tempfile

    name = "fp64" if dtype == F64 else "fp32"
    is64, block = dtype == F64, gpu.BLOCK[dtype]
    forward = _compile_for_sm90(
        gpu._forward_kernel,
        {"A": f"*{name}", "L": f"*{name}", "Q": f"*{name}", "V": f"*{name}", "n": "i32",
         "sb": "i32", "sr": "i32", "sc": "i32", "ROUNDS": "constexpr", "IS64": "constexpr",
         "BLOCK": "constexpr"},
        {"ROUNDS": 14 if is64 else 12, "IS64": is64, "BLOCK": block},
    )  # fmt: skip
    for has_gl, has_gq in ((True, True), (False, True), (True, False)):
        _compile_for_sm90(
            gpu._backward_kernel,
            {"GL": f"*{name}", "GQ": f"*{name}", "L": f"*{name}", "V": f"*{name}",
             "G": f"*{name}", "n": "i32", "GAP_EPS": "constexpr", "HAS_GL": "constexpr",
             "HAS_GQ": "constexpr", "IS64": "constexpr", "BLOCK": "constexpr"},
            {"GAP_EPS": 1e-6, "HAS_GL": has_gl, "HAS_GQ": has_gq, "IS64": is64, "BLOCK": block},
        )  # fmt: skip
    ptx = forward.asm["ptx"]
    assert ptx.count(f"sqrt.rn.f{name[2:]}") >= 2 * (14 if is64 else 12)
    assert "sqrt.approx" not in ptx and "div.full" not in ptx and "div.approx" not in ptx
    ptxas = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "ptxas")
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "forward.ptx")
        with open(path, "w") as file:
            file.write(ptx)
        done = subprocess.run(
            [ptxas, "-v", "--gpu-name", "sm_90a", path, "-o", os.devnull],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
    assert "0 bytes spill stores" in done.stderr + done.stdout, done.stderr


def test_auto_picks_triton_only_for_cuda_tensors():
    assert ops.resolve_kernel("auto", torch.device("cuda")) == "triton"
    assert ops.resolve_kernel("auto", torch.device("cpu")) in ("cpu", "eager")
