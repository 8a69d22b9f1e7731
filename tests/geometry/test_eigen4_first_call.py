"""The A layer's first call in a fresh process (issue 27).

ATen computes `torch.sqrt` (and exp, log, sin, cos, tanh, ...) of a contiguous CPU tensor with MKL's
vector math library (VML), one call per intra-op thread. On Intel CPUs VML's first call in a process
races between those threads: one thread's share of the array came back wrong (up to 2520 ulp) in 3
of 160 fresh processes on a 16-core Xeon (2 torch threads, after a LAPACK call). The Jacobi solver
took one square root per rotation, so a wrong root for half the batch turned into eigenvectors off
by 0.1 degrees. The solver now uses no op that ATen hands to MKL VML (the eager path only ATen's own
kernels, the fused CPU kernel the C library's sqrt):

- `test_no_mkl_vml_op_on_the_cpu_paths` checks that on every machine (it fails on the code before
  the fix, which called `aten.sqrt_`);
- the fresh-process tests run the issue's reproduction, with other first calls (the eigh path,
  float64, a batch just past a CPU chunk, CUDA where present), and require every result to equal a
  1-thread reference of the same process bit for bit, and the angle bound of `sym4_eigh_min`.
  The race needs an Intel CPU (AMD EPYC: 0 of 60 processes, before the fix), so on other CPUs
  they pass either way; they are the check for machines where it bites.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from rotlearn.geometry import a_from_vec, sym4_eigh_min
from rotlearn.geometry.eigen4 import cpu as cpu_kernel
from rotlearn.heads.symmetric import AHead
from tests.conftest import gen

# The ops that ATen 2.x computes with MKL VML on the CPU (ATen/cpu/vml.h, IMPLEMENT_VML_MKL), in
# place, out of place or out=.
VML_OPS = {
    "acos", "asin", "atan", "cos", "erf", "erfc", "erfinv", "exp", "log", "log10", "log2",
    "sin", "sqrt", "tan", "tanh", "trunc",
}  # fmt: skip


class _OpNames(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.names: set[str] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.add(func.overloadpacket.__name__.rstrip("_"))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("kernel", ["cpu", "eager"])
@pytest.mark.parametrize("method", ["jacobi", "eigh"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_mkl_vml_op_on_the_cpu_paths(method: str, dtype: torch.dtype, kernel: str) -> None:
    if kernel == "cpu" and not cpu_kernel.available():
        pytest.skip("no CPU kernel here")
    theta = torch.randn(64, 10, generator=gen(0), dtype=dtype, requires_grad=True)
    mode = _OpNames()
    with mode:
        eigenvalues, q = sym4_eigh_min(a_from_vec(theta), check=False, method=method, kernel=kernel)
        (q.sum() + eigenvalues.sum()).backward()
    assert mode.names, "no op was seen: the dispatch mode did not trace the solver"
    assert not mode.names & VML_OPS, sorted(mode.names & VML_OPS)


# One fresh process: a LAPACK call, then the first call of the layer with 2 threads, then the same
# call with 1 thread as the reference. Prints JSON.
PROBE = r"""
import json, math, sys, torch
from rotlearn.geometry import a_from_vec, quat_to_rotmat, sym4_eigh_min
from rotlearn.heads.symmetric import AHead
variant, device = sys.argv[1], sys.argv[2]
torch.set_num_threads(2)
batch = {"chunk": 32769}.get(variant, 4096)
dtype = torch.float64 if variant == "float64" else torch.float32
torch.linalg.qr(torch.randn(4096, 4, 4, dtype=torch.float64))  # any LAPACK call before
theta = torch.randn(batch, 10, generator=torch.Generator().manual_seed(7), dtype=dtype)
theta = theta.to(device)
def layer():
    if variant == "head":
        return AHead()(theta).q
    method = "eigh" if variant == "eigh" else "jacobi"
    kernel = "eager" if variant == "eager" else "auto"
    return sym4_eigh_min(a_from_vec(theta), check=False, method=method, kernel=kernel)[1]
