"""Demo KITTI odometry and MAV datasets: layouts, determinism, images that agree with the poses;
rotlearn-make-demo-data."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from rotlearn.cli.make_demo_data import demo_writers, main
from rotlearn.data.demo import kitti as kitti_demo
from rotlearn.data.demo import mav as mav_demo
from rotlearn.data.demo.kitti import write_kitti_demo
from rotlearn.data.demo.mav import MAV_PAIR_GAPS, MAV_POSE_HEADER, write_mav_demo
from rotlearn.data.demo.synth import camera_matrix, exp_rotvec

KITTI = {"sequences": ("00", "01"), "frames": 6, "width": 248, "height": 76}  # 1 degree: 2.6 px
MAV = {"frames": 40, "width": 64, "height": 52}


@pytest.fixture(scope="module")
def kitti(tmp_path_factory) -> Path:
    return write_kitti_demo(tmp_path_factory.mktemp("kitti"), **KITTI)


@pytest.fixture(scope="module")
def kitti_exact(tmp_path_factory) -> Path:
    """The same dataset without the street camera: the exact renders the poses describe."""
    return write_kitti_demo(tmp_path_factory.mktemp("exact"), **KITTI, street_camera=False)


@pytest.fixture(scope="module")
def mav(tmp_path_factory) -> Path:
    return write_mav_demo(tmp_path_factory.mktemp("mav"), **MAV)


def _kitti_poses(root: Path, sequence: str) -> np.ndarray:
    """(frames, 3, 4) camera-to-world poses of a poses/<XX>.txt."""
    return np.loadtxt(root / "poses" / f"{sequence}.txt", ndmin=2).reshape(-1, 3, 4)


def _calib(root: Path, sequence: str) -> dict[str, np.ndarray]:
    lines = (root / "sequences" / sequence / "calib.txt").read_text().splitlines()
    return {k: np.array(v.split(), float) for k, v in (line.split(":") for line in lines)}


def _frames_csv(root: Path) -> np.ndarray:
    """Frame timestamps (ns, int64) of flea3/data.csv, checking each row's file name."""
    lines = (root / "flea3" / "data.csv").read_text().splitlines()
    assert lines[0] == "#timestamp [ns],filename"
    stamps, names = zip(*(line.split(",") for line in lines[1:]), strict=True)
    assert list(names) == [f"{t}.png" for t in stamps]
    return np.array(stamps, dtype=np.int64)


def _poses_csv(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """(pose timestamps (P,) ns int64, rows (P, 7): position, quaternion w x y z)."""
    lines = (root / "pose" / "data.csv").read_text().splitlines()
    assert lines[0] == MAV_POSE_HEADER
    rows = [line.split(",") for line in lines[1:]]
    return np.array([r[0] for r in rows], np.int64), np.array([r[1:] for r in rows], float)


def _rotmat_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of one Hamilton quaternion, scalar first (written independently of
    rotlearn.geometry, to check the file convention)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _angle_deg(C: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(C) - 1) / 2, -1.0, 1.0))))


def _warp_gain(first: np.ndarray, second: np.ndarray, K: np.ndarray, C_21: np.ndarray) -> float:
    """Mean |second - first| over mean |second - H first|, H = K C_21 K^-1, on the interior
    pixels that the warp covers: large when the rotation C_21 explains the image change."""
    height, width = first.shape[:2]
    H = K @ C_21 @ np.linalg.inv(K)
    warped = cv2.warpPerspective(first, H, (width, height), flags=cv2.INTER_LINEAR)
    covered = cv2.warpPerspective(np.ones((height, width), np.uint8), H, (width, height))
    inside = cv2.erode(covered, np.ones((5, 5), np.uint8)).astype(bool)
    a, b, c = (im.astype(np.float64)[inside] for im in (first, second, warped))
    return float(np.abs(b - a).mean() / np.abs(b - c).mean())


