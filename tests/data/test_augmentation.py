"""Training-time augmentation of image pairs: the pair swap, the multi-gap KITTI pairs and the
photometric jitter (`rotlearn.data.augment`, `ImagePairDataModule.finish_batch`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.data import KittiOdometryDataModule, MAVDataModule, read_kitti_poses
from rotlearn.data.augment import apply_jitter, swap_pairs
from rotlearn.errors import ConfigError
from rotlearn.geometry import quat_to_rotmat, relative_rotation, rotmat_to_quat, so3_exp
from tests.conftest import write_kitti, write_mav, yaw_sequence

pytest.importorskip("cv2")


def kitti_module(root: Path, **kwargs) -> KittiOdometryDataModule:
    defaults = {"train_sequences": ["01"], "test_sequences": ["00"], "image_size": 8}
    return KittiOdometryDataModule(str(root), num_workers=0, **{**defaults, **kwargs})


@pytest.fixture
def root(tmp_path) -> Path:
    g = torch.Generator().manual_seed(3)
    turns = {name: [so3_exp(0.05 * torch.randn(3, generator=g, dtype=torch.float64)).numpy()
                    for _ in range(n)] for name, n in (("00", 8), ("01", 40))}  # fmt: skip
    return write_kitti(tmp_path, turns)


def loader_batches(dm: KittiOdometryDataModule, split: str) -> list[dict]:
    loader = {"train": dm.train_dataloader, "val": dm.val_dataloader, "test": dm.test_dataloader}
    return list(loader[split]())


# -- the pair swap -------------------------------------------------------------------------------


def test_swap_pairs_exchanges_frames_and_inverts_targets():
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (5, 6, 4, 4), generator=g, dtype=torch.uint8)
    R = so3_exp(torch.randn(5, 3, generator=g))
    q = rotmat_to_quat(R)
    swap = torch.tensor([True, False, True, False, False])
    out, R2, q2 = swap_pairs(images, R, q, swap)
    assert torch.equal(out[swap, :3], images[swap, 3:]) and torch.equal(
        out[swap, 3:], images[swap, :3]
    )
    assert torch.equal(out[~swap], images[~swap])
    assert torch.equal(R2[swap], R[swap].mT) and torch.equal(R2[~swap], R[~swap])
    torch.testing.assert_close(quat_to_rotmat(q2), R2, atol=1e-6, rtol=0)
    torch.testing.assert_close(R2 @ R, torch.where(swap[:, None, None], torch.eye(3), R @ R))


def test_training_batches_are_swapped_exactly(root):
    dm = kitti_module(root, swap_pairs=0.5, batch_size=16)
    dm.setup()
    train = dm.sets["train"]
    frames = np.load(train.index.caches[0])
    seen = 0
    for raw in loader_batches(dm, "train"):
        swap, idx = raw["swap"], raw["index"]
        assert raw["input"].dtype == torch.uint8  # the loader only draws; finish_batch swaps
        batch = dm.finish_batch(raw)
        assert "swap" not in batch and "jitter" not in batch
        first = torch.from_numpy(frames[train.index.first[idx]]).float() / 255
        second = torch.from_numpy(frames[train.index.second[idx]]).float() / 255
        s = swap[:, None, None, None]
        torch.testing.assert_close(batch["input"][:, :3], torch.where(s, second, first))
        torch.testing.assert_close(batch["input"][:, 3:], torch.where(s, first, second))
        target = torch.where(swap[:, None, None], train.R[idx].mT, train.R[idx])
        torch.testing.assert_close(batch["R"], target)
        torch.testing.assert_close(quat_to_rotmat(batch["q"]), target, atol=1e-5, rtol=0)
        seen += int(swap.sum())
    assert 0 < seen < len(train)  # about half of the 39 training pairs


def test_validation_and_test_batches_are_never_augmented(root):
    dm = kitti_module(root, swap_pairs=1.0, photometric={"brightness": 0.5}, val_fraction=0.1)
    dm.setup()
    assert all(bool(b["swap"].all()) for b in loader_batches(dm, "train"))
    for split in ("val", "test"):
        for raw in loader_batches(dm, split):
            assert "swap" not in raw and "jitter" not in raw
            batch = dm.finish_batch(raw)
            torch.testing.assert_close(batch["R"], dm.sets[split].R[raw["index"]])
            torch.testing.assert_close(batch["input"], raw["input"].float() / 255)
    # the OOD evaluation's loaders, over the training split too, are plain as well
    assert "swap" not in next(iter(dm.eval_loader("train")))


def test_same_seed_same_draws_other_seed_other_draws(root):
    def draws(seed: int) -> list[torch.Tensor]:
        dm = kitti_module(root, swap_pairs=0.5, photometric={"contrast": 0.3}, seed=seed)
        dm.setup()
        return [torch.cat([b["index"][:, None].float(), b["swap"][:, None], b["jitter"]], 1)
                for b in loader_batches(dm, "train")]  # fmt: skip

    a, b, c = draws(0), draws(0), draws(1)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(torch.equal(x, y) for x, y in zip(a, c, strict=True))


def test_mav_gray_pairs_are_swapped_and_jittered_in_the_normalised_space(tmp_path):
    root = write_mav(tmp_path, frames=30)
    photometric = {"brightness": 0.3, "contrast": 0.3}
    dm = MAVDataModule(str(root), resize=10, image_size=8, num_workers=0, swap_pairs=1.0,
                       photometric=photometric)  # fmt: skip
    dm.setup()
    raw = loader_batches(dm, "train")[0]
    batch = dm.finish_batch(raw, dtype=torch.float64)
    frames = raw["input"].double() / 255
    expected = apply_jitter(frames.roll(1, dims=1), raw["jitter"], 1)
    torch.testing.assert_close(batch["input"], (expected - 0.45) / 0.25)
    torch.testing.assert_close(batch["R"], raw["R"].double().mT)


def test_swap_is_off_by_default(root):
    dm = kitti_module(root)
    dm.setup()
    raw = loader_batches(dm, "train")[0]
    assert "swap" not in raw and "jitter" not in raw


# -- several frame gaps --------------------------------------------------------------------------


def test_deltas_make_a_pair_per_gap_per_frame_with_its_relative_rotation(root):
    dm = kitti_module(root, deltas=[1, 2, 5], delta=3, val_fraction=0.0)  # every training pair
    dm.setup()
    train, test = dm.sets["train"].index, dm.sets["test"].index
    gaps = train.second - train.first
    assert len(train) == 39 + 38 + 35
    assert [int((gaps == d).sum()) for d in (1, 2, 5)] == [39, 38, 35]
    assert set(np.unique(test.second - test.first)) == {3}  # the test keeps `delta`
    R = torch.from_numpy(read_kitti_poses(root / "poses" / "01.txt")[:, :, :3])
    expected = relative_rotation(R[train.first], R[train.second])
    torch.testing.assert_close(torch.from_numpy(train.R), expected)


def test_deltas_null_keeps_delta(root):
    dm = kitti_module(root, delta=2)
    dm.setup()
    assert set(np.unique(dm.sets["train"].index.second - dm.sets["train"].index.first)) == {2}


def test_a_gap_longer_than_a_sequence_is_refused(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(6, 1.0), "01": yaw_sequence(3, 1.0)})
    with pytest.raises(ValueError, match="sequence 01: 3 frames, none with a frame 4 later"):
        kitti_module(root, deltas=[1, 4]).setup()


# -- photometric jitter --------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(
    brightness=st.floats(0.0, 0.99),
    contrast=st.floats(0.0, 0.99),
    u=st.lists(st.floats(0.0, 1.0), min_size=2, max_size=2),
    seed=st.integers(0, 2**16),
)
def test_jitter_stays_in_range_and_matches_its_factors(brightness, contrast, u, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 6, 5, 5, generator=g, dtype=torch.float64) * 0.5 + 0.25
    b = 1 + (2 * u[0] - 1) * brightness
    c = 1 + (2 * u[1] - 1) * contrast
    out = apply_jitter(x.clone(), torch.tensor([[b, c]]), 3)
    assert out.min() >= 0 and out.max() <= 1
    for frame in (slice(0, 3), slice(3, 6)):  # the same factors for both frames
        bright = b * x[:, frame]
        expected = (c * bright + (1 - c) * bright.mean()).clamp(0, 1)
        torch.testing.assert_close(out[:, frame], expected)


def test_jitter_factors_lie_within_their_bounds(root):
    dm = kitti_module(root, photometric={"brightness": 0.2, "contrast": 0.4}, batch_size=64)
    dm.setup()
    jitter = torch.cat([b["jitter"] for b in loader_batches(dm, "train")])
    assert not any("swap" in b and b["swap"].any() for b in loader_batches(dm, "train"))
    assert float(jitter[:, 0].min()) >= 0.8 and float(jitter[:, 0].max()) <= 1.2
    assert float(jitter[:, 1].min()) >= 0.6 and float(jitter[:, 1].max()) <= 1.4
    assert float(jitter.std(0).min()) > 0.05
    batch = dm.finish_batch(loader_batches(dm, "train")[0])
    assert float(batch["input"].min()) >= 0 and float(batch["input"].max()) <= 1


# -- validation ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("swap_pairs=1.5", "swap_pairs"),
        ("swap_pairs=-0.1", "swap_pairs"),
        ("swap_pairs=true", "swap_pairs"),
        ("deltas=[]", "deltas"),
        ("deltas=[1,0]", "deltas"),
        ("deltas=[1.5]", "deltas"),
    ],
)
def test_bad_augmentation_options_are_refused_by_the_config(make_cfg, on_disk, override, key):
    from rotlearn.config import validate

    with pytest.raises(ConfigError) as caught:
        validate(on_disk(make_cfg(["data=kitti", f"data.{override}"])))
    assert caught.value.key == f"data.{key}"


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"deltas": [2, 2]}, "deltas"),
        ({"photometric": {"gamma": 0.1}}, "photometric"),
        ({"photometric": {"brightness": 1.0}}, "photometric.brightness"),
        ({"photometric": {"contrast": -0.1}}, "photometric.contrast"),
        ({"photometric": 0.2}, "photometric"),
    ],
)
def test_bad_augmentation_options_are_refused(tmp_path, kwargs, key):
    with pytest.raises(ConfigError) as caught:
        kitti_module(tmp_path, **kwargs)
    assert caught.value.key == key


def test_the_options_are_config_keys_of_the_image_datamodules(make_cfg, on_disk, tmp_path):
    """The config validator reads the new keys from the constructors' signatures."""
    from hydra.utils import instantiate

    from rotlearn.config import validate

    over = ["data.swap_pairs=0.5", "data.photometric={brightness: 0.2, contrast: 0.1}"]
    cfg = on_disk(make_cfg(["data=kitti", f"data.root={tmp_path}", "data.deltas=[1,2]", *over]))
    validate(cfg)
    dm = instantiate(cfg.data)
    assert (dm.swap_pairs, dm.deltas) == (0.5, [1, 2])
    assert dm.photometric == {"brightness": 0.2, "contrast": 0.1}
    validate(on_disk(make_cfg(["data=mav", *over])))
    with pytest.raises(ConfigError, match=r"data\.swap_pairs"):
        validate(on_disk(make_cfg(["data=kitti", "data.swap_pairs=half"])))
