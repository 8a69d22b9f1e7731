"""rotlearn.nn: the drop-in layers (tensor in, tensor out), in nn.Sequential, under autocast and
torch.compile."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rotlearn.geometry import sixd_to_rotmat, special_orthogonalize, symmatrixvec_to_quat
from rotlearn.nn import ALayer, SixDToRotmat, SVDToRotmat, SymmetricMatrixToQuat
from tests.conftest import gen

F64 = torch.float64


def randn(seed: int, shape: tuple[int, ...], dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.randn(shape, generator=gen(seed), dtype=dtype)


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_layers_equal_their_functional_maps(dtype, lead):
    theta, v, m = (
        randn(1, (*lead, 10), dtype),
        randn(2, (*lead, 6), dtype),
        randn(3, (*lead, 9), dtype),
    )
    q = ALayer()(theta)
    assert q.shape == (*lead, 4) and q.dtype == dtype
    assert torch.equal(q, symmatrixvec_to_quat(theta))
    q2, ev = ALayer(return_eigenvalues=True, solver="jacobi")(theta)
    q3, ev3 = symmatrixvec_to_quat(theta, solver="jacobi", return_eigenvalues=True)
    assert torch.equal(q2, q3) and torch.equal(ev, ev3) and ev.shape == (*lead, 4)
    R = SixDToRotmat()(v)
    assert R.shape == (*lead, 3, 3) and torch.equal(R, sixd_to_rotmat(v))
    R = SVDToRotmat()(m)
    assert R.shape == (*lead, 3, 3)
    assert torch.equal(R, special_orthogonalize(m.unflatten(-1, (3, 3))))


def test_layers_have_no_parameters_and_say_what_they_are():
    assert SymmetricMatrixToQuat is ALayer
    for layer in (ALayer(), SixDToRotmat(), SVDToRotmat()):
        assert list(layer.parameters()) == [] and list(layer.buffers()) == []
    assert "return_eigenvalues=True" in repr(ALayer(return_eigenvalues=True))
    assert "solver='eigh'" in repr(ALayer(solver="eigh"))


def test_layers_refuse_bad_input():
    with pytest.raises(ValueError, match="solver"):
        ALayer(solver="qr")
    with pytest.raises(ValueError, match=r"\(\.\.\., 10\)"):
        ALayer()(torch.zeros(4, 9))
    with pytest.raises(ValueError, match=r"\(\.\.\., 9\)"):
        SVDToRotmat()(torch.zeros(4, 10))


@pytest.mark.parametrize("layer", [ALayer, SixDToRotmat, SVDToRotmat])
def test_layers_end_a_bf16_autocast_model_in_float32(layer):
    size = {ALayer: 10, SixDToRotmat: 6, SVDToRotmat: 9}[layer]
    model = nn.Sequential(nn.Linear(8, 16), nn.ReLU(), nn.Linear(16, size), layer())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(randn(4, (32, 8), torch.float32))
    assert out.dtype == torch.float32
    out.square().sum().backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in model.parameters())


@pytest.mark.parametrize(
    "backend",
    [
        # graph capture of forward and backward (dynamo + AOTAutograd), no C++ compiler needed
        "aot_eager",
        # torch.compile's default: generates and compiles C++ (2.5 min cold on 2 busy cores)
        pytest.param("inductor", marks=pytest.mark.slow),
    ],
)
def test_compiled_model_ending_in_a_layer_trains(backend):
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(8, 32), nn.ReLU(), nn.Linear(32, 10), ALayer())
    compiled = torch.compile(model, backend=backend)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    x = randn(5, (64, 8), torch.float32)
    target = nn.functional.normalize(randn(6, (64, 4), torch.float32), dim=-1)
    losses = []
    for _ in range(8):
        q = compiled(x)
        loss = (1 - (q * target).sum(-1) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    torch.testing.assert_close(compiled(x), model(x), atol=1e-6, rtol=0)  # same function
    assert losses[-1] < losses[0] - 0.05


@pytest.mark.parametrize(
    ("layer", "size"),
    [(ALayer, 10), (SymmetricMatrixToQuat, 10), (SixDToRotmat, 6), (SVDToRotmat, 9)],
)
def test_each_layer_names_an_input_of_the_wrong_size(layer, size):
    with pytest.raises(ValueError, match=rf"expected a tensor of shape \(\.\.\., {size}\), got"):
        layer()(torch.randn(2, size + 1))
