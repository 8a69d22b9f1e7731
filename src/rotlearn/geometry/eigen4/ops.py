"""The A layer's eigensolver as registered PyTorch operators, and the choice of the path behind.

Two operators (torch.library.custom_op), each with a fake (meta) implementation and a vmap rule:

- ``rotlearn::sym4_eigh(A, gap_eps, rounds, method, kernel) -> (eigenvalues, q, V)``: A (B, 4, 4)
  -> eigenvalues (B, 4) ascending, q (B, 4) the eigenvector of the smallest with canonical sign, V
  (B, 4, 4) the eigenvectors as columns (column 0 = q; not differentiable, saved for the backward).
  Its backward (`register_autograd`) is the second operator:
- ``rotlearn::sym4_eigh_backward(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps, kernel)``.

So torch.compile(fullgraph=True) traces the A layer as one node forward and one backward, on every
path, and torch.func.vmap moves the vmapped dimension into the batch (one call, no per-sample loop).
`apply` is what `sym4_eigh_min` calls: the op under torch.compile and torch.func (through
`Sym4Eigh`), the op's implementations directly in eager autograd (`Sym4EighEager`, less Python per
call).

Paths (`kernel`): "cpu", the fused C kernel (`rotlearn.geometry.eigen4.cpu`), one call per
forward and one per backward; "triton", the Triton kernels (`rotlearn.geometry.eigen4.gpu`), one
launch each on CUDA (on CPU tensors they run in Triton's interpreter, for tests); "eager", tensor
operations (`rotlearn.geometry.eigen4.eager`); "auto": the fused kernel of the tensor's device
where it can run, else eager (one RuntimeWarning per process says why). `method`: "jacobi", "eigh"
(torch.linalg.eigh's forward, the same backward) or "auto" (jacobi wherever a fused kernel runs;
on the eager path eigh below `EIGH_BELOW` matrices).
"""

from __future__ import annotations

import functools
import importlib.util
import warnings

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from rotlearn.extras import require
from rotlearn.geometry.eigen4 import cpu, eager

__all__ = [
    "DEFAULT_GAP_EPS",
    "DEFAULT_ROUNDS",
    "EIGH_BELOW",
    "KERNELS",
    "METHODS",
    "Sym4Eigh",
    "Sym4EighEager",
    "apply",
    "backward_impl",
    "forward_impl",
    "resolve_kernel",
    "sym4_eigh",
    "sym4_eigh_backward",
]

DEFAULT_GAP_EPS = 1e-6
DEFAULT_ROUNDS = {torch.float32: 12, torch.float64: 14}
METHODS = ("auto", "jacobi", "eigh")  # sym4_eigh_min's forward (also the A head's rep.solver)
KERNELS = ("auto", "cpu", "triton", "eager")  # what runs it
# method="auto" on the eager path: the torch.linalg.eigh forward below this many matrices, Jacobi
# from there on. Measured by `bench/rep_layers.py --crossover` (the batch size from which the
# eager Jacobi's forward + backward is faster than eigh's; bench/results/solver_crossover.json).
EIGH_BELOW = 1024

_warned_triton = False


@functools.cache
def triton_available() -> bool:
    """Whether the `triton` package (the [gpu] extra) is installed."""
    return importlib.util.find_spec("triton") is not None


def resolve_kernel(kernel: str, device: torch.device) -> str:
    """The path that runs for `kernel` on `device`: "cpu", "triton" or "eager".

    Raises:
        ValueError: an unknown kernel, or one that does not run on this device type.
        RuntimeError: kernel="cpu" where the C kernel cannot run (the reason in the message).
        rotlearn.extras.MissingExtraError: kernel="triton" without triton (the [gpu] extra).
    """
    global _warned_triton
    if kernel == "auto":
        if device.type == "cpu":
            return "cpu" if cpu.available(warn=True) else "eager"
        if device.type == "cuda":
            if triton_available():
                return "triton"
            if not _warned_triton:
                _warned_triton = True
                warnings.warn(
                    "rotlearn: triton is not installed (pip install rotlearn[gpu]); the A layer"
                    " runs its eager solver on CUDA (~450 kernel launches per call)",
                    RuntimeWarning,
                    stacklevel=2,
                )
        return "eager"
    if kernel == "cpu":
        if device.type != "cpu":
            raise ValueError(f"kernel='cpu' needs CPU tensors, got {device}")
        cpu.library()
    elif kernel == "triton":
        if device.type not in ("cuda", "cpu"):
            raise ValueError(
                f"kernel='triton' needs CUDA tensors (or CPU: interpreter), got {device}"
            )
        require("gpu", "sym4_eigh_min(kernel='triton')")
    elif kernel != "eager":
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    return kernel


