"""Untrusted datasets (issue 13): crafted bad files and escaping names, for every loader.

Each test copies a valid demo dataset (the session's `demo_data`) into tmp_path, corrupts one
file or names a path outside the root, and checks the error type, that the message names the file
and line (or frame, or the config key), and that nothing was written outside the cache folder
(and no partial cache left in it).
"""

from __future__ import annotations

import math
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

from rotlearn.data import KittiOdometryDataModule, MAVDataModule, ShapeNetDataModule
from rotlearn.data.mav import read_frame_list, read_pair_file
from rotlearn.errors import ConfigError, NonFiniteError
from rotlearn.io import plain_name, read_number_rows, resolve_inside
from rotlearn.nets.pointnet import PointNet

cv2 = pytest.importorskip("cv2")


# ---- helpers ------------------------------------------------------------------------------------


def copy_demo(demo_data: dict[str, Path], name: str, tmp_path: Path) -> Path:
    """A private copy of a demo dataset, `<tmp_path>/data/<dataset>`."""
    source = demo_data[name]
    root = tmp_path / "data" / source.name
    shutil.copytree(source, root, ignore=shutil.ignore_patterns(".rotlearn_cache"))
    return root


def files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file() or p.is_symlink()}


@contextmanager
def writes_only_complete_caches(tmp_path: Path, cache_dir: Path) -> Iterator[None]:
    """Assert that the block creates files only inside `cache_dir`, and there only whole caches
    (each `.npy` with its `.json` manifest, no temporary file)."""
    before = files_under(tmp_path)
    try:
        yield
    finally:
        new = files_under(tmp_path) - before
        outside = [p for p in new if not p.is_relative_to(cache_dir)]
        assert outside == [], f"files written outside the cache folder: {outside}"
        assert not [p for p in new if ".tmp" in p.name], f"partial cache left: {new}"
        stems = lambda suffix: {p.with_suffix("") for p in new if p.suffix == suffix}  # noqa: E731
        assert stems(".npy") == stems(".json"), f"a cache without its manifest: {new}"


def set_line(path: Path, lineno: int, text: str) -> None:
    """Replace line `lineno` (1-based) of a text file."""
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


def refuses(make, tmp_path, cache, error, pattern):
    """Run `make()` (build + setup a datamodule) expecting `error` matching `pattern`, with
    nothing written outside `cache`; returns the error."""
    with writes_only_complete_caches(tmp_path, cache), pytest.raises(error, match=pattern) as e:
        make()
    return e.value


# ---- KITTI --------------------------------------------------------------------------------------


def kitti(root: Path, cache: Path, **kw) -> KittiOdometryDataModule:
    args = {"train_sequences": ["02"], "test_sequences": ["00"], "image_size": 8, **kw}
    dm = KittiOdometryDataModule(str(root), num_workers=0, cache_dir=str(cache), **args)
    dm.setup()
    return dm


@pytest.mark.parametrize(
    ("column", "word", "pattern"),
    [
        (0, "nan", "not finite"),
        (5, "inf", "not finite"),
        (3, "nan", "not finite"),  # the translation: not used, still refused
        (4, "1e999", "not finite"),
        (7, "one", "not a number"),
        (11, None, "expected 12 numbers .* got 11"),
    ],
)
def test_kitti_pose_lines_are_checked(demo_data, tmp_path, column, word, pattern):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    poses = root / "poses" / "00.txt"
    numbers = poses.read_text().splitlines()[2].split()
    tail = [] if word is None else [word, *numbers[column + 1 :]]
    numbers = numbers[:column] + tail
    set_line(poses, 3, " ".join(numbers))
    refuses(lambda: kitti(root, cache), tmp_path, cache, ValueError, rf"00\.txt:3: {pattern}")


def test_kitti_too_few_pose_lines_name_the_file(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    poses = root / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join(lines[:-1]) + "\n")
    pattern = rf"00\.txt: {len(lines) - 1} poses, but .*image_2 holds {len(lines)} frames"
    refuses(lambda: kitti(root, cache), tmp_path, cache, ValueError, pattern)


def test_kitti_poses_that_are_a_named_pipe_are_named_so(demo_data, tmp_path):
    """A FIFO in place of poses/00.txt was reported as "no poses file"; it is named for what it
    is, and never opened (a read would hang)."""
    from rotlearn.io import UnreadableFileError

    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    poses = root / "poses" / "00.txt"
    poses.unlink()
    os.mkfifo(poses)
    pattern = r"00\.txt: a named pipe \(FIFO\), not a regular file; not read"
    refuses(lambda: kitti(root, cache), tmp_path, cache, UnreadableFileError, pattern)


def _png_bytes(width: int, height: int) -> bytes:
    image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return cv2.imencode(".png", image)[1].tobytes()


