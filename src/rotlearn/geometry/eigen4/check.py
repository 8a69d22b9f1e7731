"""Input check of the A layer's eigensolver: finite, symmetric 4x4 float32/float64 matrices."""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from rotlearn.errors import batch_index
from rotlearn.geometry.eigen4.eager import UPPER
from rotlearn.geometry.shapes import require_shape

__all__ = ["validate_sym4"]

LOWER = (0, 5, 10, 15, 4, 8, 12, 9, 13, 14)  # the entries mirroring UPPER's (flat, row-major)


@functools.lru_cache(maxsize=16)
def _indices(device: torch.device, flat: tuple[int, ...]) -> Tensor:
    return torch.tensor(flat, device=device)


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
    require_shape(A, (4, 4), "A")
    if A.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"expected float32 or float64, got {A.dtype}")
    batch = A.shape[:-2]
    flat = A.reshape(-1, 16)
    if flat.shape[0] == 0:
        return
    # Entry-major layout (rows = entries, reductions over rows are fast): the upper and the
    # mirrored lower triangle.
    upper = flat.t().index_select(0, _indices(A.device, UPPER))
    lower = flat.t().index_select(0, _indices(A.device, LOWER))
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