# ---- KITTI ---------------------------------------------------------------------------------------


def test_kitti_layout(kitti):
    assert kitti.name == "kitti"
    assert sorted(p.name for p in (kitti / "poses").iterdir()) == ["00.txt", "01.txt"]
    for sequence in KITTI["sequences"]:
        folder = kitti / "sequences" / sequence
        names = sorted(p.name for p in (folder / "image_2").iterdir())
        assert names == [f"{i:06d}.png" for i in range(KITTI["frames"])]
        image = cv2.imread(str(folder / "image_2" / names[0]), cv2.IMREAD_UNCHANGED)
        assert image.shape == (KITTI["height"], KITTI["width"], 3) and image.dtype == np.uint8
        times = np.loadtxt(folder / "times.txt")
        np.testing.assert_allclose(times, 0.1 * np.arange(KITTI["frames"]), atol=1e-9)
        calib = _calib(kitti, sequence)
        assert list(calib) == ["P0", "P1", "P2", "P3", "Tr"]
        assert all(v.shape == (12,) for v in calib.values())
        lines = (kitti / "poses" / f"{sequence}.txt").read_text().splitlines()
        assert len(lines) == KITTI["frames"] and all(len(line.split()) == 12 for line in lines)


def test_kitti_poses_are_rotations_starting_at_identity_moving_forward(kitti):
    poses = _kitti_poses(kitti, "00")
    R, t = poses[:, :, :3], poses[:, :, 3]
    np.testing.assert_array_equal(poses[0], np.hstack((np.eye(3), np.zeros((3, 1)))))
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=3e-6
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=3e-6)
    np.testing.assert_allclose(np.linalg.norm(np.diff(t, axis=0), axis=1), 1.0, atol=1e-5)
    angles = [_angle_deg(R[i].T @ R[i + 1]) for i in range(len(R) - 1)]
    assert max(angles) < 2.5 and np.mean(angles) > 0.3


def test_kitti_intrinsics_are_80_degrees_across_centred(kitti):
    K = _calib(kitti, "00")["P2"].reshape(3, 4)
    width, height = KITTI["width"], KITTI["height"]
    np.testing.assert_allclose(K[:, 3], 0.0)
    assert K[0, 0] == pytest.approx(K[1, 1])
    assert np.degrees(2 * np.arctan(width / 2 / K[0, 0])) == pytest.approx(80.0, abs=1e-3)
    assert (K[0, 2], K[1, 2]) == pytest.approx(((width - 1) / 2, (height - 1) / 2))


def _kitti_consecutive_pairs(kitti):
    """(sequence, i, frame i, frame i + 1, C_21 = R_{i+1}^T R_i from the pose file) of every
    consecutive pair of every demo sequence."""
    for sequence in KITTI["sequences"]:
        R = _kitti_poses(kitti, sequence)[:, :, :3]
        folder = kitti / "sequences" / sequence / "image_2"
        frames = [cv2.imread(str(folder / f"{i:06d}.png")) for i in range(KITTI["frames"])]
        for i in range(KITTI["frames"] - 1):
            yield sequence, i, frames[i], frames[i + 1], R[i + 1].T @ R[i]


def test_kitti_consecutive_frames_differ_by_the_written_rotation(kitti_exact):
    """Warping frame i by K C_21 K^-1, C_21 = R_{i+1}^T R_i from the pose file, reproduces frame
    i + 1 far better than frame i itself does: the images and the poses agree."""
    K = _calib(kitti_exact, "00")["P2"].reshape(3, 4)[:, :3]
    for sequence, i, first, second, C_21 in _kitti_consecutive_pairs(kitti_exact):
        if _angle_deg(C_21) > 0.5:
            assert _warp_gain(first, second, K, C_21) > 3.0, (sequence, i)
            assert _warp_gain(first, second, K, C_21.T) < 1.0  # the wrong way


