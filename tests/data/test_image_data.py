"""KITTI and MAV readers, the frame cache and corruption, on tiny datasets written here."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.data import (
    KittiOdometryDataModule,
    MAVDataModule,
    corrupted_flags,
    draw_erasing_boxes,
    erase_boxes,
    match_poses,
    read_kitti_poses,
)
from rotlearn.errors import ConfigError
from rotlearn.geometry import angle_deg, relative_rotation, so3_exp
from tests.conftest import pose_line, rot_y, write_kitti, write_mav, yaw_sequence

cv2 = pytest.importorskip("cv2")


def kitti_module(root: Path, **kwargs) -> KittiOdometryDataModule:
    defaults = {"train_sequences": ["01"], "test_sequences": ["00"], "image_size": 8}
    return KittiOdometryDataModule(str(root), num_workers=0, **{**defaults, **kwargs})


# -- relative-rotation convention --------------------------------------------------------------


def test_relative_rotation_maps_camera_1_directions_to_camera_2():
    """A world direction seen from two camera-to-world orientations: d_2 = C_21 d_1."""
    g = torch.Generator().manual_seed(0)
    R_w1 = so3_exp(torch.randn(5, 3, generator=g, dtype=torch.float64))
    R_w2 = so3_exp(torch.randn(5, 3, generator=g, dtype=torch.float64))
    d_w = torch.randn(5, 3, 1, generator=g, dtype=torch.float64)
    d_1, d_2 = R_w1.mT @ d_w, R_w2.mT @ d_w
    torch.testing.assert_close(relative_rotation(R_w1, R_w2) @ d_1, d_2)


def test_kitti_target_of_a_known_yaw(tmp_path):
    """The camera turns +3 degrees about its y axis (down) per frame: a point straight ahead in
    frame i lies at -3 degrees about y in frame i + 1, so C_21 = Exp(-3 deg * y)."""
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 3.0), "01": yaw_sequence(3, 1.0)})
    dm = kitti_module(root)
    dm.setup()
    test = dm.sets["test"]
    assert len(test) == 3 and len(dm.sets["train"]) == 2
    expected = torch.from_numpy(rot_y(-3.0)).float().expand(3, 3, 3)
    torch.testing.assert_close(test.R, expected, atol=1e-6, rtol=0)
    ahead = torch.tensor([0.0, 0.0, 1.0])
    moved = test.R[0] @ ahead
    assert moved[0] < 0  # the point ahead moves to the left (x right, y down, z forward)


def test_delta_pairs_frames_delta_apart(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(6, 2.0), "01": yaw_sequence(3, 1.0)})
    dm = kitti_module(root, delta=2)
    dm.setup()
    test = dm.sets["test"]
    assert list(test.index.second - test.index.first) == [2] * 4
    assert torch.allclose(angle_deg(test.R, torch.eye(3)), torch.tensor(4.0), atol=1e-3)


def test_batches_stack_the_two_frames_as_channels(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    dm = kitti_module(root)
    dm.setup()
    frames = np.load(dm.sets["test"].index.caches[0])
    batch = dm.sets["test"].__getitems__([2, 0])
    assert batch["input"].shape == (2, 6, 8, 8) and batch["input"].dtype == torch.uint8
    assert np.array_equal(batch["input"][0, :3].numpy(), frames[2])
    assert np.array_equal(batch["input"][0, 3:].numpy(), frames[3])
    floats = dm.on_after_batch_transfer(batch, 0)["input"]
    assert floats.dtype == torch.float32 and float(floats.max()) <= 1.0
    # the one finishing step, with the device and dtype given by the caller
    double = dm.finish_batch(batch, "cpu", torch.float64)
    assert double["input"].dtype == double["R"].dtype == torch.float64
    torch.testing.assert_close(double["input"].float(), floats)


def _first_test_batch_shape(root: Path) -> tuple[int, ...]:
    dm = KittiOdometryDataModule(str(root), ["01"], ["00"], image_size=8, num_workers=1)
    dm.setup()
    return tuple(next(iter(dm.test_dataloader()))["input"].shape)


def test_loader_workers_start_inside_a_joblib_job(tmp_path):
    """`hydra/launcher=joblib` runs each job in a loky process, whose default start method
    ("loky") cannot start a loader worker ("'Process' object has no attribute 'env'")."""
    joblib = pytest.importorskip("joblib")
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    kitti_module(root).setup()  # the frame caches, written once here
    jobs = joblib.Parallel(n_jobs=2, backend="loky")  # n_jobs=1 would run in this process
    shape = jobs(joblib.delayed(_first_test_batch_shape)(root) for _ in range(1))[0]
    assert shape == (3, 6, 8, 8)


# -- frame cache -------------------------------------------------------------------------------


def test_cache_is_reused_without_decoding(tmp_path, monkeypatch):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    kitti_module(root).setup()
    cached = sorted((root / ".rotlearn_cache").glob("*.npy"))
    assert [p.name for p in cached] == ["00_image_2_8.npy", "01_image_2_8.npy"]

    def no_decoding(*args, **kwargs):
        raise AssertionError("the cache should have been reused")

    monkeypatch.setattr(cv2, "imread", no_decoding)
    dm = kitti_module(root)
    dm.setup()
    assert len(dm.sets["test"]) == 3
    monkeypatch.undo()
    # another image size is another cache
    kitti_module(root, image_size=6).setup()
    assert (root / ".rotlearn_cache" / "00_image_2_6.npy").is_file()


def test_a_changed_frame_rebuilds_the_cache(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    kitti_module(root).setup()
    frame = root / "sequences" / "00" / "image_2" / "000001.png"
    cv2.imwrite(str(frame), np.zeros((16, 24, 3), np.uint8))
    dm = kitti_module(root)
    dm.setup()
    assert not np.load(dm.sets["test"].index.caches[0])[1].any()


@pytest.mark.parametrize("shipped", ["frames of another size", "an npz archive"])
def test_a_shipped_cache_that_does_not_hold_the_recipes_frames_is_rebuilt(tmp_path, shipped):
    """A cache whose manifest matches was reused if its frames were square, of any size (a
    sparse file of 6000 x 6000 frames beside image_size=8 made one batch 432 MB), and an `.npz`
    in its place raised a bare AttributeError."""
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    kitti_module(root).setup()
    npy = root / ".rotlearn_cache" / "00_image_2_8.npy"
    genuine = np.load(npy).copy()
    with npy.open("wb") as f:
        if shipped == "an npz archive":
            np.savez(f, frames=genuine)
        else:
            np.save(f, np.zeros((len(genuine), 3, 16, 16), np.uint8))
    dm = kitti_module(root)
    dm.setup()
    assert dm.pair_shape() == (6, 8, 8)
    np.testing.assert_array_equal(np.load(npy), genuine)


def test_a_thin_frame_is_refused_before_it_is_resized(tmp_path, monkeypatch):
    """MAV's resize scales the shorter side up to `resize` before cropping: frames of 1 x 8000
    pixels (8 kB each) took 1.5 GB and 25 s for 12 frames, and one of 1 x 1,000,000 a raw
    cv2.error. A resized frame over the pixel budget is refused, naming the file."""
    from rotlearn.data import images

    monkeypatch.setattr(images, "MAX_PIXELS", 10_000)  # the same rule at a test's scale
    root = write_mav(tmp_path)
    for frame in (root / "flea3" / "data").glob("*.png"):
        cv2.imwrite(str(frame), np.zeros((1, 400), np.uint8))
    with pytest.raises(ValueError, match=r"data/\d+\.png: frame 0: a 400x1 frame resized to "
                       r"4000x10 is over the pixel budget \(10000 pixels\)$"):  # fmt: skip
        mav_module(root).setup()
    assert not list((root / ".rotlearn_cache").glob("*.npy"))
    assert images.resize_center_crop(np.zeros((20, 26), np.uint8), 10, 8).shape == (8, 8)
    thin = next((root / "flea3" / "data").glob("*.png"))  # rotlearn-predict's pair: named too
    with pytest.raises(ValueError, match=rf"^{re.escape(str(thin))}: a 400x1 frame resized"):
        mav_module(root).read_pair(thin, thin)


def test_a_square_size_over_the_pixel_budget_is_refused_before_resizing(tmp_path, monkeypatch):
    """KITTI's resize to data.image_size had no budget: a received checkpoint's image_size=30000
    made rotlearn-predict allocate 2.7 GB for the resize alone (then a cv2.error traceback)."""
    from rotlearn.data import images

    monkeypatch.setattr(images, "MAX_PIXELS", 10_000)  # the same rule at a test's scale
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    frame = sorted((root / "sequences" / "00" / "image_2").glob("*.png"))[0]
    with pytest.raises(ValueError, match=rf"^{re.escape(str(frame))}: a \d+x\d+ frame resized to "
                       r"101x101 is over the pixel budget \(10000 pixels\)$"):  # fmt: skip
        kitti_module(root, image_size=101).read_pair(frame, frame)
    assert images.resize_square(np.zeros((20, 26), np.uint8), 100).shape == (100, 100)


def test_a_batch_over_the_budget_is_refused_before_any_frame_is_read(tmp_path):
    """A received checkpoint chooses an evaluation's frame size and batches: image_size=8192
    with KITTI's default batches asked for 13 and 26 GB (the pixel budget stops only sizes over
    8192). A batch of pairs is at most MAX_BATCH_BYTES, refused in the constructor, so the
    pre-flight build of `rotlearn-train` and an evaluation stop before any frame is cached."""
    root = write_kitti(tmp_path / "kitti", {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    with pytest.raises(ConfigError, match=r"^config key batch_size: 32 pairs of 6 x 8192 x 8192 "
                       r"bytes take 12 GiB, over the 4 GiB a batch may take \(MAX_BATCH_BYTES\); "
                       r"lower it or image_size$"):  # fmt: skip
        kitti_module(root, image_size=8192)
    with pytest.raises(ConfigError, match=r"^config key eval_batch_size: 64 pairs of 6 x 4096 "):
        kitti_module(root, image_size=4096, batch_size=1)
    kitti_module(root, image_size=4096, batch_size=1, eval_batch_size=16)  # 1.5 GiB: taken
    mav = write_mav(tmp_path / "mav")
    with pytest.raises(ConfigError, match=r"^config key eval_batch_size: 200 pairs of 2 x 4096 "):
        mav_module(mav, resize=4096, image_size=4096, eval_batch_size=200)
    mav_module(mav, resize=4096, image_size=4096)  # 2 GiB for the default 64: taken
    assert not list(tmp_path.rglob(".rotlearn_cache"))


def test_a_sequence_or_scene_listed_twice_is_refused(tmp_path):
    """train_sequences=["02", "2"] read sequence 02 twice: 14 training pairs for its 7."""
    root = write_kitti(tmp_path / "kitti", {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    with pytest.raises(ConfigError, match=r"^config key train_sequences: lists '01' twice"):
        kitti_module(root, train_sequences=["01", "1"])
    with pytest.raises(ConfigError, match=r"^config key test_scenes: lists 'outdoor' twice"):
        mav_module(write_mav(tmp_path / "mav"), test_scenes=["outdoor", "outdoor"])


def test_a_split_leaving_no_training_pair_is_refused_naming_the_dataset(tmp_path):
    """A MAV scene of one pair: it went to test, and training failed at its first batch with
    PyTorch's "num_samples should be a positive integer value, but got num_samples=0"."""
    root = write_mav(tmp_path / "mav")
    (root / "pairs" / "outdoor.csv").write_text("0,1\n")
    with pytest.raises(ValueError, match=rf"^data.root {re.escape(str(root))}: no training pair "
                       r"left once the test and validation pairs are taken"):  # fmt: skip
        mav_module(root).setup()


