"""Heteroscedastic data (issue 17): per-sample noise levels and numbers of distinct points, the
laws they follow, repetition that a max-pooling net cannot see, seeding, and refused settings."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from rotlearn.data import SyntheticWahbaDataModule, wahba_batch
from rotlearn.data.heteroscedastic import check_range, log_uniform, repeat_rows, uniform_counts
from rotlearn.errors import ConfigError
from rotlearn.nets import PointNet

TRAIN, VAL, TEST = 0, 1, 2
SIGMAS, MATCHES = (0.01, 1.0), (3, 40)


def _hetero(n: int, seed: int = 0, dtype=torch.float64, **kw) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    args = {"sigma_range": SIGMAS, "matches_range": MATCHES, **kw}
    return wahba_batch(n, MATCHES[1], math.radians(180), 0.05, generator=g, dtype=dtype, **args)


def test_noise_levels_are_log_uniform_in_the_range():
    n = 4000
    sigma = _hetero(n)["sigma"]
    assert sigma.min() >= SIGMAS[0] and sigma.max() <= SIGMAS[1]
    # log-uniform: each quarter of [log lo, log hi] holds 1/4 of the draws (std 0.007 for n = 4000)
    t = (sigma.log() - math.log(SIGMAS[0])) / math.log(SIGMAS[1] / SIGMAS[0])
    quarters = torch.bincount((t * 4).long().clamp(max=3), minlength=4) / n
    assert torch.allclose(quarters, torch.full((4,), 0.25, dtype=quarters.dtype), atol=0.04)


def test_each_sample_has_its_own_noise_level():
    batch = _hetero(256, matches_range=None)
    u, v = batch["input"][..., :3], batch["input"][..., 3:]
    residual = v - u @ batch["R"].transpose(-1, -2)  # (B, N, 3): N(0, sigma_b^2 I) per sample
    sample_std = residual.pow(2).mean(dim=(-1, -2)).sqrt()
    # 120 draws per sample: the ratio's std is about 1 / sqrt(240) = 0.065; allow 6 of them
    assert ((sample_std / batch["sigma"]).log().abs() < 0.4).all()


def test_match_counts_are_uniform_integers_in_the_range():
    n = 3800
    counts = _hetero(n)["num_matches"]
    assert counts.dtype == torch.int64
    values = torch.arange(MATCHES[0], MATCHES[1] + 1)
    freq = (counts.unsqueeze(-1) == values).double().mean(0)  # 38 values, 100 draws each
    assert freq.sum() == 1.0
    assert (freq - 1 / len(values)).abs().max() < 6 * math.sqrt(1 / len(values) / n)


def test_missing_rows_repeat_the_samples_own_matches():
    batch = _hetero(64)
    x, counts = batch["input"], batch["num_matches"]
    for b in range(len(x)):  # a test, not a hot path
        n = int(counts[b])
        distinct = x[b, :n]
        assert torch.equal(x[b], distinct[torch.arange(x.shape[1]) % n])
        assert len(torch.unique(distinct, dim=0)) == n


def test_difficulty_is_sigma_over_sqrt_matches():
    batch = _hetero(100)
    expected = batch["sigma"] / batch["num_matches"].double().sqrt()
    assert torch.equal(batch["difficulty"], expected)


def test_homoscedastic_batches_are_unchanged_and_draw_first():
    """Without ranges: the old batch (no extra keys). The extra draws come after the old ones, so a
    degenerate range [s, s] reproduces the homoscedastic batch of noise s value for value."""
    g = torch.Generator().manual_seed(5)
    plain = wahba_batch(32, 40, math.pi, 0.2, generator=g, dtype=torch.float64)
    assert set(plain) == {"input", "R", "q"}
    same = _hetero(32, seed=5, sigma_range=(0.2, 0.2), matches_range=None)
    for key in plain:
        assert torch.allclose(plain[key], same[key], rtol=0, atol=1e-15)
    assert (same["num_matches"] == 40).all() and torch.allclose(
        same["sigma"], plain["q"].new_full((32,), 0.2)
    )


def test_repeat_rows_matches_its_formula():
    x = torch.arange(2 * 5 * 2).view(2, 5, 2)
    out = repeat_rows(x, torch.tensor([2, 5]))
    assert torch.equal(out[0, :, 0], torch.tensor([0, 2, 0, 2, 0]))
    assert torch.equal(out[1], x[1])


def test_pointnet_cannot_see_repeated_rows():
    """Max pooling: a cloud of n points and the same cloud filled to N rows by repetition give the
    same output, so the net sees exactly n distinct matches."""
    torch.manual_seed(0)
    net = PointNet(out_dim=10, point_channels=(16, 32), head_channels=(8,)).double()
    cloud = torch.randn(3, 7, 6, dtype=torch.float64)
    filled = repeat_rows(torch.cat((cloud, torch.zeros(3, 13, 6, dtype=torch.float64)), 1),
                         torch.tensor([7, 7, 7]))  # fmt: skip
    assert torch.equal(filled[:, 7:14], cloud)
    torch.testing.assert_close(net(filled), net(cloud), rtol=0, atol=1e-12)


def _module(**kw) -> SyntheticWahbaDataModule:
    base = dict(num_matches=20, batch_size=8, batches_per_epoch=2, num_val=8, num_test=8,
                sigma_range=[0.01, 0.5], matches_range=[3, 20])  # fmt: skip
    dm = SyntheticWahbaDataModule(**{**base, **kw})
    dm.trainer = SimpleNamespace(current_epoch=0, lightning_module=None)
    return dm


def test_module_draws_are_reproducible_per_seed_split_and_index():
    a, b = _module(seed=1).draw(TRAIN, 0, 8), _module(seed=1).draw(TRAIN, 0, 8)
    for key in ("input", "sigma", "num_matches", "difficulty"):
        assert torch.equal(a[key], b[key])
    for other in (_module(seed=2).draw(TRAIN, 0, 8), _module(seed=1).draw(TEST, 0, 8)):
        assert not torch.equal(a["sigma"], other["sigma"])


def test_module_honours_dtype_and_device():
    batch = _module().draw(VAL, 0, 8, device="cpu", dtype=torch.float64)
    for key in ("input", "R", "q", "sigma", "difficulty"):
        assert batch[key].dtype == torch.float64 and batch[key].device.type == "cpu"
    assert batch["num_matches"].dtype == torch.int64


def test_laws_accept_float32():
    g = torch.Generator().manual_seed(0)
    s = log_uniform(10, 0.1, 0.2, generator=g, dtype=torch.float32)
    assert s.dtype == torch.float32 and ((s >= 0.1) & (s <= 0.2)).all()
    assert set(uniform_counts(200, 4, 5, generator=g).tolist()) == {4, 5}


@pytest.mark.parametrize(
    ("kw", "key"),
    [
        ({"sigma_range": [0.0, 0.1]}, "sigma_range"),
        ({"sigma_range": [-0.1, 0.1]}, "sigma_range"),
        ({"sigma_range": [0.5, 0.1]}, "sigma_range"),
        ({"sigma_range": [0.1]}, "sigma_range"),
        ({"sigma_range": "ab"}, "sigma_range"),
        ({"sigma_range": [0.1, float("inf")]}, "sigma_range"),
        ({"matches_range": [1, 20]}, "matches_range"),
        ({"matches_range": [3.5, 20]}, "matches_range"),
        ({"matches_range": [10, 5]}, "matches_range"),
        ({"matches_range": [3, 15]}, "matches_range"),  # hi != num_matches (20)
        ({"matches_range": [3, 30]}, "matches_range"),
    ],
)
def test_bad_ranges_are_refused_naming_the_key(kw, key):
    with pytest.raises(ConfigError) as info:
        _module(**kw)
    assert info.value.key == key


def test_check_range_passes_null_and_good_pairs():
    assert check_range("k", None, minimum=0) is None
    assert check_range("k", [2, 2], minimum=2, integer=True) == (2.0, 2.0)
    with pytest.raises(ConfigError, match="hi <= 1"):
        check_range("k", [0.5, 2], minimum=0, maximum=1)


def _shapenet(**kw):
    from rotlearn.data import ShapeNetDataModule

    dm = ShapeNetDataModule("unused", rotations_per_cloud=16, test_rotations=16, **kw)
    g = torch.Generator().manual_seed(0)
    cloud = torch.randn(50, 3, generator=g, dtype=torch.float64)  # no files: clouds set directly
    dm.clouds = {TRAIN: [cloud], VAL: [cloud], TEST: [cloud]}
    dm.trainer = SimpleNamespace(current_epoch=0, lightning_module=None)
    return dm, cloud


def test_shapenet_noise_and_dropout_per_sample():
    dm, cloud = _shapenet(noise_range=[0.01, 0.1], keep_range=[0.2, 0.6])
    batch = dm.draw(TEST, 0, 16, dtype=torch.float64)
    x, y, n = batch["input"][..., :3], batch["input"][..., 3:], batch["num_points"]
    assert ((batch["sigma"] >= 0.01) & (batch["sigma"] <= 0.1)).all()
    assert ((n >= 10) & (n <= 30)).all() and len(n.unique()) > 1  # ceil(f * 50), f in [0.2, 0.6]
    torch.testing.assert_close(batch["difficulty"], batch["sigma"] / n.double().sqrt())
    for b in range(16):  # a test, not a hot path
        k = int(n[b])
        kept = x[b, :k]
        assert torch.equal(x[b], kept[torch.arange(50) % k])  # the rest repeats the kept points
        assert len(torch.unique(kept, dim=0)) == k  # distinct points of the cloud
        assert (kept[:, None] == cloud).all(-1).any(-1).all()  # each a point of the cloud
        residual = y[b, :k] - kept @ batch["R"][b].T
        assert residual.std() == pytest.approx(float(batch["sigma"][b]), rel=0.6)
    again = dm.draw(TEST, 0, 16, dtype=torch.float64)
    assert all(torch.equal(batch[k], again[k]) for k in batch)


def test_shapenet_without_ranges_is_unchanged():
    dm, _ = _shapenet()
    batch = dm.draw(TEST, 0, 16, dtype=torch.float64)
    assert set(batch) == {"input", "R", "q"}
    x, y = batch["input"][..., :3], batch["input"][..., 3:]
    torch.testing.assert_close(y, x @ batch["R"].transpose(-1, -2))
    only_keep, _ = _shapenet(keep_range=[0.5, 0.5])
    kept = only_keep.draw(TEST, 0, 16, dtype=torch.float64)
    torch.testing.assert_close(kept["R"], batch["R"])  # extra draws come after the rotations
    assert (kept["num_points"] == 25).all() and (kept["sigma"] == 0).all()
    torch.testing.assert_close(kept["difficulty"], torch.full((16,), 0.2, dtype=torch.float64))


@pytest.mark.parametrize(
    ("kw", "key"),
    [
        ({"noise_range": [0.0, 0.1]}, "noise_range"),
        ({"noise_range": [0.2, 0.1]}, "noise_range"),
        ({"keep_range": [0.0, 0.5]}, "keep_range"),
        ({"keep_range": [0.5, 1.5]}, "keep_range"),
        ({"keep_range": [0.5]}, "keep_range"),
    ],
)
def test_shapenet_bad_ranges_are_refused_naming_the_key(kw, key):
    with pytest.raises(ConfigError) as info:
        _shapenet(**kw)
    assert info.value.key == key


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("data.sigma_range=[0.5,0.1]", "data.sigma_range"),
        ("data.matches_range=[3,99]", "data.matches_range"),
    ],
)
def test_a_bad_range_on_the_command_line_names_the_config_key(make_cfg, override, key):
    from rotlearn.cli.train import ConfigError, build

    with pytest.raises(ConfigError, match=rf"config key {key}:"):
        build(make_cfg([override]))
