"""Validation comes from the training side, never from the test side: one proof per dataset."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.data import KittiOdometryDataModule, MAVDataModule, ShapeNetDataModule
from rotlearn.data.pairs import PairIndex
from rotlearn.data.splits import frame_keys, hold_out_tail
from rotlearn.data.synthetic import SyntheticWahbaDataModule
from rotlearn.errors import ConfigError
from tests.conftest import write_kitti, write_mav, yaw_sequence

pytest.importorskip("cv2")


def _pairs(index: PairIndex) -> set[tuple[str, int, int]]:
    caches = [str(c) for c in index.caches]
    return {(caches[s], int(a), int(b)) for s, a, b in
            zip(index.source, index.first, index.second, strict=True)}  # fmt: skip


def _frames_by_cache(index: PairIndex) -> dict[str, np.ndarray]:
    out: dict[str, list[int]] = {}
    for cache, frame in frame_keys(index):
        out.setdefault(cache, []).append(frame)
    return {k: np.asarray(sorted(v)) for k, v in out.items()}


def assert_disjoint(train: PairIndex, val: PairIndex, test: PairIndex) -> None:
    """No test pair or frame in validation; no training frame in validation, and every training
    frame more than the largest pair distance away from every validation frame of its cache."""
    assert len(val) > 0
    assert not frame_keys(val) & frame_keys(test)
    assert not _pairs(val) & _pairs(test)
    assert not frame_keys(val) & frame_keys(train)
    distance = int(np.abs(train.second - train.first).max())
    trained = _frames_by_cache(train)
    for cache, frames in _frames_by_cache(val).items():
        if cache in trained:
            gaps = np.abs(frames[:, None] - trained[cache][None, :])
            assert gaps.min() > distance


def test_kitti_validation_is_the_tail_of_each_training_sequence(tmp_path):
    sequences = {"00": yaw_sequence(12, 1.0), "01": yaw_sequence(40, 1.0),
                 "02": yaw_sequence(30, -1.0)}  # fmt: skip
    root = write_kitti(tmp_path, sequences, size=(12, 8))
    dm = KittiOdometryDataModule(str(root), train_sequences=["01", "02"], test_sequences=["00"],
                                 image_size=8, num_workers=0, deltas=[1, 3],
                                 val_fraction=0.2)  # fmt: skip
    dm.setup()
    train, val, test = (dm.sets[s].index for s in ("train", "val", "test"))
    assert_disjoint(train, val, test)
    # each training sequence gives its last 20 % of frames (at least a pair distance + 1)
    by_name = {name: val.source == i for i, name in enumerate(val.names)}
    assert np.minimum(val.first, val.second)[by_name["01"]].min() == 40 - 8
    assert np.minimum(val.first, val.second)[by_name["02"]].min() == 30 - 6
    assert np.maximum(train.first, train.second).max() < 32 - 3
    # validation pairs never carry the training augmentation and are never corrupted
    assert not dm.sets["val"].corrupted.any()


def test_kitti_held_out_sequences_validate_and_are_never_trained_or_tested(tmp_path):
    sequences = {name: yaw_sequence(10, 1.0) for name in ("00", "01", "02")}
    root = write_kitti(tmp_path, sequences, size=(12, 8))
    dm = KittiOdometryDataModule(str(root), train_sequences=["01", "02"], test_sequences=["00"],
                                 val_sequences=["02"], image_size=8, num_workers=0,
                                 val_fraction=0.0)  # fmt: skip
    dm.setup()
    train, val, test = (dm.sets[s].index for s in ("train", "val", "test"))
    assert train.names == ["01"] and len(val) == 9 and set(val.names) >= {"02"}
    assert_disjoint(train, val, test)
    # an unseen street: its validation pairs count as unseen like the test street's
    assert bool(dm.unseen_pairs("val").all()) and bool(dm.unseen_pairs("test").all())
    with pytest.raises(ConfigError, match="val_sequences"):
        KittiOdometryDataModule(str(root), test_sequences=["00"], val_sequences=["00"])


def test_mav_validation_is_the_scene_tail_without_any_test_frame(tmp_path):
    root = write_mav(tmp_path / "mav", frames=120)
    dm = MAVDataModule(str(root), image_size=16, resize=20, num_workers=0, test_fraction=0.2,
                       val_fraction=0.3)  # fmt: skip
    dm.setup()
    train, val, test = (dm.sets[s].index for s in ("train", "val", "test"))
    assert_disjoint(train, val, test)
    # the MAV test pairs are a random part of the whole scene (the paper's protocol), so some
    # test pairs lie in the validation region: those and every pair sharing a frame with them
    # are left out of validation
    tail = np.minimum(val.first, val.second).min()
    assert (np.minimum(test.first, test.second) >= tail).any()


def test_mav_scenes_sharing_frames_never_train_on_a_validation_frame(tmp_path):
    """A training scene whose pairs read frames of another scene's validation tail (both index
    the flea3 cache) trained on those validation frames."""
    root = write_mav(tmp_path / "mav", frames=30)
    (root / "pairs" / "transition.csv").write_text("".join(f"{i},{i + 1}\n" for i in range(5, 19)))
    dm = MAVDataModule(str(root), train_scenes=["outdoor", "transition"], test_scenes=["indoor"],
                       val_fraction=0.3, resize=18, image_size=16, num_workers=0)  # fmt: skip
    dm.setup()
    train, val, test = (dm.sets[s].index for s in ("train", "val", "test"))
    assert_disjoint(train, val, test)
    assert len(train) > 0


def test_shapenet_validation_clouds_are_held_out_training_clouds(demo_data):
    dm = ShapeNetDataModule(str(demo_data["pts"]), num_val=1, test_rotations=3)
    dm.setup()
    train, val, test = dm.clouds[0], dm.clouds[1], dm.clouds[2]
    assert len(val) == 1 and len(train) == 5

    def same(a, b):
        return any(x.shape == y.shape and torch.equal(x, y) for x in a for y in b)

    assert not same(val, test) and not same(val, train)
    # a request for more than a fifth of the training clouds is capped (training keeps 4/5)
    capped = ShapeNetDataModule(str(demo_data["pts"]), num_val=100)
    capped.setup()
    assert len(capped.clouds[1]) == 1 and len(capped.clouds[0]) == 5


def test_synthetic_validation_and_test_samples_differ():
    dm = SyntheticWahbaDataModule(num_matches=8, num_val=50, num_test=50, eval_batch_size=50)
    val = dm.draw(1, 0, 50)["input"]
    test = dm.draw(2, 0, 50)["input"]
    assert not (val[:, None] == test[None, :]).all(-1).all(-1).any()


@settings(max_examples=60, deadline=None)
@given(
    lengths=st.lists(st.integers(2, 60), min_size=1, max_size=4),
    deltas=st.lists(st.integers(1, 6), min_size=1, max_size=3, unique=True),
    fraction=st.floats(0.0, 0.9),
    test_every=st.integers(2, 7),
    shared=st.booleans(),
)
def test_the_tail_split_never_shares_a_frame(lengths, deltas, fraction, test_every, shared):
    """Whatever the sequences, gaps and fraction, and where sources read overlapping frames of
    one cache (MAV's scenes): validation and training share no frame, are more than a pair
    distance apart, and no validation pair reads a frame of the test pairs."""
    parts = []
    for i, n in enumerate(lengths):
        first = np.concatenate([np.arange(max(n - d, 0)) for d in deltas]).astype(np.int64)
        second = first + np.repeat(deltas, [max(n - d, 0) for d in deltas])
        start, cache = (10 * i, "c.npy") if shared else (0, f"c{i}.npy")
        rotations, source = np.zeros((len(first), 3, 3)), np.zeros(len(first), np.int64)
        parts.append(PairIndex([Path(cache)], source, first + start, second + start, rotations,
                               [f"s{i}"]))  # fmt: skip
    index = PairIndex.concat(parts)
    is_test = np.arange(len(index)) % test_every == 0
    test, rest = index.subset(is_test), index.subset(~is_test)
    train, val = hold_out_tail(rest, fraction, exclude=test)
    assert len(train) + len(val) <= len(rest)
    assert not frame_keys(val) & frame_keys(test)
    assert not frame_keys(val) & frame_keys(train)
    gaps = np.zeros(len(rest.caches), dtype=np.int64)  # each source's pair distance
    np.maximum.at(gaps, rest.source, np.abs(rest.second - rest.first))

    def frames(index):  # (cache name, source, frame) of every frame a pair reads
        rows = zip(index.source, index.first, index.second, strict=True)
        return [(str(index.caches[s]), s, f) for s, a, b in rows for f in (a, b)]

    for cache, s, v in frames(val):  # more than the larger pair distance from a training frame
        for other_cache, t, f in frames(train):
            if other_cache == cache:
                assert abs(int(v) - int(f)) > max(gaps[s], gaps[t])
    if fraction == 0:
        assert len(val) == 0 and len(train) == len(rest)


def test_a_source_keeps_its_own_training_pairs_beside_a_wider_source(tmp_path):
    """Two sources of one cache, pair distances 1 and 6: the first source's training pairs two
    frames before its validation tail were dropped for the second source's distance."""
    first = np.concatenate([np.arange(29), 100 + np.arange(55)])
    second = first + np.where(first < 100, 1, 6)
    source = (first >= 100).astype(np.int64)
    index = PairIndex([Path("c.npy"), Path("c.npy")], source, first, second,
                      np.zeros((len(first), 3, 3)), ["a", "b"])  # fmt: skip
    train, val = hold_out_tail(index, 0.2)
    kept = set(zip(train.first.tolist(), train.second.tolist(), strict=True))
    assert (21, 22) in kept and (22, 23) not in kept  # a gap of its own distance, 1
    assert min(val.first[val.source == 0]) == 24


def test_a_validation_sequence_missing_from_data_root_is_refused_before_anything_is_built(
    tmp_path,
):
    """`data.val_sequences` is part of the KITTI layout that validation checks (as the training
    and test sequences are): a sequence data.root lacks is named before any datamodule runs."""
    from rotlearn.config import ConfigError, compose

    still = {seq: [np.eye(3)] * 4 for seq in ("00", "01", "10")}
    root = write_kitti(tmp_path / "kitti", still)
    base = [
        "data=kitti",
        f"data.root={root}",
        "data.train_sequences=[1]",
        "data.test_sequences=[0]",
    ]
    assert compose([*base, "data.val_sequences=[10]"]).data.val_sequences == [10]
    with pytest.raises(ConfigError, match=r"data\.val_sequences: .*kitti lacks sequences/07/"):
        compose([*base, "data.val_sequences=[7]"])
