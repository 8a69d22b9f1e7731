"""The correlation pair network: the cost volume against a per-sample loop, its gradients, the net's
shapes for any batch, gradient flow, order sensitivity, and its config."""

from __future__ import annotations

import itertools

import pytest
import torch
from hydra.utils import instantiate

from rotlearn.nets import PairCNN, PairCorrelationNet, correlation
from tests.conftest import DTYPES, demo_overrides, gen


def naive_correlation(first: torch.Tensor, second: torch.Tensor, radius: int) -> torch.Tensor:
    """The cost volume one sample, displacement and pixel at a time (B, C, H, W inputs)."""
    batch, channels, height, width = first.shape
    side = 2 * radius + 1
    out = torch.zeros(batch, side * side, height, width, dtype=first.dtype)
    for b, (k, (dy, dx)), y, x in itertools.product(
        range(batch),
        enumerate(itertools.product(range(-radius, radius + 1), repeat=2)),
        range(height),
        range(width),
    ):
        if 0 <= y + dy < height and 0 <= x + dx < width:
            out[b, k, y, x] = (first[b, :, y, x] * second[b, :, y + dy, x + dx]).sum() / channels
    return out


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("radius", [0, 1, 2])
def test_correlation_matches_a_per_sample_loop(dtype, radius):
    first = torch.randn(2, 3, 5, 4, generator=gen(radius), dtype=dtype)
    second = torch.randn(2, 3, 5, 4, generator=gen(10 + radius), dtype=dtype)
    out = correlation(first, second, radius)
    assert out.shape == (2, (2 * radius + 1) ** 2, 5, 4) and out.dtype == dtype
    torch.testing.assert_close(out, naive_correlation(first, second, radius))


def test_correlation_takes_any_batch_shape():
    first = torch.randn(2, 3, 4, 5, 6, generator=gen(0))
    second = torch.randn(2, 3, 4, 5, 6, generator=gen(1))
    out = correlation(first, second, 1)
    assert out.shape == (2, 3, 9, 5, 6)
    torch.testing.assert_close(out[1, 2], correlation(first[1, 2:3], second[1, 2:3], 1)[0])
    single = correlation(first[0, 0], second[0, 0], 1)  # no batch axis: (C, H, W)
    torch.testing.assert_close(single, out[0, 0])


def test_a_shifted_map_peaks_at_its_shift():
    """second(y, x) = first(y - 1, x + 2): the largest cost of an inner pixel is the displacement
    (dy, dx) = (1, -2), where the map matches itself (mean of squares ~ 1 against ~ 0)."""
    first = torch.randn(1, 64, 12, 12, generator=gen(3))
    second = torch.roll(first, shifts=(1, -2), dims=(-2, -1))
    out = correlation(first, second, 3)[0, :, 4:8, 4:8]
    k = (1 + 3) * 7 + (-2 + 3)
    assert (out.argmax(dim=0) == k).all()


def test_correlation_gradcheck():
    first = torch.randn(2, 3, 4, 5, dtype=torch.float64, generator=gen(4), requires_grad=True)
    second = torch.randn(2, 3, 4, 5, dtype=torch.float64, generator=gen(5), requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: correlation(a, b, 2), (first, second))


@pytest.mark.parametrize(
    ("first", "second", "radius", "message"),
    [
        ((2, 3, 4, 4), (2, 3, 4, 5), 1, "one shape"),
        ((4, 4), (4, 4), 1, "one shape"),
        ((2, 3, 4, 4), (2, 3, 4, 4), -1, "radius"),
    ],
)
def test_correlation_refuses_bad_input(first, second, radius, message):
    with pytest.raises(ValueError, match=message):
        correlation(torch.zeros(first), torch.zeros(second), radius)