def _perturbed(C: np.ndarray, degrees: float) -> list[np.ndarray]:
    """C turned further by `degrees` about each camera axis, either way (6 rotations)."""
    axes = np.vstack((np.eye(3), -np.eye(3)))
    return [exp_rotvec(np.radians(degrees) * axis) @ C for axis in axes]


def test_kitti_frames_pin_the_rotation_to_a_quarter_degree(kitti_exact):
    """The written rotation explains the image change clearly better than any rotation off it
    by 0.25 degrees (0.6 pixels here) about any axis: the poses are exact, not just roughly
    right."""
    K = _calib(kitti_exact, "00")["P2"].reshape(3, 4)[:, :3]
    for sequence, i, first, second, C_21 in _kitti_consecutive_pairs(kitti_exact):
        gain = _warp_gain(first, second, K, C_21)
        for wrong in _perturbed(C_21, 0.25):
            assert gain > 1.2 * _warp_gain(first, second, K, wrong), (sequence, i)


def test_the_street_camera_changes_the_pixels_and_nothing_else(kitti, kitti_exact):
    """With and without the street camera the same seed writes the same poses, times and
    calibration; the frames differ (exposure, noise, traffic) but show the same view: the
    exposure-normalised images still correlate strongly."""
    for name in sorted(p.relative_to(kitti) for p in kitti.rglob("*") if p.is_file()):
        if name.suffix != ".png":
            assert (kitti / name).read_bytes() == (kitti_exact / name).read_bytes(), name
            continue
        seen, exact = (cv2.imread(str(r / name)).astype(float) for r in (kitti, kitti_exact))
        assert not np.array_equal(seen, exact), name
        assert np.corrcoef(seen.ravel(), exact.ravel())[0, 1] > 0.5, name


def test_kitti_test_sequence_views_a_street_unseen_in_training_and_11_revisits_02(
    tmp_path, monkeypatch
):
    """Each sequence views its own street (so the default test sequence 00 is a scene never
    trained on), except the revisit 11, which views 02's street on its own trajectory; a
    street depends only on (seed, its sequence), not on which others are written."""
    from rotlearn.data.demo import natural

    drawn, real = [], natural.street_panorama
    monkeypatch.setattr(
        natural, "street_panorama", lambda rng, w: drawn.append(real(rng, w)) or drawn[-1]
    )
    small = {"frames": 3, "width": 62, "height": 19}
    root = write_kitti_demo(tmp_path / "a", sequences=("00", "02", "11"), **small)
    street_00, street_02, street_11 = drawn
    assert not np.array_equal(street_00, street_02)
    np.testing.assert_array_equal(street_11, street_02)
    assert kitti_demo.kitti_scene("11") == "02" and kitti_demo.kitti_scene("00") == "00"
    assert "11" in kitti_demo.KITTI_SEQUENCES
    poses = [(root / "poses" / f"{s}.txt").read_bytes() for s in ("02", "11")]
    assert poses[0] != poses[1]
    write_kitti_demo(tmp_path / "b", sequences=("02",), **small)
    np.testing.assert_array_equal(drawn[-1], street_02)


def test_kitti_is_deterministic_in_the_seed(kitti, tmp_path):
    same = write_kitti_demo(tmp_path / "same", **KITTI)
    other = write_kitti_demo(tmp_path / "other", **KITTI, seed=1)
    for sequence in KITTI["sequences"]:
        poses = f"poses/{sequence}.txt"
        image = f"sequences/{sequence}/image_2/000003.png"
        assert (same / poses).read_bytes() == (kitti / poses).read_bytes()
        assert (same / image).read_bytes() == (kitti / image).read_bytes()
        assert (other / poses).read_bytes() != (kitti / poses).read_bytes()
        assert (other / image).read_bytes() != (kitti / image).read_bytes()


# ---- MAV -----------------------------------------------------------------------------------------


