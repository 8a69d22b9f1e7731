"""rotlearn.geometry.linalg: torch.linalg's eigensolvers in chunks on CUDA, equal to one call."""

from __future__ import annotations

import pytest
import torch

from rotlearn.geometry import linalg, sym4_eigh_min
from rotlearn.geometry.linalg import _in_chunks

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _symmetric(*batch: int, n: int = 4, dtype=torch.float64) -> torch.Tensor:
    M = torch.randn(*batch, n, n, dtype=dtype)
    return M + M.transpose(-1, -2)


@pytest.mark.parametrize("batch", [(0,), (1,), (7,), (3, 5), (2, 3, 4)])
@pytest.mark.parametrize("size", [1, 2, 6])
def test_chunks_give_what_one_call_gives(batch, size):
    """Every output, any batch shape, in chunks of `size` matrices: equal to the single call,
    with the batch shape kept (a tuple's parts and a tensor alike)."""
    torch.manual_seed(0)
    A, M = _symmetric(*batch), torch.randn(*batch, 3, 3, dtype=torch.float64)
    calls = [
        (lambda X: tuple(torch.linalg.eigh(X)), A),
        (torch.linalg.eigvalsh, A),
        (lambda X: tuple(torch.linalg.svd(X)), M),
    ]
    for function, X in calls:
        whole, parts = function(X), _in_chunks(function, X, size)
        for a, b in zip(
            *(o if isinstance(o, tuple) else (o,) for o in (whole, parts)), strict=True
        ):
            assert b.shape == a.shape
            torch.testing.assert_close(b, a, rtol=0, atol=0)


def test_gradients_flow_through_the_chunks():
    """The chunked eigenvalues' gradient is the single call's (d lambda_i / dA = v_i v_i^T)."""
    torch.manual_seed(1)
    A = _symmetric(9).requires_grad_(True)
    weights = torch.randn(9, 4, dtype=torch.float64)
    (grad_whole,) = torch.autograd.grad((torch.linalg.eigvalsh(A) * weights).sum(), A)
    (grad_parts,) = torch.autograd.grad(
        (_in_chunks(torch.linalg.eigvalsh, A, 4) * weights).sum(), A
    )
    torch.testing.assert_close(grad_parts, grad_whole, rtol=0, atol=1e-12)


def test_on_the_cpu_one_call_whatever_the_batch(monkeypatch):
    """Off CUDA the batch goes to torch at once, however large (no chunk loop on the CPU)."""
    calls = []

    def counted(X):
        calls.append(X.shape[0])
        return torch.linalg.eigvalsh(X)

    monkeypatch.setattr(linalg, "CUDA_BATCH", 2)
    _in_chunks(counted, _symmetric(5))
    assert calls == [5]


@CUDA
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_batches_past_cusolvers_limit(dtype):
    """A batch of 4 x CUDA_BATCH + 3 on CUDA (cuSOLVER's batched eigh fails from 2^16 matrices
    on): eigh and eigvalsh run and match the CPU's; the A layer's method="eigh" too."""
    torch.manual_seed(2)
    A = _symmetric(4 * linalg.CUDA_BATCH + 3, dtype=dtype)
    tol = {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {}
    ev, V = linalg.eigh(A.cuda())
    torch.testing.assert_close(ev.cpu(), torch.linalg.eigvalsh(A), **tol)
    torch.testing.assert_close(linalg.eigvalsh(A.cuda()).cpu(), ev.cpu(), **tol)
    residual = A.cuda() @ V - V * ev.unsqueeze(-2)
    assert residual.abs().amax() <= 1e-3 * A.abs().amax()
    q = sym4_eigh_min(A.cuda(), method="eigh")[1]
    assert q.shape == (A.shape[0], 4) and bool(torch.isfinite(q).all())