def small_net(dtype=torch.float32, **kwargs) -> PairCorrelationNet:
    torch.manual_seed(0)
    args = {"out_dim": 10, "in_channels": 6, "image_size": 32, "channels": [8], "radius": 2,
            "head_channels": [8, 16], "hidden": 16} | kwargs  # fmt: skip
    return PairCorrelationNet(**args).to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(
    ("in_channels", "image_size", "channels", "batch"),
    [(6, 32, [8], 3), (2, 33, [8], 1), (6, 64, [8, 8], 5), (2, 16, [4], 2)],
)
def test_output_shape_for_any_batch(dtype, in_channels, image_size, channels, batch):
    net = small_net(dtype, in_channels=in_channels, image_size=image_size, channels=channels).eval()
    pairs = torch.randn(batch, in_channels, image_size, image_size, dtype=dtype, generator=gen(1))
    out = net(pairs)
    assert out.shape == (batch, 10) and out.dtype == dtype and torch.isfinite(out).all()
    torch.testing.assert_close(net(pairs[:1]), out[:1])  # eval: a sample does not see the batch


def test_every_parameter_gets_a_gradient():
    net = small_net()
    net(torch.randn(4, 6, 32, 32, generator=gen(2))).square().sum().backward()
    for name, parameter in net.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_a_swapped_pair_gives_another_output():
    net = small_net().eval()
    pairs = torch.randn(3, 6, 32, 32, generator=gen(6))
    swapped = torch.cat((pairs[:, 3:], pairs[:, :3]), dim=1)
    assert (net(pairs) - net(swapped)).abs().amax(dim=1).min() > 1e-4


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("net.in_channels=3", r"net\.in_channels: should be a multiple of 2, got 3"),
        ("net.radius=-1", r"net\.radius: should be greater than or equal to 0, got -1"),
    ],
)
def test_bad_arguments_are_refused(make_cfg, on_disk, override, message):
    from rotlearn.config import ConfigError, validate

    with pytest.raises(ConfigError, match=message):
        validate(on_disk(make_cfg(["data=kitti", "net=pair_corr", override])))


@pytest.mark.parametrize("data", ["kitti", "mav"])
def test_net_pair_corr_composes_and_runs_on_a_batch(make_cfg, demo_data, data):
    from rotlearn.config import validate

    cfg = make_cfg([f"data={data}", "net=pair_corr", "rep=a", *demo_overrides(demo_data, data)])
    validate(cfg)
    net, dm = instantiate(cfg.net), instantiate(cfg.data)
    assert isinstance(net, PairCorrelationNet)
    assert net.in_channels == cfg.data.pair_channels and net.image_size == cfg.data.image_size
    dm.setup("fit")
    batch = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
    assert net(batch["input"][:2]).shape == (2, 10)


@pytest.mark.parametrize(
    ("net", "sizes"),
    [
        (PairCorrelationNet, {"channels": (4,), "head_channels": (8,)}),
        (PairCNN, {"channels": (4, 8)}),
    ],
)
def test_output_gain_scales_a_pair_nets_output_by_exp_of_the_extra_number(net, sizes):
    """net.output_gain=true on a pair net: the same weights without the gain give the output
    before its scale (the gain net has one more output)."""
    torch.manual_seed(0)
    with_gain = net(10, image_size=16, hidden=16, output_gain=True, **sizes)
    plain = net(10, image_size=16, hidden=16, **sizes)
    state = with_gain.state_dict()
    weight, bias = "regressor.2.weight", "regressor.2.bias"
    plain.load_state_dict({**state, weight: state[weight][:-1], bias: state[bias][:-1]})
    with torch.no_grad():
        with_gain.regressor[2].bias[-1] = 1.5  # a known log-gain offset
    pairs = torch.randn(3, 6, 16, 16, generator=gen(1))
    raw = []
    with_gain.regressor.register_forward_hook(lambda module, args, out: raw.append(out))
    with torch.no_grad():
        out = with_gain(pairs)
    log_gain = raw[0][:, -1:]
    assert out.shape == (3, 10)
    torch.testing.assert_close(out, plain(pairs) * log_gain.exp())