@pytest.mark.parametrize(
    ("content", "pattern"),
    [
        (b"", "cannot be read as an image"),
        ("truncated", "cannot be read as an image"),
        (b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4, "cannot be read as an image"),
        ("other size", r"frame 3 is 40x30 pixels, but frame 0 .* is 62x19"),
    ],
    ids=["zero-byte", "truncated", "garbage", "other-size"],
)
def test_kitti_bad_frames_are_named(demo_data, tmp_path, content, pattern):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    frame = root / "sequences" / "00" / "image_2" / "000003.png"
    if content == "truncated":
        content = frame.read_bytes()[: frame.stat().st_size // 2]
    elif content == "other size":
        content = _png_bytes(40, 30)
    frame.write_bytes(content)
    message = str(refuses(lambda: kitti(root, cache), tmp_path, cache, ValueError, pattern))
    assert str(frame) in message
    assert not (cache.exists() and any(p.name.startswith("00_") for p in cache.iterdir()))


def plant_kitti_sequence(root: Path, target: Path) -> None:
    """A valid sequence folder at `target` (a copy of sequence 00), outside or inside root."""
    shutil.copytree(root / "sequences" / "00", target)


@pytest.mark.parametrize("key", ["train_sequences", "test_sequences"])
@pytest.mark.parametrize("name", ["../../x", "..", "/abs/x", "a\\b"])
def test_kitti_sequence_names_cannot_leave_the_root(demo_data, tmp_path, key, name):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    plant_kitti_sequence(root, tmp_path / "data" / "x")  # what sequences/../../x would read
    shutil.copy(root / "poses" / "00.txt", tmp_path / "data" / "x.txt")
    make = lambda: kitti(root, cache, **{key: [name]})  # noqa: E731
    error = refuses(make, tmp_path, cache, ConfigError, "not a plain file or folder name")
    assert error.key == key


def test_kitti_traversal_from_the_command_line_names_the_config_key(demo_data, tmp_path, make_cfg):
    from rotlearn.cli.train import ConfigError, build

    root = copy_demo(demo_data, "kitti", tmp_path)
    plant_kitti_sequence(root, tmp_path / "data" / "x")
    cfg = make_cfg(["data=kitti", f"data.root={root}", "data.train_sequences=[../../x]"])
    with pytest.raises(ConfigError, match=r"data\.train_sequences: '\.\./\.\./x' is not a plain"):
        build(cfg)


def test_kitti_symlinked_sequence_outside_the_root_is_refused(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    outside = tmp_path / "elsewhere" / "03"
    plant_kitti_sequence(root, outside)
    (root / "sequences" / "03").symlink_to(outside, target_is_directory=True)
    shutil.copy(root / "poses" / "00.txt", root / "poses" / "03.txt")
    pattern = r"data\.train_sequences entry '03': .*sequences/03/image_2 resolves to .*outside"
    make = lambda: kitti(root, cache, train_sequences=["03"])  # noqa: E731
    refuses(make, tmp_path, cache, ValueError, pattern)
    kitti(root, cache, train_sequences=["02"])  # the same dataset loads without the link


def test_kitti_symlinked_frame_outside_the_root_is_refused(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    frame = root / "sequences" / "00" / "image_2" / "000002.png"
    outside = tmp_path / "secret.png"
    shutil.move(frame, outside)
    frame.symlink_to(outside)
    pattern = r"data\.test_sequences entry '00': .*000002\.png resolves to .*outside"
    refuses(lambda: kitti(root, cache), tmp_path, cache, ValueError, pattern)


@pytest.mark.parametrize(
    ("rename", "first"),
    [
        ({f"{i:06d}.png": f"{i}.png" for i in range(10)}, "0.png"),  # sorted: 0, 1, 10, 2, ...
        ({"000004.png": None, "000009.png": "000010.png"}, "000010.png"),  # 000004 missing
        ({"000003.png": "000003 (copy).png"}, "000003 (copy).png"),
        ({"000002.png": "0000002.png"}, "0000002.png"),
    ],
    ids=["unpadded", "gap", "copy", "seven-digits"],
)
def test_kitti_frames_must_be_named_by_their_zero_padded_index(demo_data, tmp_path, rename, first):
    """Frames are paired with pose lines in name order: 0.png ... 11.png used to sort as 0, 1,
    10, 11, 2, ... and silently take the wrong poses."""
    root, cache = copy_demo(demo_data, "kitti", tmp_path), tmp_path / "cache"
    folder = root / "sequences" / "00" / "image_2"
    for old, new in rename.items():
        if new is None:
            (folder / old).unlink()
        else:
            (folder / old).rename(folder / new)
    count = len(list(folder.glob("*.png")))
    poses = root / "poses" / "00.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:count]) + "\n")  # one per frame
    pattern = rf"sequence 00: .*image_2/{re.escape(first)} is not named as a frame: "
    message = str(refuses(lambda: kitti(root, cache), tmp_path, cache, ValueError, pattern))
    assert f"{folder / first} is not named" in message
    assert f"must be 000000.png to {count - 1:06d}.png" in message


# ---- MAV ----------------------------------------------------------------------------------------


def mav(root: Path, cache: Path, **kw) -> MAVDataModule:
    args = {"resize": 10, "image_size": 8, "test_fraction": 0.25, **kw}
    dm = MAVDataModule(str(root), num_workers=0, cache_dir=str(cache), **args)
    dm.setup()
    return dm


def test_mav_nan_quaternion_names_the_line(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    path = root / "pose" / "data.csv"
    fields = path.read_text().splitlines()[6].split(",")
    set_line(path, 7, ",".join([*fields[:-4], "nan", *fields[-3:]]))
    pattern = r"pose/data\.csv:7: not finite \(qw qx qy qz\)"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_a_repeated_time_stamp_with_another_pose_names_both_lines(demo_data, tmp_path):
    """The first pose used to win silently; which one is right is unknown."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    path = root / "pose" / "data.csv"
    lines = path.read_text().splitlines()
    stamp, *position, qw, qx, qy, qz = lines[6].split(",")
    conflicting = ",".join([stamp, *position, qx, qw, qz, qy])  # another rotation
    path.write_text("\n".join([*lines, conflicting]) + "\n")
    pattern = rf"pose/data\.csv:{len(lines) + 1}: time stamp {stamp.strip()} repeats line 7"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_a_repeated_identical_pose_is_read_once(demo_data, tmp_path):
    from rotlearn.data import read_pose_file

    root = copy_demo(demo_data, "mav", tmp_path)
    path = root / "pose" / "data.csv"
    stamps, quats = read_pose_file(path)
    lines = path.read_text().splitlines()
    stamp, *rest = lines[6].split(",")
    flipped = [f"{-float(v)}" for v in rest[-4:]]  # -q: the same rotation
    path.write_text("\n".join([*lines, lines[6], ",".join([stamp, *rest[:-4], *flipped])]) + "\n")
    again, quats_again = read_pose_file(path)
    np.testing.assert_array_equal(again, stamps)
    np.testing.assert_array_equal(quats_again, quats)


@pytest.mark.parametrize(
    ("line", "pattern"),
    [
        ("1.5e18,x.png", r"data\.csv:3: not an integer: '1\.5e18'"),
        ("1_403_636_580,x.png", r"data\.csv:3: not an integer"),
        ("1403636580000000000,../../x.png", r"data\.csv:3: '\.\./\.\./x\.png' is not a plain"),
        ("1403636580000000000,ABSOLUTE", r"data\.csv:3: '/.*x\.png' is not a plain"),
        ("1403636580000000000,..", r"data\.csv:3: '\.\.' is not a plain"),
    ],
    ids=["float-stamp", "underscores", "traversal", "absolute", "dotdot"],
)
def test_mav_frame_list_rows_are_checked(demo_data, tmp_path, line, pattern):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    target = tmp_path / "data" / "x.png"  # what flea3/data/../../x.png would read
    shutil.copy(next((root / "flea3" / "data").glob("*.png")), target)
    set_line(root / "flea3" / "data.csv", 3, line.replace("ABSOLUTE", str(target)))
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_frame_file_listed_twice_names_both_lines(demo_data, tmp_path):
    """Rows naming one file would each be decoded and cached: 4000 rows naming a 1 x 1 PNG once
    wrote a 201 MB cache."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    listing = root / "flea3" / "data.csv"
    lines = listing.read_text().splitlines()
    name, stamp = lines[1].split(",")[1], lines[4].split(",")[0]
    set_line(listing, 5, f"{stamp},{name}")
    pattern = rf"data\.csv:5: frame file '{re.escape(name)}' is listed again \(line 2\)"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


@pytest.mark.parametrize("kind", ["frames", "pairs"])
def test_mav_rows_listed_again_name_the_first_repeat_in_the_file(tmp_path, kind):
    """Of many rows listed again, the first one in the file is named, with the row it repeats:
    the frame list named whichever its names' hashes sorted first (random from run to run)."""
    rows = [*range(20), *range(19, -1, -1)]  # the first repeat: line 21, of line 20
    path = tmp_path / "data.csv"
    if kind == "frames":
        path.write_text("".join(f"{i},f{n}.png\n" for i, n in enumerate(rows)))
        pattern = r"data\.csv:21: frame file 'f19\.png' is listed again \(line 20\)"
        read = lambda: read_frame_list(path)  # noqa: E731
    else:
        path.write_text("".join(f"{n},{n + 1}\n" for n in rows))
        pattern = r"data\.csv:21: the pair 19,20 again \(line 20\); each pair once"
        read = lambda: read_pair_file(path, num_frames=21)  # noqa: E731
    with pytest.raises(ValueError, match=pattern):
        read()


def test_a_repeat_among_names_whose_hashes_collide_is_found():
    """Names are compared where their hashes are equal: with x and y colliding, x, y, x was no
    repeat (only neighbours in hash order were compared)."""
    from rotlearn.data.mav import _first_repeat

    names = ["x", "y", "w", "x", "y"]
    collide = np.array([7, 7, 1, 7, 7], dtype=np.int64)  # x and y share a hash
    assert _first_repeat(collide, lambda i, j: names[i] == names[j]) == (0, 3)
    assert _first_repeat(collide[:3], lambda i, j: names[i] == names[j]) is None
    assert _first_repeat(np.array([5, 3, 5, 5, 3])) == (0, 2)  # exact keys: the first's row


def test_a_frame_cache_its_disk_cannot_hold_is_refused_before_any_frame_is_read(
    demo_data, tmp_path, monkeypatch
):
    """A dataset of many small frame files can ask for a cache thousands of times its size: the
    disk's free space is checked before the first frame is decoded."""
    import types

    import cv2

    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    frames = len(list((root / "flea3" / "data").glob("*.png")))
    free = 2**28 + frames * 8 * 8 - 1  # one byte short of the (frames, 1, 8, 8) cache + 256 MiB
    monkeypatch.setattr(shutil, "disk_usage", lambda path: types.SimpleNamespace(free=free))
    monkeypatch.setattr(cv2, "imread", lambda *a, **k: pytest.fail("a frame was decoded"))
    pattern = r"flea3_10_8\.npy: the frame cache takes 0\.00 GB, but its disk has 0\.27 GB free"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)
    monkeypatch.undo()
    mav(root, cache)  # with room, the same dataset caches


def test_a_killed_cache_builds_leftover_is_removed_before_the_space_is_checked(
    demo_data, tmp_path, monkeypatch
):
    """A cache build killed mid-way (the out-of-memory killer) left its temporary file, and the
    next build counted its gigabytes against the disk's free space: on a nearly full disk the
    build was refused and the leftover never removed. Here the disk has room only once it is
    gone."""
    import types

    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    mav(root, cache)
    [built] = cache.rglob("*.npy")
    size = built.stat().st_size
    built.with_suffix(".json").unlink()  # its manifest: the cache is built again
    leftover = built.with_name(f".{built.name}.0123abcd.tmp.npy")
    leftover.write_bytes(b"\0" * 4096)
    room = 2**28 + size  # what the check asks for
    free = lambda path: types.SimpleNamespace(free=room - (1 if leftover.exists() else 0))  # noqa: E731
    monkeypatch.setattr(shutil, "disk_usage", free)
    mav(root, cache)
    assert not leftover.exists() and built.with_suffix(".json").exists()


def test_mav_symlinked_frame_outside_the_root_names_the_line(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    name = (root / "flea3" / "data.csv").read_text().splitlines()[4].split(",")[1]
    frame, outside = root / "flea3" / "data" / name, tmp_path / "secret.png"
    shutil.move(frame, outside)
    frame.symlink_to(outside)
    pattern = rf"flea3/data\.csv:5: .*{name} resolves to .*outside"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_frame_folder_symlinked_outside_the_root_is_refused(demo_data, tmp_path):
    """The frames are checked against their folder, resolved once: a folder that leads out of
    data.root is refused, however plain each frame inside it is."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    folder, outside = root / "flea3" / "data", tmp_path / "elsewhere"
    shutil.move(folder, outside)
    folder.symlink_to(outside)
    pattern = r"data\.root: .*flea3/data resolves to .*elsewhere, outside"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_a_mav_line_over_the_cap_is_refused_before_it_is_split(demo_data, tmp_path, monkeypatch):
    """A line of commas was split into a field each before anything was checked (the text cap
    allows 256 MB on one line)."""
    import rotlearn.io as io

    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    listing = root / "flea3" / "data.csv"
    lines = listing.read_text().splitlines()
    monkeypatch.setattr(io, "MAX_LINE_CHARS", max(map(len, lines)))
    listing.write_text("\n".join([*lines[:3], "," * (io.MAX_LINE_CHARS + 1), *lines[3:]]) + "\n")
    pattern = rf"flea3/data\.csv:4: a line of {io.MAX_LINE_CHARS + 1} characters, over the"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_pair_index_out_of_range_names_the_line(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    set_line(root / "pairs" / "outdoor.csv", 2, "0,999")
    pattern = r"outdoor\.csv:2: frame 999 does not exist .*40 frames"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_pair_listed_twice_names_both_lines(demo_data, tmp_path):
    """A pair listed again was read, cached and counted again: 2 million copies of one pair
    (8 MB of text) took 1.2 GB and 11 s, and would have trained it 2 million times."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    pairs = root / "pairs" / "outdoor.csv"
    first = pairs.read_text().splitlines()[0]
    set_line(pairs, 3, first)
    pattern = rf"outdoor\.csv:3: the pair {first} again \(line 1\); each pair once$"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_mav_pairs_past_the_cap_are_refused_as_they_are_read(demo_data, tmp_path, monkeypatch):
    import rotlearn.data.mav as mav_module

    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    monkeypatch.setattr(mav_module, "MAX_PAIRS", 5)  # the same rule at a test's scale
    pattern = r"outdoor\.csv:6: more than 5 pairs; a scene lists fewer$"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


def test_a_missing_mav_frame_is_named_with_its_line_at_once(demo_data, tmp_path):
    """A frame list of a million rows naming no file took 14 s and 500 MB before the first
    missing frame was reported (every frame was stat'ed into lists first)."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    listing = root / "flea3" / "data.csv"
    lines = listing.read_text().splitlines()
    stamp = int(lines[-1].split(",")[0])
    rows = "".join(f"{stamp + 50_000_000 * (i + 1)},{i:x}.png\n" for i in range(1000))
    listing.write_text("\n".join(lines) + "\n" + rows)
    pattern = rf"flea3/data\.csv:{len(lines) + 1}: no frame file .*/flea3/data/0\.png$"
    refuses(lambda: mav(root, cache), tmp_path, cache, FileNotFoundError, pattern)


def test_mav_non_integer_pair_index_names_the_line(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    set_line(root / "pairs" / "outdoor.csv", 2, "0,1.0")
    pattern = r"outdoor\.csv:2: not an integer: '1\.0'"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


BEYOND_INT64 = "99999999999999999999"  # > 2^63 - 1: numpy's int64 used to raise OverflowError


@pytest.mark.parametrize(
    ("file", "lineno", "make_line", "pattern"),
    [
        ("flea3/data.csv", 3, lambda line: f"{BEYOND_INT64},{line.split(',')[1]}",
         rf"time stamp {BEYOND_INT64} is out of range"),
        ("pose/data.csv", 6, lambda line: BEYOND_INT64 + line[line.index(","):],
         rf"time stamp {BEYOND_INT64} is out of range"),
        ("pose/data.csv", 2, lambda line: f"{-(2**63)}" + line[line.index(","):],
         rf"time stamp {-(2**63)} is out of range \(integer ns since the epoch"),
        ("flea3/data.csv", 3, lambda line: f"-1,{line.split(',')[1]}",
         r"time stamp -1 is out of range"),
        ("pose/data.csv", 4, lambda line: "9" * 5000 + line[line.index(","):],
         r"not an integer: 5000 digits"),  # past Python's int(str) limit (4300 digits)
        ("pairs/outdoor.csv", 2, lambda line: f"0,{BEYOND_INT64}",
         rf"frame {BEYOND_INT64} does not exist \(flea3/data\.csv lists 40 frames"),
        ("pairs/outdoor.csv", 2, lambda line: f"-{BEYOND_INT64},1",
         rf"frame -{BEYOND_INT64} does not exist"),
    ],
    ids=["frame-beyond-int64", "pose-beyond-int64", "pose-int64-min", "negative-frame",
         "5000-digits", "pair-beyond-int64", "pair-below-int64"],
)  # fmt: skip
def test_mav_integers_out_of_range_name_the_file_and_line(
    demo_data, tmp_path, file, lineno, make_line, pattern
):
    """Time stamps are ns since the epoch, 0 to 2^63 - 1; pair indices name frames."""
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    path = root / file
    set_line(path, lineno, make_line(path.read_text().splitlines()[lineno - 1]))
    error = refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)
    assert str(error).startswith(f"{path}:{lineno}: ")


def test_mav_a_pose_292_years_away_is_not_within_the_tolerance():
    """|0 - (-2^63)| wrapped around in int64 to -2^63 ns, "within 30 ms": a planted pose won."""
    from rotlearn.data import match_poses

    lowest, highest = -(2**63), 2**63 - 1
    poses = np.array([lowest, 900_000_000], dtype=np.int64)
    nearest, gaps = match_poses(np.array([0, lowest], dtype=np.int64), poses)
    assert nearest.tolist() == [1, 0] and gaps.tolist() == [900_000_000, 0]
    nearest, gaps = match_poses(np.array([highest], dtype=np.int64), poses[:1])
    assert nearest.tolist() == [0] and gaps.tolist() == [highest]  # 2^64 - 1 ns, saturated
    assert gaps.dtype == np.int64


@pytest.mark.parametrize("key", ["train_scenes", "test_scenes"])
def test_mav_scene_names_cannot_leave_the_root(demo_data, tmp_path, key):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    shutil.copy(root / "pairs" / "outdoor.csv", root / "x.csv")  # what pairs/../x.csv would read
    make = lambda: mav(root, cache, **{key: ["../x"]})  # noqa: E731
    error = refuses(make, tmp_path, cache, ConfigError, r"'\.\./x' is not a plain")
    assert error.key == key


def test_mav_symlinked_scene_file_outside_the_root_is_refused(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mav", tmp_path), tmp_path / "cache"
    outside = tmp_path / "outdoor.csv"
    shutil.move(root / "pairs" / "outdoor.csv", outside)
    (root / "pairs" / "outdoor.csv").symlink_to(outside)
    pattern = r"data\.train_scenes entry 'outdoor': .*resolves to .*outside"
    refuses(lambda: mav(root, cache), tmp_path, cache, ValueError, pattern)


# ---- ShapeNet -----------------------------------------------------------------------------------


def shapenet(root: Path, cache: Path, **kw) -> ShapeNetDataModule:
    args = {"num_train": 6, "num_test": 3, "num_points": 16, "rotations_per_cloud": 2, **kw}
    dm = ShapeNetDataModule(str(root), cache_dir=str(cache), **args)
    dm.setup("fit")
    return dm


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("nan 0 0", "not finite"),
        ("0 inf 0", "not finite"),
        ("0 0 1e999", "not finite"),
        ("1e39 0 0", "not finite"),  # beyond float32, the dtype of the clouds
        ("0 zero 0", "not a number"),
        ("0 0", "expected 3 numbers"),
    ],
)
def test_pts_rows_are_checked(demo_data, tmp_path, text, pattern):
    root, cache = copy_demo(demo_data, "pts", tmp_path), tmp_path / "cache"
    path = sorted((root / "test").glob("*.pts"))[1]
    set_line(path, 3, text)
    message = str(refuses(lambda: shapenet(root, cache), tmp_path, cache, ValueError, pattern))
    assert f"{path}:3:" in message


def test_a_non_utf8_pts_file_names_the_line(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "pts", tmp_path), tmp_path / "cache"
    path = sorted((root / "train").glob("*.pts"))[0]
    path.write_bytes(b"0 0 1\n1 2 3\n\xff\xfe 0 0\n")
    pattern = rf"{path.name}:3: not UTF-8 text"
    refuses(lambda: shapenet(root, cache), tmp_path, cache, ValueError, pattern)


def test_a_cloud_of_more_points_than_a_draw_may_hold_is_refused(demo_data, tmp_path):
    """Each draw holds a cloud's points 6 times a sample: 100k short lines once made a batch of
    100 take 240 MB. The cap counts the points used (data.point_fraction of the file's)."""
    from rotlearn.data.shapenet import MAX_CLOUD_POINTS

    root, cache = copy_demo(demo_data, "pts", tmp_path), tmp_path / "cache"
    path = sorted((root / "train").glob("*.pts"))[0]
    path.write_text("0 0 1\n" * (2 * MAX_CLOUD_POINTS + 2))  # half used: one point over
    pattern = rf"{path.name}: {MAX_CLOUD_POINTS + 1} points used \(data\.point_fraction=0\.5 of"
    refuses(lambda: shapenet(root, cache), tmp_path, cache, ValueError, pattern)
    path.write_text("0 0 1\n" * 2 * MAX_CLOUD_POINTS)  # at the cap: read
    shapenet(root, cache)


CUBE_VERTICES = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"


@pytest.mark.parametrize(
    ("content", "pattern"),
    [
        (b"\xff\xfe\x00\x81garbage\x80\n", r":1: not UTF-8 text"),
        (b"hello world\nfoo bar\n", r": no rows of numbers \(v x y z\)"),
        (CUBE_VERTICES.encode(), ": the mesh has no faces"),
        ((CUBE_VERTICES + "f 1 2 9\n").encode(), r":5: a corner names vertex 9, but the file has"),
        (b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", r": the mesh's total area is 0\.0"),
        (b"v 0 0 0\nv 1 0 0\n# x\nv nan 1 0\nf 1 2 3\n", r":4: not finite \(v x y z\)"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1e999 0\nf 1 2 3\n", r":3: not finite \(v x y z\)"),
        # finite in float64, sampled into float32 clouds of inf points
        (b"v 0 0 0\nv 1 0 0\nv 0 1e39 0\nf 1 2 3\n", r":3: not finite \(v x y z\): \[0\.0, inf"),
        # finite in float32, overflowed once rotated (clouds of inf in the cache and training)
        (b"v 0 0 0\nv 1 0 0\nv 0 3e38 0\nf 1 2 3\n", r":3: not finite .*beyond \+-1e\+06"),
        # trimesh joined the continued line the vertex check read as two: a vertex of 1e39 passed
        (b"v 0 0 0\nv 1 0 0\nv\\\n 0 1e39 0\nf 1 2 3\n", r":3: a line continued with"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 2 3\n", r":4: corner '0' names no vertex"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", r":4: corner '-4' names no vertex"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1.5 2 3\n", r":4: not an integer"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n", r":4: corner '9+' names no"),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r":4: a face of 2 corners"),
        # positive area in float64, none once float32 (the clouds' dtype): all-zero clouds
        (b"v 0 0 0\nv 1e-60 0 0\nv 0 1e-60 0\nf 1 2 3\n", r": the mesh's total area is 0\.0"),
    ],
    ids=[
        "binary",
        "text",
        "no-faces",
        "bad-index",
        "zero-area",
        "nan-vertex",
        "inf-vertex",
        "float32-overflow-vertex",
        "huge-finite-vertex",
        "continued-line",
        "zero-index",
        "relative-index-before-the-first",
        "fractional-index",
        "index-beyond-int64",
        "two-corner-face",
        "float32-vanishing-area",
    ],
)
def test_bad_meshes_are_refused_naming_the_file(demo_data, tmp_path, content, pattern):
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    path = sorted(root.glob("02691156/*/models/model_normalized.obj"))[4]
    path.write_bytes(content)
    make = lambda: shapenet(root, cache, format="mesh")  # noqa: E731
    message = str(refuses(make, tmp_path, cache, ValueError, pattern))
    assert message.startswith(str(path)) and "module" not in message
    assert not cache.exists() or not list(cache.iterdir())


@pytest.mark.parametrize(
    "name", ["evil\n\x1b[2Jrotlearn-train: all good", "evil\udcff"], ids=["line-break", "not-utf8"]
)
def test_a_model_folder_whose_name_would_garble_a_message_is_refused(demo_data, tmp_path, name):
    """A name with a line break cut the one-line error before its cause (the rest reached the
    terminal raw, escape codes included); one not UTF-8 crashed the log file's handler."""
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    model = sorted(root.glob("02691156/*/models"))[0].parent
    model.rename(model.with_name(name))
    make = lambda: shapenet(root, cache, format="mesh")  # noqa: E731
    error = refuses(make, tmp_path, cache, ValueError, "a line break, a control character")
    assert str(error).count("\n") == 0 and "\x1b" not in str(error) and repr(name) in str(error)


def test_mtllib_outside_the_root_is_never_read(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    path = sorted(root.glob("02691156/*/models/model_normalized.obj"))[0]
    path.write_text("mtllib ../../../../../../no/such/dir/evil.mtl\n" + path.read_text())
    dm = shapenet(root, cache, format="mesh")  # loads: the material file is never opened
    assert np.isfinite(torch.stack(dm.clouds[0]).numpy()).all()


@pytest.mark.parametrize("synset", ["../..", "..", "a/b"])
def test_the_synset_cannot_leave_the_root(demo_data, tmp_path, synset):
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    make = lambda: shapenet(root, cache, format="mesh", synset=synset)  # noqa: E731
    assert refuses(make, tmp_path, cache, ConfigError, "not a plain").key == "synset"


def test_a_symlinked_model_outside_the_root_is_refused(demo_data, tmp_path):
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    model = sorted((root / "02691156").iterdir())[0]
    outside = tmp_path / "elsewhere"
    shutil.move(model, outside)
    model.symlink_to(outside, target_is_directory=True)
    pattern = r"data\.synset: .*model_normalized\.obj resolves to .*elsewhere.*outside"
    refuses(lambda: shapenet(root, cache, format="mesh"), tmp_path, cache, ValueError, pattern)


# ---- the shared helpers -------------------------------------------------------------------------


def test_plain_name_and_resolve_inside(tmp_path):
    assert plain_name("00", "f:1") == "00" and plain_name("a..b", "f:1") == "a..b"
    assert plain_name("évian é", "f:1") == "évian é"  # printable, not ASCII: plain
    assert plain_name("می\u200cخواهم", "f:1")  # a zero-width non-joiner, as Persian writes
    for bad in ("", ".", "..", "../x", "x/..", "/etc", "a\\b", "x\0", "a\nb", "x\x1b[2J",
                "x\udcff", "a\u2028b", "a\x85", "abc\u202egnp.exe", "a\u200bb"):  # fmt: skip
        with pytest.raises(ValueError, match=r"f:1: .* not a plain"):
            plain_name(bad, "f:1")
    with pytest.raises(ConfigError) as err:
        plain_name("../x", key="train_sequences")
    assert err.value.key == "train_sequences"
    (tmp_path / "root").mkdir()
    assert resolve_inside(tmp_path / "root", tmp_path / "root" / "new", "w").name == "new"
    with pytest.raises(ValueError, match=r"^w: .* outside"):
        resolve_inside(tmp_path / "root", tmp_path / "root" / ".." / "x", "w")
    loop = tmp_path / "root" / "000005.png"  # a dataset's frame or cache linked to itself
    loop.symlink_to(loop)  # Python 3.11's resolve: RuntimeError, a traceback in rotlearn-train
    with pytest.raises(ValueError, match=r"^w: .*000005\.png cannot be resolved .*symlink loop"):
        resolve_inside(tmp_path / "root", loop, "w")


def test_number_rows_name_the_first_non_finite_line(tmp_path):
    path = tmp_path / "rows.txt"
    path.write_text("# header\n1 2\n\n3 nan\n-inf 4\n")
    with pytest.raises(ValueError, match=r"rows\.txt:4: not finite .*2 such row\(s\)"):
        read_number_rows(path, 2, "a b")


# ---- NonFiniteError tells the truth -------------------------------------------------------------


def test_initialize_from_refuses_a_non_finite_batch_and_keeps_the_biases():
    net = PointNet(out_dim=4, point_channels=(8, 16), head_channels=(8,))
    before = [p.clone() for p in net.parameters()]
    points = torch.randn(3, 10, 6)
    points[1, 2, 0] = math.nan
    with pytest.raises(NonFiniteError, match="input batch is itself non-finite"):
        net.initialize_from(points)
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))
    net.initialize_from(points.nan_to_num())  # a finite batch centres the biases
    assert not all(torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))
    assert all(bool(p.isfinite().all()) for p in net.parameters())


def test_initialize_from_undoes_an_overflow():
    net = PointNet(out_dim=4, point_channels=(8, 16), head_channels=(8,))
    before = [p.clone() for p in net.parameters()]
    points = torch.full((3, 10, 6), 3e38) * torch.randn(3, 10, 1).sign()
    with pytest.raises(NonFiniteError, match="overflow"):
        net.initialize_from(points)
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))


def test_a_non_finite_output_blames_the_weights_only_when_they_are_not_finite(make_cfg):
    from rotlearn.cli.train import build

    model = build(make_cfg(["data=tiny", "trainer=cpu", "logger=none"]))[0]
    finite = {"input": torch.zeros(2, 5, 6)}
    bad_output = torch.tensor([math.nan])
    with pytest.raises(NonFiniteError, match=r"inputs and the weights are finite: .*overflowed"):
        model._check_finite("loss", bad_output, finite, "train", 0)
    with pytest.raises(NonFiniteError, match="input batch is itself non-finite"):
        model._check_finite("loss", bad_output, {"input": torch.tensor([math.inf])}, "train", 0)
    with torch.no_grad():
        next(model.net.parameters())[0] = math.nan
    with pytest.raises(NonFiniteError, match=r"weights are not \(first: net\."):
        model._check_finite("loss", bad_output, finite, "train", 0)


def test_a_dangling_mesh_link_is_refused_not_left_out_of_the_split(demo_data, tmp_path):
    """A model whose mesh is a dangling symlink was silently left out of the dataset (so every
    later model moved split); it is refused, naming it."""
    root, cache = copy_demo(demo_data, "mesh", tmp_path), tmp_path / "cache"
    path = sorted(root.glob("02691156/*/models/model_normalized.obj"))[2]
    path.unlink()
    path.symlink_to(root / "gone.obj")
    make = lambda: shapenet(root, cache, format="mesh")  # noqa: E731  (every mesh of the demo)
    refuses(make, tmp_path, cache, FileNotFoundError, rf"{path}: mesh \d+: no such file")


def test_a_shipped_cache_symlink_cannot_send_the_default_cache_out_of_the_root(demo_data, tmp_path):
    root = copy_demo(demo_data, "kitti", tmp_path)
    elsewhere = tmp_path / "home"
    elsewhere.mkdir()
    (root / ".rotlearn_cache").symlink_to(elsewhere, target_is_directory=True)
    dm = KittiOdometryDataModule(str(root), train_sequences=["02"], test_sequences=["00"],
                                 image_size=8, num_workers=0)  # fmt: skip
    with pytest.raises(ValueError, match=r"data\.cache_dir \(sequence '02'\): .*outside"):
        dm.setup()
    assert list(elsewhere.iterdir()) == []
