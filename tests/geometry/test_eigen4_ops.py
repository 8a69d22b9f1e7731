"""rotlearn.geometry.eigen4.ops: the registered operators, torch.compile, launches per call.

- opcheck (torch.library's own test of a custom op: schema, fake implementation, autograd
  registration, AOT dispatch) for both operators on every CPU path;
- torch.compile(fullgraph=True) of the A layer on every path and method, forward and backward:
  aot_eager here (dynamo's capture and AOT autograd, no C++ compiler), inductor marked slow;
- the work per call, counted with torch.profiler: the fused CPU path runs no ATen compute op
  (only its output allocations) and calls its kernel once forward and once backward, where the
  eager Jacobi runs hundreds of ops; under torch.compile the graph holds one op each way.
"""

from __future__ import annotations

import collections

import pytest
import torch
from torch.profiler import ProfilerActivity, profile

from rotlearn.geometry import a_from_vec, sym4_eigh_min
from rotlearn.geometry.eigen4 import cpu as cpu_kernel
from rotlearn.geometry.eigen4 import ops
from tests.conftest import gen
from tests.geometry.test_eigen4 import NO_CPU_KERNEL, PATHS, SOLVERS, sym_randn

# ---------------------------------------------------------------------------------------------
# the operators
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck_forward(method, kernel, dtype):
    A = sym_randn(16, 1).to(dtype).requires_grad_()
    rounds = 12 if dtype == torch.float32 else 14
    torch.library.opcheck(ops.sym4_eigh, (A, 1e-6, rounds, method, kernel))


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("with_grad", ["both", "eigenvalues", "q"])
def test_opcheck_backward(kernel, with_grad):
    eigenvalues, q, V = ops.sym4_eigh(sym_randn(16, 2), 1e-6, 14, "jacobi", kernel)
    g_l = None if with_grad == "q" else torch.randn(16, 4, generator=gen(3), dtype=torch.float64)
    g_q = None if with_grad == "eigenvalues" else torch.randn_like(q)
    torch.library.opcheck(ops.sym4_eigh_backward, (g_l, g_q, eigenvalues, V, 1e-6, kernel))


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_op_and_eager_route_give_the_same_numbers(method, kernel):
    """sym4_eigh_min runs the op's implementations directly in eager mode and the op itself under
    torch.func and torch.compile: the same functions, so the same bits, forward and backward."""
    A = sym_randn(64, 4)
    g_l = torch.randn(64, 4, generator=gen(5), dtype=torch.float64)
    g_q = torch.randn(64, 4, generator=gen(6), dtype=torch.float64)
    results = []
    for route in (ops.Sym4EighEager, ops.Sym4Eigh):
        leaf = A.clone().requires_grad_()
        eigenvalues, q, _ = route.apply(leaf, 1e-6, 14, method, kernel)
        (grad,) = torch.autograd.grad((eigenvalues * g_l).sum() + (q * g_q).sum(), leaf)
        results.append((eigenvalues, q, grad))
    for x, y in zip(*results, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_vmap_and_jacrev_go_through_the_op(method, kernel):
    """torch.func.vmap joins the vmapped dimension to the batch (one op call, the same numbers
    as the batched call); jacrev (vmap of vjp) gives autograd's Jacobian."""
    A = sym_randn(12, 14).reshape(3, 4, 4, 4)

    def solve(a):
        return sym4_eigh_min(a, check=False, method=method, kernel=kernel)

    for got, ref in zip(torch.func.vmap(solve)(A), solve(A), strict=True):
        assert torch.equal(got, ref)
    a = A[0, 0]
    jac = torch.func.jacrev(lambda x: solve(x)[1])(a)  # (4, 4, 4): dq_i / dA_jk
    leaf = a.clone().requires_grad_()
    q = solve(leaf)[1]
    rows = [torch.autograd.grad(q[i], leaf, retain_graph=True)[0] for i in range(4)]
    torch.testing.assert_close(jac, torch.stack(rows), atol=1e-12, rtol=0)


def test_unknown_kernel_raises():
    with pytest.raises(ValueError, match="kernel"):
        sym4_eigh_min(torch.eye(4), kernel="fortran")
    with pytest.raises(ValueError, match="CPU tensors"):
        ops.resolve_kernel("cpu", torch.device("meta"))


# ---------------------------------------------------------------------------------------------
# torch.compile: one graph, forward and backward, on every path
# ---------------------------------------------------------------------------------------------


def _compiled_matches_eager(method: str, kernel: str, backend: str) -> None:
    def layer(theta: torch.Tensor) -> torch.Tensor:
        eigenvalues, q = sym4_eigh_min(a_from_vec(theta), check=False, method=method, kernel=kernel)
        return q * eigenvalues[..., :1]

    torch._dynamo.reset()
    compiled = torch.compile(layer, backend=backend, fullgraph=True)  # raises on a graph break
    weight = torch.randn(48, 4, generator=gen(8))
    for batch in (48, 17):  # a second shape: no graph break on a new batch size either
        theta = torch.randn(batch, 10, generator=gen(7)).requires_grad_()
        out = compiled(theta)
        (grad,) = torch.autograd.grad((out * weight[:batch]).sum(), theta)
        leaf = theta.detach().requires_grad_()
        ref = layer(leaf)
        (ref_grad,) = torch.autograd.grad((ref * weight[:batch]).sum(), leaf)
        torch.testing.assert_close(out, ref, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(grad, ref_grad, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_compiles_to_one_graph_aot_eager(method, kernel):
    """Dynamo's capture and AOT autograd, no C++ compiler needed: the op forward and the backward
    op appear as single nodes; fullgraph=True fails on any graph break."""
    _compiled_matches_eager(method, kernel, "aot_eager")


@pytest.mark.slow
@pytest.mark.parametrize(("method", "kernel"), SOLVERS)
def test_compiles_to_one_graph_inductor(method, kernel):
    """torch.compile's default backend (C++ code generation: minutes on 2 busy cores)."""
    _compiled_matches_eager(method, kernel, "inductor")


@pytest.mark.parametrize("kernel", PATHS)
def test_compiled_graph_holds_one_op_each_way(kernel):
    """The traced forward graph calls rotlearn::sym4_eigh once and nothing else of the solver; the
    backward graph rotlearn::sym4_eigh_backward once."""
    graphs = []

    def backend(gm, example_inputs):
        from functorch.compile import make_boxed_func
        from torch._functorch.aot_autograd import aot_module_simplified

        def keep(graph_module, _):
            graphs.append(graph_module)
            return make_boxed_func(graph_module.forward)

        return aot_module_simplified(gm, example_inputs, fw_compiler=keep, bw_compiler=keep)

    def solve(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)

    torch._dynamo.reset()
    A = sym_randn(32, 9).to(torch.float32).requires_grad_()
    eigenvalues, q = torch.compile(solve, backend=backend, fullgraph=True)(A)
    torch.autograd.grad(eigenvalues.sum() + q.sum(), A)
    assert len(graphs) == 2, graphs  # forward and backward
    for graph, op in zip(graphs, ("sym4_eigh", "sym4_eigh_backward"), strict=True):
        targets = [str(node.target) for node in graph.graph.nodes if node.op == "call_function"]
        assert sum(t == f"rotlearn.{op}.default" for t in targets) == 1, targets


# ---------------------------------------------------------------------------------------------
# work per call (torch.profiler)
# ---------------------------------------------------------------------------------------------


def _aten_ops(kernel: str, n: int = 4096) -> collections.Counter:
    A = sym_randn(n, 10).to(torch.float32).requires_grad_()
    g_l = torch.randn(n, 4, generator=gen(11))
    g_q = torch.randn(n, 4, generator=gen(12))

    def step():
        eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel=kernel)
        torch.autograd.grad((eigenvalues, q), A, (g_l, g_q))

    step()  # warm-up (the kernel's first load)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        step()
    return collections.Counter(e.name for e in prof.events() if e.name.startswith("aten::"))


@NO_CPU_KERNEL
def test_fused_cpu_path_runs_one_kernel_call_each_way(monkeypatch):
    """Forward+backward on the fused path: the ATen ops are only the output allocations (and
    no-op conversions), against hundreds of elementwise ops of the eager Jacobi; and the C
    kernel is entered once forward, once backward."""
    allocation = {"aten::empty", "aten::new_empty", "aten::to", "aten::contiguous"}
    fused = _aten_ops("cpu")
    assert set(fused) <= allocation, fused
    assert sum(fused.values()) <= 12, fused
    eager = _aten_ops("eager")
    assert sum(eager.values()) > 300, eager  # the eager Jacobi, for scale
    lib = cpu_kernel.library()
    calls = collections.Counter()

    class Counting:
        def __getattr__(self, name):
            def call(*args):
                calls[name] += 1
                return getattr(lib, name)(*args)

            return call

    monkeypatch.setattr(cpu_kernel, "library", Counting)
    A = sym_randn(4096, 13).to(torch.float32).requires_grad_()
    eigenvalues, q = sym4_eigh_min(A, check=False, method="jacobi", kernel="cpu")
    torch.autograd.grad(eigenvalues.sum() + q.sum(), A)
    assert calls == {"rotlearn_sym4_forward": 1, "rotlearn_sym4_backward": 1}, calls