def test_mav_layout(mav):
    assert mav.name == "mav"
    stamps = _frames_csv(mav)
    assert len(stamps) == MAV["frames"] and np.all(np.diff(stamps) > 0)
    files = sorted(p.name for p in (mav / "flea3" / "data").iterdir())
    assert files == sorted(f"{t}.png" for t in stamps)
    image = cv2.imread(str(mav / "flea3" / "data" / files[0]), cv2.IMREAD_UNCHANGED)
    assert image.shape == (MAV["height"], MAV["width"]) and image.dtype == np.uint8
    assert np.median(np.diff(stamps)) == pytest.approx(50e6, rel=0.1)  # ~20 Hz


def test_mav_frames_are_off_the_pose_clock_but_within_30_ms(mav):
    frames = _frames_csv(mav)
    pose_times, rows = _poses_csv(mav)
    assert np.all(np.diff(pose_times) == 5_000_000)  # 200 Hz
    assert not set(frames.tolist()) & set(pose_times.tolist())
    nearest = np.abs(frames[:, None] - pose_times[None, :]).min(axis=1)
    assert nearest.max() <= 30_000_000 and nearest.max() <= 1_500_000
    np.testing.assert_allclose(np.linalg.norm(rows[:, 3:], axis=1), 1.0, atol=1e-8)


def test_mav_pose_rate_keeps_the_nearest_pose_label_within_0_05_degrees(mav):
    _, rows = _poses_csv(mav)
    q = rows[:, 3:]
    step = np.degrees(2 * np.arccos(np.clip(np.abs((q[1:] * q[:-1]).sum(1)), 0, 1)))
    rate = step / 0.005  # deg/s
    assert rate.max() * 0.0015 < 0.05 and 5.0 < rate.mean() < 25.0


def test_mav_pairs_are_a_few_frames_apart_inside_disjoint_scenes(mav):
    ranges = {}
    for scene in ("outdoor", "transition", "indoor"):
        pairs = np.loadtxt(mav / "pairs" / f"{scene}.csv", delimiter=",", dtype=int, ndmin=2)
        assert len(pairs) > 0
        gaps = pairs[:, 1] - pairs[:, 0]
        assert set(gaps.tolist()) == set(MAV_PAIR_GAPS)
        assert len(np.unique(pairs, axis=0)) == len(pairs)
        assert pairs.min() >= 0 and pairs.max() < MAV["frames"]
        ranges[scene] = (pairs.min(), pairs.max())
    assert ranges["outdoor"][1] < ranges["transition"][0]
    assert ranges["transition"][1] < ranges["indoor"][0]


def test_mav_indoor_frames_are_darker_and_flatter(mav):
    stamps = _frames_csv(mav)

    def frame(i: int) -> np.ndarray:
        return cv2.imread(str(mav / "flea3" / "data" / f"{stamps[i]}.png"), cv2.IMREAD_GRAYSCALE)

    outdoor, indoor = frame(2), frame(MAV["frames"] - 2)
    assert indoor.mean() < outdoor.mean() - 20


def test_mav_frames_differ_by_the_rotation_of_their_nearest_poses(mav):
    """Inside a scene, the scalar-first quaternions of the nearest poses explain the motion
    between the frames of each written pair, clearly better than the inverse rotation or one a
    degree off about any axis (the transition cross-fades, so it is left out)."""
    stamps = _frames_csv(mav)
    pose_times, rows = _poses_csv(mav)
    R = [_rotmat_wxyz(rows[np.abs(pose_times - t).argmin(), 3:]) for t in stamps]
    K = camera_matrix(MAV["width"], MAV["height"])
    folder = mav / "flea3" / "data"
    frames = [cv2.imread(str(folder / f"{t}.png"), cv2.IMREAD_GRAYSCALE) for t in stamps]
    checked = 0
    for scene in ("outdoor", "indoor"):
        pairs = np.loadtxt(mav / "pairs" / f"{scene}.csv", delimiter=",", dtype=int, ndmin=2)
        for i, j in pairs:
            C_21 = R[j].T @ R[i]
            if _angle_deg(C_21) > 1.5:
                gain = _warp_gain(frames[i], frames[j], K, C_21)
                assert gain > 3.0, (scene, i, j)
                assert _warp_gain(frames[i], frames[j], K, C_21.T) < 1.0, (scene, i, j)
                for wrong in _perturbed(C_21, 1.0):  # 0.7 pixels here
                    assert gain > 1.2 * _warp_gain(frames[i], frames[j], K, wrong), (scene, i, j)
                checked += 1
    assert checked >= 5


