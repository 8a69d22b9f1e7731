"""PointNet's output gain: a per-sample log-scale of the belief that leaves every rotation alone."""

from __future__ import annotations

import pytest
import torch

from rotlearn.heads import make_head
from rotlearn.nets import PointNet


def _pair(seed: int = 0) -> tuple[PointNet, PointNet]:
    """The same weights with and without the gain (the gain net has one more output)."""
    torch.manual_seed(seed)
    gained = PointNet(10, point_channels=(16, 32), head_channels=(16,), output_gain=True)
    plain = PointNet(10, point_channels=(16, 32), head_channels=(16,))
    state = gained.state_dict()
    last = max(k for k in state if k.startswith("head_mlp") and k.endswith("weight"))
    bias = last.replace("weight", "bias")
    plain.load_state_dict({**state, last: state[last][:-1], bias: state[bias][:-1]})
    return gained, plain


def test_output_gain_scales_the_output_by_exp_of_the_extra_number():
    gained, plain = _pair()
    points = torch.randn(5, 20, 6)
    with torch.no_grad():
        gained.head_mlp[-1].bias[-1] = 1.5  # a known log-gain offset
        features = gained.pool(gained.point_mlp(points))
        log_gain = gained.head_mlp(features)[..., -1:]
        out = gained(points)
    assert out.shape == (5, 10)
    torch.testing.assert_close(out, plain(points) * log_gain.exp())


@pytest.mark.parametrize("rep", ["a", "fisher", "svd9d"])
def test_output_gain_moves_the_belief_not_the_rotation(rep):
    """Every head's rotation is invariant to a positive scale of its input: the gain changes the
    concentration (DT scales by the gain) and nothing else."""
    head = make_head(rep)
    raw = torch.randn(6, head.out_dim, dtype=torch.float64)
    gain = torch.rand(6, 1, dtype=torch.float64) * 50 + 0.1
    base, scaled = head(raw), head(raw * gain)
    torch.testing.assert_close(scaled.R, base.R)
    if base.dt is not None:
        torch.testing.assert_close(scaled.dt, base.dt * gain.squeeze(-1))


def test_output_gain_is_clamped_and_differentiable():
    net = PointNet(9, point_channels=(8, 16), head_channels=(8,), output_gain=True)
    with torch.no_grad():
        net.head_mlp[-1].bias[-1] = 1e4  # an overflowing log-gain is clamped
    points = torch.randn(3, 10, 6, requires_grad=True)
    out = net(points)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(points.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(5,), (2, 3, 5), (1, 5)])
def test_gained_takes_any_batch_shape_and_is_differentiable(dtype, shape):
    from rotlearn.nets.pointnet import LOG_GAIN_MAX, gained

    out = torch.randn(shape, dtype=dtype) * 3
    result = gained(out)
    assert result.shape == (*shape[:-1], shape[-1] - 1) and result.dtype == dtype
    torch.testing.assert_close(result, out[..., :-1] * out[..., -1:].exp())
    big = out.clone()
    big[..., -1] = 1e4
    torch.testing.assert_close(gained(big), big[..., :-1] * torch.tensor(LOG_GAIN_MAX).exp())
    x = torch.randn(shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(gained, (x,))