def _gpu():
    from rotlearn.geometry.eigen4 import gpu  # imports triton: only where it is asked for

    return gpu


def forward_impl(A: Tensor, rounds: int, method: str, kernel: str) -> tuple[Tensor, Tensor, Tensor]:
    """The forward on real tensors: A (B, 4, 4) -> eigenvalues (B, 4), q (B, 4), V (B, 4, 4)."""
    backend = resolve_kernel(kernel, A.device)
    if method == "eigh" or (method == "auto" and backend == "eager" and A.shape[0] < EIGH_BELOW):
        return eager.eigh_forward(A)
    if backend == "cpu":
        return cpu.forward(A, rounds)
    if backend == "triton":
        return _gpu().forward(A, rounds)
    return eager.jacobi_forward(A, rounds)


def backward_impl(
    grad_eigenvalues: Tensor | None,
    grad_q: Tensor | None,
    eigenvalues: Tensor,
    V: Tensor,
    gap_eps: float,
    kernel: str,
) -> Tensor:
    """The backward on real tensors: grad_A (B, 4, 4), exactly symmetric (formula: `_backward`)."""
    backend = resolve_kernel(kernel, V.device)
    if backend == "cpu":
        return cpu.backward(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps)
    if backend == "triton":
        return _gpu().backward(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps)
    return eager.backward(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps)


# Explicit schemas: torch 2.4 infers none from the string annotations of `from __future__`.
@torch.library.custom_op(
    "rotlearn::sym4_eigh",
    mutates_args=(),
    schema="(Tensor A, float gap_eps, int rounds, str method, str kernel) "
    "-> (Tensor, Tensor, Tensor)",
)
def sym4_eigh(
    A: Tensor, gap_eps: float, rounds: int, method: str, kernel: str
) -> tuple[Tensor, Tensor, Tensor]:
    """A (B, 4, 4) -> eigenvalues (B, 4), q (B, 4), V (B, 4, 4); see the module docstring."""
    return forward_impl(A, rounds, method, kernel)


@sym4_eigh.register_fake
def _sym4_eigh_fake(A, gap_eps, rounds, method, kernel):
    B = A.shape[0]
    return A.new_empty(B, 4), A.new_empty(B, 4), A.new_empty(B, 4, 4)


@torch.library.custom_op(
    "rotlearn::sym4_eigh_backward",
    mutates_args=(),
    schema="(Tensor? grad_eigenvalues, Tensor? grad_q, Tensor eigenvalues, Tensor V, "
    "float gap_eps, str kernel) -> Tensor",
)
def sym4_eigh_backward(
    grad_eigenvalues: Tensor | None,
    grad_q: Tensor | None,
    eigenvalues: Tensor,
    V: Tensor,
    gap_eps: float,
    kernel: str,
) -> Tensor:
    """grad_A (B, 4, 4), exactly symmetric, of `sym4_eigh` (the formula: `_backward`)."""
    return backward_impl(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps, kernel)


@sym4_eigh_backward.register_fake
def _sym4_eigh_backward_fake(grad_eigenvalues, grad_q, eigenvalues, V, gap_eps, kernel):
    return V.new_empty(V.shape)


def _setup_context(ctx, inputs: tuple, output: tuple[Tensor, Tensor, Tensor]) -> None:
    _, gap_eps, _, _, kernel = inputs
    eigenvalues, _, V = output
    ctx.mark_non_differentiable(V)
    ctx.save_for_backward(eigenvalues, V)
    ctx.gap_eps = gap_eps
    ctx.kernel = kernel
    ctx.set_materialize_grads(False)


def _backward(ctx, grad_eigenvalues: Tensor | None, grad_q: Tensor | None, _grad_V=None):
    """With l1 <= ... <= l4 and orthonormal eigenvectors v1 = q, v2, v3, v4:
        grad_A = sym(-u q^T + sum_i g_li v_i v_i^T),   u = sum_{i>=2} v_i (v_i . g_q) / gap_i,
        gap_i = max(l_i - l1, gap_eps (l4 - l1))  (gap_i = 1 for l1 = l4, A = cI),
        sym(X) = (X + X^T) / 2.
    The first term is dq = -(A - l1 I)^+ dA q (paper eq. 9), the second dl_i = v_i^T dA v_i.
    Only the projector onto each eigenspace above l1 enters u, so repeated l2 = l3 = l4 is
    harmless; the clamp keeps l1 = l2 (and A = cI) finite. The clamp is relative to the spread
    l4 - l1, as the gaps and q: the gradient of A + cI is that of A for any c. grad_A is exactly
    symmetric: the gradient along symmetric perturbations, so that a mirrored A (a_from_vec) gets
    the right gradient in both triangles. First order only: the gradient is not itself
    differentiable."""
    eigenvalues, V = ctx.saved_tensors
    if grad_eigenvalues is None and grad_q is None:
        return None, None, None, None, None
    with torch.no_grad():
        grad = sym4_eigh_backward(grad_eigenvalues, grad_q, eigenvalues, V, ctx.gap_eps, ctx.kernel)
    return grad, None, None, None, None