def test_mav_is_deterministic_in_the_seed(mav, tmp_path):
    same = write_mav_demo(tmp_path / "same", **MAV)
    other = write_mav_demo(tmp_path / "other", **MAV, seed=1)
    for name in ("pose/data.csv", "flea3/data.csv", "pairs/indoor.csv"):
        assert (same / name).read_bytes() == (mav / name).read_bytes()
    first = sorted((mav / "flea3" / "data").iterdir())[5]
    assert (same / "flea3" / "data" / first.name).read_bytes() == first.read_bytes()
    assert (other / "pose" / "data.csv").read_bytes() != (mav / "pose" / "data.csv").read_bytes()


# ---- writing safely ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "write", [lambda out: write_kitti_demo(out, **KITTI), lambda out: write_mav_demo(out, **MAV)]
)
def test_an_interrupted_write_leaves_nothing_under_the_final_name(write, tmp_path, monkeypatch):
    real_imwrite, calls = cv2.imwrite, []

    def failing_imwrite(*args, **kwargs):
        calls.append(args[0])
        if len(calls) > 3:
            raise KeyboardInterrupt
        return real_imwrite(*args, **kwargs)

    monkeypatch.setattr(cv2, "imwrite", failing_imwrite)
    with pytest.raises(KeyboardInterrupt):
        write(tmp_path)
    assert len(calls) == 4 and list(tmp_path.iterdir()) == []


def test_an_interrupted_rewrite_keeps_the_old_dataset_and_a_finished_one_replaces_it(
    tmp_path, monkeypatch
):
    old = write_kitti_demo(tmp_path, **KITTI)
    (old / "stale.txt").write_text("from the previous run")
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: (_ for _ in ()).throw(OSError("disk")))
    with pytest.raises(OSError):
        write_kitti_demo(tmp_path, **KITTI)
    assert (old / "stale.txt").exists()
    monkeypatch.undo()
    write_kitti_demo(tmp_path, **KITTI)
    assert not (old / "stale.txt").exists() and (old / "poses" / "00.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["kitti"]


def test_a_folder_the_writer_did_not_make_is_never_replaced(tmp_path, monkeypatch, capsys):
    """`<out>/kitti` (or `<out>/mav`) that is no demo dataset (no DEMO_MARK: a user's own data,
    or a file) is refused before anything is rendered, and left as it was."""
    mine = tmp_path / "kitti"
    mine.mkdir()
    (mine / "real_data.txt").write_text("mine")
    (tmp_path / "mav").write_text("a file")
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: pytest.fail("rendered"))
    assert main(["--out", str(tmp_path), "--only", "kitti"]) == 1
    err = capsys.readouterr().err
    assert f"{mine} exists and is not a demo dataset rotlearn wrote" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    with pytest.raises(FileExistsError, match="mav exists and is not a demo dataset"):
        write_mav_demo(tmp_path, **MAV)
    assert (mine / "real_data.txt").read_text() == "mine" and (tmp_path / "mav").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kitti", "mav"]


def test_every_dataset_with_a_demo_module_is_offered():
    assert list(demo_writers()) == ["kitti", "mav", "shapenet"]