def test_a_loader_worker_refuses_a_cache_rebuilt_since_the_run_read_it(tmp_path):
    """A loader worker started with `spawn` (macOS, Windows) opens the caches again by path: a
    cache another run had rebuilt meanwhile was read as this run's frames."""
    import os
    import pickle

    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    dm = kitti_module(root)
    dm.setup()
    pairs = dm.sets["test"]
    assert pickle.loads(pickle.dumps(pairs)).arrays[0].shape == pairs.arrays[0].shape
    worker = pickle.loads(pickle.dumps(pairs))  # what a spawned worker receives
    cache = pairs.index.caches[0]
    rebuilt = cache.with_name("rebuilt.npy")
    np.save(rebuilt, np.load(cache)[::-1].copy())
    os.replace(rebuilt, cache)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(cache))}: the frame cache changed"):
        worker.arrays  # noqa: B018


# -- KITTI bad input ---------------------------------------------------------------------------


def test_poses_with_fewer_lines_than_images_are_refused(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    poses = root / "poses" / "00.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:3]) + "\n")
    with pytest.raises(ValueError, match=r"00\.txt: 3 poses, but .*image_2 holds 4 frames"):
        kitti_module(root).setup()


def test_a_pose_line_that_is_not_12_numbers_is_named(tmp_path):
    path = tmp_path / "07.txt"
    path.write_text(pose_line(np.eye(3)) + "\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"07\.txt:2: expected 12 numbers .* got 11"):
        read_kitti_poses(path)
    path.write_text(pose_line(np.eye(3)).replace("0.000000e+00", "nan?", 1) + "\n")
    with pytest.raises(ValueError, match=r"07\.txt:1: not a number"):
        read_kitti_poses(path)


def test_a_non_orthonormal_rotation_is_named(tmp_path):
    path = tmp_path / "00.txt"
    sheared = np.eye(3)
    sheared[0, 1] = 0.05
    path.write_text(f"{pose_line(np.eye(3))}\n{pose_line(rot_y(5))}\n{pose_line(sheared)}\n")
    with pytest.raises(ValueError, match=r"00\.txt:3: the rotation is not orthonormal"):
        read_kitti_poses(path)
    reflection = np.diag([1.0, 1.0, -1.0])
    path.write_text(f"{pose_line(reflection)}\n")
    with pytest.raises(ValueError, match=r"00\.txt:1: .*det = -1"):
        read_kitti_poses(path)


def test_poses_are_projected_onto_so3(tmp_path):
    path = tmp_path / "00.txt"
    noisy = rot_y(30) + 1e-5
    path.write_text(pose_line(noisy) + "\n")
    R = read_kitti_poses(path)[0, :, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12


def test_an_unreadable_image_is_named_and_no_cache_is_left(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    bad = root / "sequences" / "00" / "image_2" / "000002.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"000002\.png: cannot be read as an image"):
        kitti_module(root).setup()
    leftovers = [p.name for p in (root / ".rotlearn_cache").iterdir() if p.name.startswith("00")]
    hidden = [p.name for p in (root / ".rotlearn_cache").iterdir() if p.name.startswith(".")]
    assert leftovers == [] and hidden == []


def test_a_missing_sequence_directory_is_named(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0)})
    with pytest.raises(
        FileNotFoundError, match=r"sequence 01: no directory .*sequences/01/image_2"
    ):
        kitti_module(root).setup()


def test_sequence_names_from_the_command_line_are_zero_padded(tmp_path):
    dm = KittiOdometryDataModule(str(tmp_path), train_sequences=[0, 2, "05"], test_sequences=[2])
    assert dm.train_sequences == ["00", "05"] and dm.test_sequences == ["02"]


# -- MAV -----------------------------------------------------------------------------------------


def mav_module(root: Path, **kwargs) -> MAVDataModule:
    defaults = {"resize": 10, "image_size": 8, "test_fraction": 0.25}
    return MAVDataModule(str(root), num_workers=0, **{**defaults, **kwargs})


def test_nearest_pose_matching():
    poses = np.array([0, 10, 20, 30], dtype=np.int64)
    frames = np.array([-3, 4, 6, 15, 29, 100], dtype=np.int64)
    nearest, gaps = match_poses(frames, poses)
    assert nearest.tolist() == [0, 0, 1, 1, 3, 3]  # a tie (15) takes the earlier pose
    assert gaps.tolist() == [3, 4, 4, 5, 1, 70]


def test_mav_targets_follow_the_matched_poses(tmp_path):
    root = write_mav(tmp_path)
    dm = mav_module(root, test_scenes=["outdoor", "indoor"])
    dm.setup()
    train, test = dm.sets["train"], dm.sets["test"]
    assert len(train) + len(dm.load("test")) > 0
    assert set(test.index.names) == {"outdoor", "indoor"}
    # 20 deg/s over ~50 ms: about 1 degree per pair, up to the 4 ms frame jitter
    angles = angle_deg(torch.cat([train.R, test.R]), torch.eye(3))
    assert ((angles > 0.75) & (angles < 1.3)).all()
    batch = test.__getitems__(list(range(len(test))))
    assert batch["input"].shape[1:] == (2, 8, 8)
    x = dm.finish_batch(batch)["input"]
    torch.testing.assert_close(x, (batch["input"].float() / 255 - 0.45) / 0.25)


def test_mav_test_split_is_seeded_and_disjoint(tmp_path):
    root = write_mav(tmp_path, frames=30)
    a, b, c = mav_module(root), mav_module(root), mav_module(root, seed=1)
    for dm in (a, b, c):
        dm.setup()
    key = lambda dm, s: set(dm.sets[s].index.first.tolist())  # noqa: E731
    assert key(a, "test") == key(b, "test")
    assert not key(a, "test") & key(a, "train")
    assert key(a, "test") != key(c, "test")


def test_a_pair_naming_a_missing_frame_is_refused(tmp_path):
    root = write_mav(tmp_path)
    (root / "pairs" / "outdoor.csv").write_text("0,1\n1,2\n2,99\n")
    with pytest.raises(ValueError, match=r"outdoor\.csv:3: frame 99 does not exist .*12 frames"):
        mav_module(root).setup()


def test_a_pose_gap_beyond_the_tolerance_names_the_frame(tmp_path):
    root = write_mav(tmp_path, pose_gap_after=1)
    with pytest.raises(ValueError, match=r"data\.csv:3: frame 1 .* no pose within 30 ms"):
        mav_module(root).setup()
    mav_module(root, pose_tolerance_ms=80).setup()  # a looser tolerance accepts it


def test_a_malformed_frame_list_line_is_named(tmp_path):
    root = write_mav(tmp_path)
    path = root / "flea3" / "data.csv"
    lines = path.read_text().splitlines()
    lines[4] = "123"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"data\.csv:5: expected 2 comma-separated fields"):
        mav_module(root).setup()


# -- corruption --------------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(height=st.integers(8, 300), width=st.integers(8, 300), seed=st.integers(0, 2**31))
def test_erasing_boxes_have_the_drawn_area_and_aspect(height, width, seed):
    boxes = draw_erasing_boxes(200, height, width, torch.Generator().manual_seed(seed))
    top, left, h, w = boxes.T.double()
    assert ((top >= 0) & (left >= 0) & (top + h <= height) & (left + w <= width)).all()
    tol = 0.5 / min(height, width) + 1.0 / (height * width)
    area = h * w / (height * width)
    assert ((area >= 0.25 - tol) & (area <= 0.5 + tol)).all()


def test_erasing_statistics_and_determinism():
    boxes = draw_erasing_boxes(4000, 224, 224, torch.Generator().manual_seed(3))
    _, _, h, w = boxes.T.double()
    area = h * w / 224**2
    assert abs(float(area.mean()) - 0.375) < 0.01  # U[0.25, 0.5]
    ratio = (h / w).log()
    assert float(ratio.min()) > math.log(0.33) - 0.02 and float(ratio.max()) < math.log(3) + 0.02
    assert abs(float(ratio.mean())) < 0.05  # log-uniform and symmetric
    again = draw_erasing_boxes(4000, 224, 224, torch.Generator().manual_seed(3))
    assert torch.equal(boxes, again)


def test_erase_zeroes_exactly_the_boxes_of_flagged_samples():
    images = torch.full((3, 6, 10, 12), 7, dtype=torch.uint8)
    boxes = torch.tensor([[[1, 2, 3, 4], [0, 0, 10, 12]]] * 3)
    out = erase_boxes(images, boxes, torch.tensor([True, False, True]))
    assert torch.equal(out[1], images[1])
    first, second = out[0, :3], out[0, 3:]
    assert (first[:, 1:4, 2:6] == 0).all() and int((first == 0).sum()) == 3 * 12
    assert (second == 0).all()
    assert (images == 7).all()


def test_corrupted_flags_mark_the_tail():
    assert corrupted_flags(5, 0.5).tolist() == [False] * 3 + [True] * 2
    assert corrupted_flags(10, 0.5).tolist() == [False] * 5 + [True] * 5
    assert not corrupted_flags(7, 0.0).any() and corrupted_flags(7, 1.0).all()


def test_corrupted_test_batches_are_erased_and_flagged(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(9, 1.0), "01": yaw_sequence(3, 1.0)})
    dm = kitti_module(root, corrupt_fraction=0.5, image_size=16)
    dm.setup()
    test = dm.sets["test"]
    batch = test.__getitems__(list(range(len(test))))
    assert batch["corrupted"].tolist() == [False] * 4 + [True] * 4
    clean = dm.finish_batch({**batch, "corrupted": torch.zeros(8, dtype=bool)})
    erased = dm.finish_batch(batch)
    changed = (clean["input"] != erased["input"]).flatten(1).any(1)
    assert changed.tolist() == batch["corrupted"].tolist()
    zero = (erased["input"][4:] == 0).float().mean(dim=(-1, -2))  # per image and channel
    assert ((zero >= 0.25 - 0.05) & (zero <= 0.5 + 0.1)).all()
    assert not dm.sets["val"].corrupted.any() and not dm.sets["train"].corrupted.any()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize(
    ("loss", "street_camera"),
    [("chordal", False), ("bingham", True)],
    ids=["chordal-without-camera", "bingham-with-camera"],
)
def test_the_kitti_demo_learner_beats_half_the_identity_error(
    tmp_path, make_cfg, seed, loss, street_camera
):
    """The demo recipe (experiment=kitti_ood_demo: the correlation pair network, A head) trained on
    the KITTI-format demo written here reaches under half the error of "predict identity" on the
    held-out sequence, for the model and data seeds 0 and 1 (docs/results.md, "The slow test"):
    with the paper's chordal loss on the world of issue 15 (no street camera; 0.42x and 0.40x when
    last measured), and with the Bingham NLL on the default world with its street camera (0.26x
    and 0.29x). The chordal loss on the camera world is at 0.59-0.61x, so that pair is not
    claimed."""
    from rotlearn.cli.train import train
    from rotlearn.data.demo.kitti import write_kitti_demo

    root = write_kitti_demo(tmp_path, street_camera=street_camera)
    overrides = [
        "experiment=kitti_ood_demo",
        "rep=a",
        f"loss={loss}",
        "~callbacks.ood",  # the rotation error only
        f"data.root={root}",
        f"seed={seed}",
        f"data.seed={seed}",
        "trainer.enable_progress_bar=false",
    ]
    metrics = train(make_cfg(overrides))
    assert metrics["test/err_mean"] < 0.5 * metrics["test/identity_err_mean"]