with torch.no_grad():
    q = layer()
    torch.set_num_threads(1)
    q_ref = layer()
L, V = torch.linalg.eigh(a_from_vec(theta).double().cpu())
separated = (L[:, 1] - L[:, 0]) >= 0.01 * (L[:, 3] - L[:, 0])  # where the bound is documented
q_sep = q.cpu()[separated]
d = torch.linalg.matrix_norm(quat_to_rotmat(q_sep.double()) - quat_to_rotmat(V[separated][..., 0]))
deg = torch.rad2deg(2 * torch.asin((d / (2 * math.sqrt(2))).clamp(max=1)))
print(json.dumps({"bitwise": bool(torch.equal(q, q_ref)), "max_deg": deg.max().item(),
                  "over_1e-3": int((deg > 1e-3).sum())}))
"""
PROCESSES = 12
# sym4_eigh_min's documented angle bound (float32, spectra with l2 - l1 >= 0.01 (l4 - l1): 4095 of
# these 4096 Gaussian matrices, worst case 6e-4 deg on the eigh path, 9e-4 deg for float32
# torch.linalg.eigh; the other one has l2 - l1 = 4e-3 (l4 - l1), where q's error, ~eps (l4 - l1) /
# (l2 - l1), may exceed the bound: with seeds 8 and 9, up to 3e-3 deg on the eigh path, 6e-3 deg
# for torch.linalg.eigh itself); float64 is far below it.
BOUND_DEG = 1e-3


def _probe(variant: str, device: str) -> dict:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    done = subprocess.run(
        [sys.executable, "-c", PROBE, variant, device],
        capture_output=True, text=True, timeout=300, env=env, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _fresh_processes(variant: str, device: str = "cpu") -> None:
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda _: _probe(variant, device), range(PROCESSES)))
    wrong = [r for r in results if not r["bitwise"] or r["max_deg"] > BOUND_DEG]
    assert not wrong, f"{len(wrong)} of {PROCESSES} fresh processes wrong: {wrong}"


def test_first_call_in_fresh_processes_head() -> None:
    """The issue's reproduction (the A head, B = 4096, float32, 2 threads after a LAPACK call)."""
    _fresh_processes("head")


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["eigh", "float64", "chunk", "eager"])
def test_first_call_in_fresh_processes_other_paths(variant: str) -> None:
    """The same with the eigh path, float64, a batch just past the CPU chunk size (of the eager
    path; the fused kernel's thread split), and the eager path."""
    _fresh_processes(variant)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_first_call_in_fresh_processes_cuda() -> None:
    _fresh_processes("head", "cuda")


@pytest.mark.parametrize("kernel", ["auto", "eager"])
def test_head_result_is_independent_of_threads_and_batch_split(kernel: str) -> None:
    """In one process: 1, 2 and 3 threads, offsets, chunks and single matrices agree bit for bit
    (forward and gradient)."""
    theta = torch.randn(40000, 10, generator=gen(3))
    weight = torch.randn(40000, 4, generator=gen(4))
    threads = torch.get_num_threads()

    def solve(rows: slice) -> tuple[torch.Tensor, ...]:
        leaf = theta[rows].clone().requires_grad_()
        eigenvalues, q = sym4_eigh_min(
            a_from_vec(leaf), check=False, method="jacobi", kernel=kernel
        )
        (grad,) = torch.autograd.grad((q * weight[rows]).sum() + eigenvalues.sum(), leaf)
        return eigenvalues.detach(), q.detach(), grad

    try:
        torch.set_num_threads(1)
        reference = solve(slice(None))
        for count in (2, 3):
            torch.set_num_threads(count)
            for start, stop in ((0, 40000), (1, 40000), (17, 33000), (39990, 40000), (5, 6)):
                got = solve(slice(start, stop))
                for x, ref in zip(got, reference, strict=True):
                    assert torch.equal(x, ref[start:stop]), (count, start, stop)
        if kernel == "auto":
            head = AHead(solver="jacobi")
            assert torch.equal(head(theta[:4096]).q, reference[1][:4096])
    finally:
        torch.set_num_threads(threads)
