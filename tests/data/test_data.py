"""Synthetic Wahba data: the generative model of paper eq. 27, seeding, fixed and redrawn splits."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from rotlearn.data import SyntheticWahbaDataModule, wahba_batch
from rotlearn.geometry import angle, quat_to_rotmat

TRAIN, VAL, TEST = 0, 1, 2


def test_batch_follows_the_generative_model():
    g = torch.Generator().manual_seed(0)
    sigma = 0.01
    batch = wahba_batch(64, 50, math.radians(90), sigma, generator=g, dtype=torch.float64)
    assert batch["input"].shape == (64, 50, 6) and batch["R"].shape == (64, 3, 3)
    u, v = batch["input"][..., :3], batch["input"][..., 3:]
    assert torch.allclose(u.norm(dim=-1), torch.ones(64, 50, dtype=torch.float64))
    residual = v - u @ batch["R"].transpose(-1, -2)
    # 64 * 50 * 3 = 9600 Gaussian draws: the sample std is within 5% of sigma (about 7 std. errors).
    assert residual.std().item() == pytest.approx(sigma, rel=0.05)
    assert torch.allclose(quat_to_rotmat(batch["q"]), batch["R"], atol=1e-12)
    assert (batch["q"][..., 3] >= 0).all()


def test_rotation_angles_are_uniform_below_phi_max():
    g = torch.Generator().manual_seed(1)
    n, phi_max = 20000, math.radians(100)
    R = wahba_batch(n, 3, phi_max, 0.0, generator=g, dtype=torch.float64)["R"]
    angles = angle(R, torch.eye(3, dtype=torch.float64))
    assert angles.max() < phi_max
    # U[0, phi_max): mean phi_max / 2, std phi_max / sqrt(12); allow 5 standard errors.
    tolerance = 5 * phi_max / math.sqrt(12 * n)
    assert abs(angles.mean().item() - phi_max / 2) < tolerance


def _module(**kw) -> SyntheticWahbaDataModule:
    defaults = dict(num_matches=10, batch_size=4, batches_per_epoch=2, num_val=8, num_test=8)
    return SyntheticWahbaDataModule(**{**defaults, **kw})


def _at_epoch(dm: SyntheticWahbaDataModule, epoch: int) -> SyntheticWahbaDataModule:
    dm.trainer = SimpleNamespace(current_epoch=epoch, lightning_module=None)
    return dm


def test_training_batches_are_redrawn_each_epoch_but_reproducible():
    a0 = _at_epoch(_module(seed=3), 0).draw(TRAIN, 1, 4)
    b0 = _at_epoch(_module(seed=3), 0).draw(TRAIN, 1, 4)
    a1 = _at_epoch(_module(seed=3), 1).draw(TRAIN, 1, 4)
    other_batch = _at_epoch(_module(seed=3), 0).draw(TRAIN, 0, 4)
    other_seed = _at_epoch(_module(seed=4), 0).draw(TRAIN, 1, 4)
    assert torch.equal(a0["input"], b0["input"])
    for different in (a1, other_batch, other_seed):
        assert not torch.allclose(a0["input"], different["input"])


def test_validation_and_test_sets_are_fixed_unless_redrawn():
    fixed = [_at_epoch(_module(), e).draw(VAL, 0, 4)["R"] for e in (0, 5)]
    assert torch.equal(fixed[0], fixed[1])
    test = _at_epoch(_module(), 0).draw(TEST, 0, 4)["R"]
    assert not torch.allclose(fixed[0], test)
    redrawn = [_at_epoch(_module(redraw_test=True), e).draw(VAL, 0, 4)["R"] for e in (0, 5)]
    assert not torch.allclose(redrawn[0], redrawn[1])


def test_loaders_cover_the_requested_sizes():
    dm = _module(num_val=10, eval_batch_size=4, batches_per_epoch=3)
    assert [r["draw_size"] for r in dm.val_dataloader()] == [4, 4, 2]
    assert sum(r["draw_size"] for r in dm.train_dataloader()) == 12
    batch = dm.on_after_batch_transfer(next(iter(dm.test_dataloader())), 0)
    assert batch["input"].shape == (4, 10, 6) and batch["input"].dtype == torch.float32


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("phi_max_deg", 0.0),
        ("phi_max_deg", 181.0),
        ("sigma", -0.1),
        ("num_matches", 0),
        ("batch_size", 2.5),
        ("seed", -1),
    ],
)
def test_bad_values_are_refused_naming_the_key(make_cfg, key, value):
    from rotlearn.config import ConfigError, validate

    with pytest.raises(ConfigError) as err:
        validate(make_cfg([f"data.{key}={value}"]))
    assert err.value.key == f"data.{key}"
