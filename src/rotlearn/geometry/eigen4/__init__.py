"""Batched eigensolver for symmetric 4x4 matrices: the A layer's `eigh`, with a finite backward.

`sym4_eigh_min` returns the four eigenvalues (ascending) and the unit eigenvector of the smallest
one with canonical sign, which is what the A head needs (paper eqs. 9, 11), with an analytic
backward that stays finite where eigenvalues coincide (torch.linalg.eigh's is NaN/Inf there).

One registered operator, three paths behind it (`rotlearn.geometry.eigen4.ops`):

- cpu: a fused C kernel (`eigen4.cpu`, sym4.c) that keeps blocks of 16 matrices in the L1 cache,
  SIMD across the block, from the load of their upper triangles to the store of their eigenpairs;
  compiled on first use and cached (no compiler: the eager path);
- triton: one Triton kernel for the forward and one for the backward (`eigen4.gpu`), each one
  launch per call, for CUDA tensors (`pip install rotlearn[gpu]`; without it the eager path);
- eager: PyTorch tensor operations (`eigen4.eager`), the fallback and the reference.

Algorithm (all three paths). A (its upper triangle) is scaled by a power of two so that its
largest entry lies in [0.5, 1) (exact for any finite input: the factor is applied as two normal
powers of two, so subnormal and huge entries too). Its mean diagonal c = trace(A) / 4 is then
subtracted (no overflow: the entries are below 4 now) and the result scaled again (exact; squares
then neither overflow nor underflow however small the spread of the eigenvalues is against
||A||_2). A - cI has A's eigenvectors, and the rounding of the rotations is relative to its
entries, so q's error scales with the spread of the eigenvalues l4 - l1, not with ||A||_2 (before
the shift, float32 q of A + 1e4 I was off by 0.4 degrees for a spectrum (0, 0.3, 0.6, 1); the A
head's losses do not depend on A's trace, so a network's trace may drift). Then a fixed number of
Jacobi *rounds*: a round applies two rotations on disjoint index
pairs at once, cycling through the three perfect matchings {01, 23}, {02, 13}, {03, 12} (three
rounds = one cyclic sweep over all six pairs). Each rotation zeroes its off-diagonal entry with
the stable small-angle formula (|angle| <= 45 degrees); V accumulates the rotations and is
orthogonal to working precision. A sorting network then orders the eigenvalues, moving the
columns of V along, and q = V's first column gets quat_canonical's sign; the eigenvalues are
scaled back, c added, and scaled back again. The eigh method solves A - cI as well (with c the
midpoint of A's diagonal, which cannot overflow).

Round counts, chosen by measurement (maximum over 10^6 Gaussian matrices, and the cases of
tests/geometry/test_eigen4.py): float32 needs 12 rounds (11 leave residuals |A q - l1 q| up to
4e-6 ||A||, 4x eigh's), float64 14 (13 leave 5e-14 ||A||).

Measured accuracy (max over 20000 matrices per case: Gaussian, I - q q^T with and without 1e-3
noise, Wahba data matrices (paper eq. 5), clustered -sum q_k q_k^T, Gaussian scaled by 1e-6 and
1e6; against float64 eigh of the same matrices (shifted by their mean diagonal); angle of R(q)
over spectra with l2 - l1 >= 0.01 (l4 - l1)), eager path:

- float32: angle <= 3e-4 deg, eigenvalues within 5e-7 ||A||_2, |A q - l1 q| <= 6e-7 ||A||_2
  (float32 torch.linalg.eigh: 1.1e-3 deg, 1.1e-6, 1.1e-6);
- float64: angle <= 3e-12 deg, eigenvalues within 3e-15 ||A||_2, |A q - l1 q| <= 1.3e-15 ||A||_2
  (float64 eigh's residual: up to 2.6e-15).

In general the angle of q (in radians) stays below about 10 eps (l4 - l1) / (l2 - l1) (measured,
every path, also for these matrices plus 1e4 ||A||_2 I), whatever ||A||_2 and the trace. The
fused kernels compute the same rotations with correctly rounded square roots and are held to the
same bounds by the same tests. With l2 - l1 = 1e-6 (l4 - l1) the residual bound still holds; q
itself is then determined only up to ~eps / 1e-6 (float32: 10 deg for this solver, 27 deg for
eigh).

No MKL VML on the CPU: VML's first call in a process races between intra-op threads on Intel CPUs
(issue 27); the eager path uses only ATen's own kernels, the C kernel the C library's sqrt.

Speed: `make bench ARGS=a_layer` (bench/a_layer.py; bench/results, docs/results.md).
"""

