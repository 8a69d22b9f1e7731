"""Max-pooling of a per-point linear map, with a backward that touches only the selected points.

PointNet's last per-point layer is followed by a max over points:
out[b, c] = max_n (W h[b, n] + bias)[c]. The gradient of that max reaches one point per (b, c), so
the layer's dense backward (two GEMMs the size of the forward) mostly multiplies zeros.
`LinearMaxPool` computes the same function and the same (sub)gradient as `nn.Linear` followed by
`max(dim=-2)`, but its backward multiplies by the sparse selection matrix instead:
O(B * C_out * C_in) work rather than O(B * N * C_out * C_in).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor, nn

from rotlearn.geometry.autocast import REDUCED_DTYPES, autocast_enabled

__all__ = ["LinearMaxPool", "linear_max"]


def linear_max(points: Tensor, weight: Tensor, bias: Tensor, chunk: int) -> tuple[Tensor, Tensor]:
    """max over points of points @ weight^T + bias, and where it is attained.

    Computed as W @ points^T in chunks of whole samples, so the max runs along a contiguous axis
    and each chunk's output stays in cache.

    Args:
        points: (B, N, C_in).
        weight: (C_out, C_in); bias: (C_out,).
        chunk: samples per chunk.

    Returns:
        values (B, C_out) and indices (B, C_out) into the N points.
    """
    N, D = points.shape[-2:]
    values, indices = [], []
    for part in points.split(chunk):
        scores = (weight @ part.reshape(-1, D).T).view(-1, part.shape[0], N)  # (C_out, k, N)
        v, i = scores.max(dim=-1)
        values.append(v)
        indices.append(i)
    values_t = torch.cat(values, dim=1).T + bias
    return values_t.contiguous(), torch.cat(indices, dim=1).T.contiguous()


def _selection_matrices(index: Tensor, grad: Tensor, num_points: int) -> tuple[Tensor, Tensor]:
    """The sparse matrix P (C_out, B * N) with P[c, b * N + index[b, c]] = grad[b, c], and P^T,
    both in CSR form (one entry per (b, c)), so that dL/dW = P @ points and dL/dpoints = P^T @ W."""
    B, C = index.shape
    device = index.device
    rows = (index + num_points * torch.arange(B, device=device).unsqueeze(-1)).reshape(-1)
    # P: row c holds the B entries (b, rows[b, c]); their columns increase with b, as CSR needs.
    P = torch.sparse_csr_tensor(
        torch.arange(0, B * C + 1, B, device=device),
        rows.view(B, C).T.reshape(-1),
        grad.T.reshape(-1),
        size=(C, B * num_points),
        check_invariants=False,
    )
    order = torch.argsort(rows, stable=True)
    crow = torch.zeros(B * num_points + 1, dtype=torch.long, device=device)
    crow[1:] = torch.bincount(rows, minlength=B * num_points).cumsum(0)
    Pt = torch.sparse_csr_tensor(
        crow,
        torch.arange(C, device=device).repeat(B)[order],
        grad.reshape(-1)[order],
        size=(B * num_points, C),
        check_invariants=False,
    )
    return P, Pt


class _LinearMaxPoolFn(torch.autograd.Function):
    """`linear_max` with the sparse backward; all inputs in one dtype. New-style Function
    (`setup_context`), so torch.compile traces it. Outputs: values and the (integer, not
    differentiable) indices of the selected points."""

    @staticmethod
    def forward(points: Tensor, weight: Tensor, bias: Tensor, chunk: int) -> tuple[Tensor, Tensor]:
        return linear_max(points, weight, bias, chunk)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, Tensor]) -> None:
        points, weight, _, _ = inputs
        ctx.mark_non_differentiable(output[1])
        ctx.save_for_backward(points, weight, output[1])

    @staticmethod
    def backward(ctx: Any, grad: Tensor, _grad_index: Any = None) -> tuple[Tensor | None, ...]:
        points, weight, index = ctx.saved_tensors
        B, N, D = points.shape
        # Sparse CSR products have no float16/bfloat16 kernels: those run in float32 (the
        # products are O(B * C_out * C_in), small next to the forward's GEMM).
        work = torch.float32 if grad.dtype in REDUCED_DTYPES else grad.dtype
        grad = grad.to(work)
        with warnings.catch_warnings(), torch.autocast(grad.device.type, enabled=False):
            warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
            P, Pt = _selection_matrices(index, grad.contiguous(), N)
            grad_points = grad_weight = grad_bias = None
            if ctx.needs_input_grad[0]:
                grad_points = (Pt @ weight.to(work)).view_as(points).to(points.dtype)
            if ctx.needs_input_grad[1]:
                grad_weight = (P @ points.reshape(B * N, D).to(work)).to(weight.dtype)
        if ctx.needs_input_grad[2]:
            grad_bias = grad.sum(0).to(weight.dtype)
        return grad_points, grad_weight, grad_bias, None


class LinearMaxPool(nn.Module):
    """`nn.Linear(in_features, out_features)` on every point, then the max over points.

    Same parameters, initialisation and state-dict keys (`linear.weight`, `linear.bias`) as a
    wrapped `nn.Linear`; the same values, and the same gradient as `Linear` + `max(dim=-2)`.
    Under autocast it computes like `nn.Linear` there: the product in the autocast dtype, whose
    output it returns (the sparse backward runs in float32 and casts back).

    Args:
        in_features, out_features: the linear map's sizes.
        chunk_points: about how many points each GEMM chunk holds (a cache-size knob).

    Input (..., N, in_features); output (..., out_features).
    """

    def __init__(self, in_features: int, out_features: int, chunk_points: int = 8192) -> None:
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)
        self.chunk_points = chunk_points

    def forward(self, points: Tensor) -> Tensor:
        lead, (n, d) = points.shape[:-2], points.shape[-2:]
        flat = points.reshape(-1, n, d)
        chunk = max(1, self.chunk_points // max(n, 1))
        weight, bias = self.linear.weight, self.linear.bias
        device_type = points.device.type
        if autocast_enabled(device_type):
            # As nn.Linear under autocast: the product in the autocast dtype (bfloat16 with
            # precision=bf16-mixed), and so is the output; the casts carry the gradients back.
            dtype = torch.get_autocast_dtype(device_type)
            with torch.autocast(device_type, enabled=False):
                out = self._pool(flat.to(dtype), weight.to(dtype), bias.to(dtype), chunk)
        else:
            out = self._pool(flat, weight, bias, chunk)
        return out.reshape(*lead, -1)

    @staticmethod
    def _pool(points: Tensor, weight: Tensor, bias: Tensor, chunk: int) -> Tensor:
        if torch.is_grad_enabled() and (points.requires_grad or weight.requires_grad):
            return _LinearMaxPoolFn.apply(points, weight, bias, chunk)[0]
        return linear_max(points, weight, bias, chunk)[0]

    def extra_repr(self) -> str:
        return f"chunk_points={self.chunk_points}"
