"""torch.linalg's symmetric eigensolvers for any batch size on CUDA.

On CUDA, torch.linalg.eigh and eigvalsh of a batch of small matrices call cuSOLVER's batched
Jacobi (cusolverDnXsyevBatched), which fails from 65 536 = 2^16 matrices on: torch 2.11 with
CUDA 13.0 on an H200 raised "CUSOLVER_STATUS_INTERNAL_ERROR" for 65 536 4 x 4 matrices in
float32 and float64 and ran 65 535 (svd and det ran 1 048 576). These functions pass a larger
batch to torch in chunks of `CUDA_BATCH` matrices, one call each, the results concatenated
(autograd flows through); elsewhere, and for smaller batches, they are torch's own call.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from torch import Tensor

__all__ = ["CUDA_BATCH", "eigh", "eigvalsh"]

# Matrices per cuSOLVER call on CUDA: a power of two below the failing 2^16 (docs/results.md).
CUDA_BATCH = 32768

Output = TypeVar("Output", Tensor, tuple[Tensor, ...])


def _in_chunks(function: Callable[[Tensor], Output], M: Tensor, size: int | None = None) -> Output:
    """`function` (a batched map (..., m, n) -> tensors (..., ...)) of M, `size` matrices at a
    time (default: `CUDA_BATCH` on CUDA, all at once elsewhere)."""
    batch = M.shape[:-2]
    size = size or (CUDA_BATCH if M.device.type == "cuda" else batch.numel())
    if batch.numel() <= size:
        return function(M)
    parts = [function(chunk) for chunk in M.reshape(-1, *M.shape[-2:]).split(size)]
    if isinstance(parts[0], Tensor):
        return torch.cat(parts).reshape(*batch, *parts[0].shape[1:])
    joined = (torch.cat(outputs) for outputs in zip(*parts, strict=True))
    return tuple(t.reshape(*batch, *t.shape[1:]) for t in joined)


def eigh(A: Tensor, UPLO: str = "L") -> tuple[Tensor, Tensor]:
    """`torch.linalg.eigh(A, UPLO)`: ascending eigenvalues (..., n) and eigenvectors as columns
    (..., n, n) of the symmetric A (..., n, n), any batch size on CUDA."""
    return _in_chunks(lambda chunk: tuple(torch.linalg.eigh(chunk, UPLO=UPLO)), A)


def eigvalsh(A: Tensor) -> Tensor:
    """`torch.linalg.eigvalsh(A)`: ascending eigenvalues (..., n) of the symmetric A (..., n, n),
    any batch size on CUDA."""
    return _in_chunks(torch.linalg.eigvalsh, A)