sym4_eigh.register_autograd(_backward, setup_context=_setup_context)


class Sym4Eigh(torch.autograd.Function):
    """The op with its registered backward, as an autograd.Function for torch.func and compile.

    The Function that `register_autograd` generates lacks `setup_context`, so torch.func.grad,
    vjp and jacrev refuse the registered op (pytorch/pytorch#170834, open in torch 2.13). This
    Function has the same forward (the op), setup_context and backward (the backward op); its
    vmap rule is generated, so vmap runs through the two ops' own vmap rules (one call each).
    torch.compile traces it as the op forward and the backward op backward.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(A: Tensor, gap_eps: float, rounds: int, method: str, kernel: str):
        return sym4_eigh(A, gap_eps, rounds, method, kernel)

    setup_context = staticmethod(_setup_context)
    backward = staticmethod(_backward)


class Sym4EighEager(torch.autograd.Function):
    """The op's forward and backward implementations called directly, for eager autograd.

    The same functions as the registered op without its Python layers: the custom-op wrapper
    (~20 us per call each way) and new-style Function.apply's argument binding (~25 us). At small
    batches those dominate (B = 1, 1 thread: 250 us per forward+backward through the op, 115 us
    this way, 165 us for torch.linalg.eigh with autograd; issue 26).
    """

    @staticmethod
    def forward(ctx, A: Tensor, gap_eps: float, rounds: int, method: str, kernel: str):
        output = forward_impl(A, rounds, method, kernel)
        _setup_context(ctx, (A, gap_eps, rounds, method, kernel), output)
        return output

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_eigenvalues: Tensor | None, grad_q: Tensor | None, _grad_V=None):
        eigenvalues, V = ctx.saved_tensors
        if grad_eigenvalues is None and grad_q is None:
            return None, None, None, None, None
        grad = backward_impl(grad_eigenvalues, grad_q, eigenvalues, V, ctx.gap_eps, ctx.kernel)
        return grad, None, None, None, None


def apply(
    A: Tensor, gap_eps: float, rounds: int, method: str, kernel: str
) -> tuple[Tensor, Tensor, Tensor]:
    """`sym4_eigh` with autograd: the registered op (`Sym4Eigh`) under torch.compile and torch.func
    transforms, its implementations directly (`Sym4EighEager`) in eager mode."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return Sym4Eigh.apply(A, gap_eps, rounds, method, kernel)
    return Sym4EighEager.apply(A, gap_eps, rounds, method, kernel)


def _batch_first(info, dim: int | None, x: Tensor | None) -> Tensor | None:
    """x with the vmapped dimension first (expanded where x is not vmapped)."""
    if x is None:
        return None
    return x.expand(info.batch_size, *x.shape) if dim is None else x.movedim(dim, 0)


def _vmap_forward(info, in_dims: tuple, A: Tensor, gap_eps, rounds, method, kernel):
    """The vmapped dimension joins the batch of matrices: one call."""
    A = _batch_first(info, in_dims[0], A)
    outputs = sym4_eigh(A.reshape(-1, 4, 4), gap_eps, rounds, method, kernel)
    split = (A.shape[0], -1)
    return tuple(x.unflatten(0, split) for x in outputs), (0, 0, 0)


def _vmap_backward(info, in_dims: tuple, grad_l, grad_q, eigenvalues, V, gap_eps, kernel):
    flat = []
    for x, dim, trailing in zip(
        (grad_l, grad_q, eigenvalues, V), in_dims[:4], (1, 1, 1, 2), strict=True
    ):
        x = _batch_first(info, dim, x)
        flat.append(None if x is None else x.reshape(-1, *x.shape[-trailing:]))
    grad = sym4_eigh_backward(*flat, gap_eps, kernel)
    return grad.unflatten(0, (info.batch_size, -1)), 0


if hasattr(torch.library, "register_vmap"):  # torch >= 2.5; on 2.4 vmap of the op is not supported
    torch.library.register_vmap(sym4_eigh, _vmap_forward)
    torch.library.register_vmap(sym4_eigh_backward, _vmap_backward)