def test_the_ood_source_protocol_serves_chosen_pairs_flags_and_noise(tmp_path):
    from rotlearn.ood import OODDataSource

    root = write_kitti(tmp_path, {"00": yaw_sequence(9, 1.0), "01": yaw_sequence(4, 1.0)})
    dm = kitti_module(root, eval_batch_size=3)
    dm.setup()
    assert isinstance(dm, OODDataSource)
    assert dm.pair_count("test") == 8 and dm.pair_shape() == (6, 8, 8)
    batches = list(dm.eval_loader("test", indices=[7, 0, 3, 5]))
    assert [b["index"].tolist() for b in batches] == [[7, 0, 3], [5]]
    erase = torch.zeros(8, dtype=torch.bool)
    erase[3] = True
    flagged = [b["corrupted"].tolist() for b in dm.eval_loader("test", indices=[7, 3], erase=erase)]
    assert flagged == [[False, True]]
    assert dm.unseen_pairs("test").all()  # sequence 00 is never trained on
    noise = dm.noise_batch(2)
    assert noise["input"].shape == (2, 6, 8, 8) and noise["input"].dtype == torch.uint8
    torch.testing.assert_close(noise["input"], dm.noise_batch(2)["input"])  # seeded
    finished = dm.finish_batch(noise, "cpu", torch.float64)
    assert finished["input"].dtype == torch.float64 and not finished["corrupted"].any()