def test_main_writes_the_chosen_datasets(tmp_path, monkeypatch, capsys):
    written = []
    monkeypatch.setattr(kitti_demo, "write_demo", lambda out, seed: written.append(seed) or [out])
    monkeypatch.setattr(mav_demo, "write_demo", lambda out, seed: pytest.fail("not chosen"))
    assert main(["--out", str(tmp_path), "--seed", "3", "--only", "kitti"]) == 0
    assert written == [3] and "kitti" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--only", "kitti,lidar"])


def test_main_writes_the_kitti_demo_without_its_street_camera_when_asked(
    tmp_path, monkeypatch, capsys
):
    asked = []
    monkeypatch.setattr(kitti_demo, "write_kitti_demo", lambda out, **kw: asked.append(kw) or out)
    assert main(["--out", str(tmp_path), "--only", "kitti"]) == 0
    assert main(["--out", str(tmp_path), "--only", "kitti", "--no-street-camera"]) == 0
    assert [kw["street_camera"] for kw in asked] == [True, False]
    with pytest.raises(SystemExit):  # a writer without a camera says so, before writing
        main(["--out", str(tmp_path / "mav"), "--only", "mav", "--no-street-camera"])
    assert "the mav writer has no street camera" in capsys.readouterr().err
    assert not (tmp_path / "mav").exists()


@pytest.mark.parametrize("flag", [["--no-street-camera"], ["--scale", "paper"]])
def test_a_flag_one_chosen_writer_cannot_take_is_refused_before_any_writes(
    tmp_path, monkeypatch, capsys, flag
):
    """With every dataset chosen (the default), the kitti demo was written whole, which at the
    paper's scale takes minutes, before the mav writer refused the flag."""
    monkeypatch.setattr(kitti_demo, "write_kitti_demo", lambda out, **kw: pytest.fail("written"))
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "out"), *flag])
    assert "the mav writer" in capsys.readouterr().err and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seed", "-1"], r"argument --seed: must be in \[0, 4294967295\], got -1"),
        (["--seed", "2**32"], r"argument --seed: not an integer: '2\*\*32'"),
        (["--workers", "0"], r"argument --workers: must be in \[1, 256\], got 0"),
    ],
)
def test_a_seed_or_worker_count_out_of_range_is_named_before_writing(
    tmp_path, capsys, args, message
):
    """--seed -1 reached the mav writer, whose numpy error did not name --seed; --workers 0 was
    taken."""
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "out"), *args])
    assert re.search(message, capsys.readouterr().err) and not (tmp_path / "out").exists()


def test_the_smallest_mav_has_a_pair_in_every_scene(tmp_path):
    root = write_mav_demo(tmp_path, frames=36, width=32, height=26)
    for scene in ("outdoor", "transition", "indoor"):
        assert (root / "pairs" / f"{scene}.csv").read_text().strip()
    root = write_mav_demo(tmp_path, frames=10, width=32, height=26, gaps=(1,))
    for scene in ("outdoor", "transition", "indoor"):
        assert (root / "pairs" / f"{scene}.csv").read_text().strip()


def test_too_few_mav_frames_for_the_gaps_are_refused_before_writing(tmp_path):
    with pytest.raises(ValueError, match="scene"):
        write_mav_demo(tmp_path, frames=20, width=32, height=26)
    with pytest.raises(ValueError, match="gaps"):
        write_mav_demo(tmp_path, frames=40, width=32, height=26, gaps=(0, 2))
    assert list(tmp_path.iterdir()) == []


def test_the_kitti_writer_writes_the_same_files_with_several_workers(tmp_path):
    import hashlib

    from rotlearn.data.demo.kitti import write_kitti_demo

    def digest(root):
        return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip

    kw = {"sequences": ("00", "02"), "frames": 3, "width": 40, "height": 12}
    one = write_kitti_demo(tmp_path / "one", **kw)
    two = write_kitti_demo(tmp_path / "two", workers=2, **kw)
    assert digest(one) == digest(two) and len(digest(one)) > 6