from __future__ import annotations

from torch import Tensor

from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.eigen4.check import validate_sym4
from rotlearn.geometry.eigen4.ops import (
    DEFAULT_GAP_EPS,
    DEFAULT_ROUNDS,
    EIGH_BELOW,
    KERNELS,
    METHODS,
    apply,
)
from rotlearn.geometry.shapes import require_shape

__all__ = [
    "DEFAULT_GAP_EPS",
    "DEFAULT_ROUNDS",
    "EIGH_BELOW",
    "KERNELS",
    "METHODS",
    "sym4_eigh_min",
    "validate_sym4",
]


@float32_under_autocast
def sym4_eigh_min(
    A: Tensor,
    *,
    gap_eps: float = DEFAULT_GAP_EPS,
    check: bool = True,
    rounds: int | None = None,
    method: str = "auto",
    kernel: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Eigenvalues and minimum eigenvector of symmetric 4x4 matrices (a fast `eigh` for the A head).

    Differentiable: an analytic backward (paper eq. 9 for q, v_i^T dA v_i for the eigenvalues;
    the formula is in `rotlearn.geometry.eigen4.ops`), finite for repeated eigenvalues, the same
    on every path. Device-agnostic; no host synchronisation when `check=False`. Every output
    element depends on its own matrix only. One registered operator (``rotlearn::sym4_eigh``):
    torch.compile(fullgraph=True) traces it (with `check=False`), torch.func.vmap batches it
    (torch >= 2.5) and grad differentiates it. Under autocast (CPU or CUDA) float16/bfloat16
    input is cast to float32 and the solver runs in float32 with autocast off.

    Args:
        A: (..., 4, 4) symmetric matrices, float32 or float64, any batch shape (also () and
            empty). Only the upper triangle is read (as torch.linalg.eigh(A, UPLO="U")); the
            gradient returned for A is symmetric.
        gap_eps: lower bound on the eigenvalue gaps l_i - l1 (i >= 2) in the backward, RELATIVE to
            the spread of the eigenvalues l4 - l1 (which, as q, does not depend on A's trace):
            gaps below gap_eps * (l4 - l1) are replaced by it (by 1 where l1 = l4, A = cI). With
            the default 1e-6 the q-gradient never exceeds about |grad_q| / (1e-6 (l4 - l1)), and
            it is exact wherever l2 - l1 >= 1e-6 (l4 - l1) (in float32 that is about 10 ulps of
            the spread, below which q is not determined by A anyway). Repeated upper eigenvalues
            (l2 = l3, l2 = l3 = l4) need no clamp. In (0, 1).
        check: run `validate_sym4` first (NaN/Inf entries, asymmetry beyond 1e-6 relative: raise
            ValueError with the first offending batch index). This synchronises with the device;
            pass False in training loops. With False there is no check at all.
        rounds: Jacobi rounds (two disjoint rotations each; 3 rounds = 1 sweep). Default: 12 for
            float32, 14 for float64 (`DEFAULT_ROUNDS`), measured to converge.
        method: "jacobi" (this package's solver), "eigh" (torch.linalg.eigh forward, this
            package's backward) or "auto": jacobi wherever a fused kernel runs (see `kernel`); on
            the eager path eigh below `EIGH_BELOW` matrices, where its lower per-call overhead
            wins, jacobi from there on. With "eigh" and check=False, NaN/Inf input makes
            torch.linalg.eigh raise (on the CPU); jacobi propagates NaN.
        kernel: what runs the Jacobi forward and the backward: "cpu" (the fused C kernel, CPU
            tensors), "triton" (the Triton kernels, CUDA tensors; on CPU tensors Triton's
            interpreter, for tests), "eager" (tensor operations) or "auto": "cpu" on the CPU
            where a C compiler built the kernel, "triton" on CUDA where triton is installed,
            else "eager" (with one RuntimeWarning per process naming the reason).

    Returns:
        eigenvalues: (..., 4), ascending, in A's dtype (float32 under autocast).
        q: (..., 4), the unit eigenvector of the smallest eigenvalue as a quaternion (x, y, z, w),
            sign exactly as `quat_canonical` (w > 0; ties by the first nonzero of w, x, y, z).

    Determinism: each output element is a function of its own matrix, the dtype, the device and
    the path alone. On the CPU every path gives bit-identical results across runs and processes
    (the first call included), thread counts and batch splits (any slice, chunk or single matrix
    of a batch; tests/geometry/test_eigen4_first_call.py). With `method="auto"` on the eager path
    the solver itself depends on the batch size (eigh below `EIGH_BELOW`), so the same matrix in
    batches of different sizes can differ in the last bits (within the accuracy below); where the
    fused kernel runs, "auto" is always jacobi. Different paths (fused, eager, eigh; CPU, CUDA)
    agree to the accuracy below, not bit for bit.

    Accuracy (against float64 torch.linalg.eigh of A as given; guaranteed by
    tests/geometry/test_eigen4.py for every path, measured values in the module docstring):
    float32: rotation angle of q <= 1e-3 degrees where l2 - l1 >= 0.01 (l4 - l1) on the test
    families (Gaussian, Wahba, near-rank-one, scaled), and for any A below 30 eps (l4 - l1) /
    (l2 - l1) radians (observed up to 10 eps: about 3e-3 degrees where the gap is just 0.01 of
    the spread; one such Gaussian-like matrix in 10^5 gave 1.1e-3 degrees from the fused CPU
    kernel), whatever ||A||_2 (A is solved as A - (trace(A) / 4) I, so A + cI gives q to the
    same accuracy for any c; rounding A + cI to float32 moves its eigenvectors by itself; method
    "eigh" subtracts the midpoint of the diagonal instead), eigenvalues within
    1e-6 ||A||_2, |A q - l1 q| <= 2e-6 ||A||_2; float64: angle <= 1e-9 degrees, eigenvalues and
    residual within 1e-14 ||A||_2; in every case no worse than torch.linalg.eigh in the same
    dtype.

    Raises:
        ValueError: wrong shape, dtype, method, kernel, rounds or gap_eps (always); NaN/Inf or
            asymmetric entries (only with `check=True`).
        RuntimeError: kernel="cpu" where the C kernel cannot run (the message says why).
        rotlearn.extras.MissingExtraError: kernel="triton" without triton (`[gpu]` extra).
    """
    require_shape(A, (4, 4), "A")
    if A.dtype not in DEFAULT_ROUNDS:
        raise ValueError(f"expected float32 or float64, got {A.dtype}")
    if check:
        validate_sym4(A)
    if rounds is not None and rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    if not 0.0 < gap_eps < 1.0:  # 0 or less: the backward divides by zero gaps (NaN)
        raise ValueError(f"gap_eps must lie in (0, 1), got {gap_eps}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    n_rounds = DEFAULT_ROUNDS[A.dtype] if rounds is None else int(rounds)
    if A.dim() == 3:  # (B, 4, 4): no reshapes (each would add a view to the autograd graph)
        eigenvalues, q, _ = apply(A, float(gap_eps), n_rounds, method, kernel)
        return eigenvalues, q
    batch = A.shape[:-2]
    eigenvalues, q, _ = apply(A.reshape(-1, 4, 4), float(gap_eps), n_rounds, method, kernel)
    return eigenvalues.reshape(*batch, 4), q.reshape(*batch, 4)
