"""MAV indoor/outdoor relative rotations (paper Fig. 8; section VI-D).

Layout (EuRoC-like):
- `<root>/flea3/data.csv`: `#timestamp [ns],filename` header, then one `t_ns,filename` row per
  frame; the images are `<root>/flea3/data/<filename>` (8-bit gray).
- `<root>/pose/data.csv`: `#...` header, then `timestamp, ..., qw, qx, qy, qz` rows: the
  camera-to-world orientation as a Hamilton quaternion, scalar FIRST in this file (rotlearn's own
  quaternions are x, y, z, w), at any rate.
- `<root>/pairs/<scene>.csv`: headerless `id1,id2` rows, 0-based indices into the frame rows of
  `flea3/data.csv`; scenes `outdoor`, `indoor`, `transition`.

Time stamps are integer nanoseconds since the epoch, as EuRoC's: 0 to 2^63 - 1 (int64), so that
no difference of two wraps around. Each frame takes the pose nearest in time, which must lie within
`pose_tolerance_ms` (30 ms).
A pair's target is C_21 = R_2^T R_1, as for KITTI (`rotlearn.geometry.relative_rotation`). Frames
go through Resize(256) -> CenterCrop(224) (cached once as uint8) and Normalize(0.45, 0.25); the
two gray frames of a pair are stacked as 2 channels. A seeded random `test_fraction` of each
scene's pairs is its test set; the validation pairs are the tail of each training scene without
any frame of a test pair (`rotlearn.data.splits.hold_out_tail`, `val_fraction`).
"""

from __future__ import annotations

import array as pyarray
import os
import stat
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, NamedTuple

import numpy as np
import torch

from rotlearn.data.draws import draw_seed
from rotlearn.data.images import frame_cache, resize_center_crop
from rotlearn.data.pairs import ImagePairDataModule, PairIndex
from rotlearn.errors import ConfigError
from rotlearn.geometry import quat_normalize, quat_to_rotmat, relative_rotation
from rotlearn.io import (
    cache_file,
    numbered_lines,
    plain_name,
    plain_names,
    read_text_file,
    require_finite,
    resolve_inside,
    strict_int,
)
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Gt, Lt, MinLen

__all__ = ["MAVDataModule", "match_poses", "read_frame_list", "read_pair_file", "read_pose_file"]

INT64_MAX = int(np.iinfo(np.int64).max)  # 2^63 - 1: the largest time stamp or frame index read
# A scene's pairs file lists at most this many pairs: each pair costs about 600 bytes once its
# targets and erasing boxes are built, so the 256 MiB text cap (67 M rows) would ask for 40 GB.
MAX_PAIRS = 2**22


def _shown(text: str) -> str:
    """`text` for a message, cut to 24 characters (an integer field can be thousands of digits)."""
    return text if len(text) <= 24 else f"{text[:20]}... ({len(text)} characters)"


def _time_stamp(text: str, where: str) -> int:
    """`text` as a time stamp: integer nanoseconds since the epoch, 0 to 2^63 - 1.

    Raises:
        ValueError: "<where>: ..." for a word that is not an integer (`strict_int`) or is out of
            that range: a negative stamp, or one beyond int64 (whose differences would wrap).
    """
    stamp = strict_int(text, where)
    if not 0 <= stamp <= INT64_MAX:
        raise ValueError(
            f"{where}: time stamp {_shown(text)} is out of range (integer ns since the epoch, "
            "0 to 2^63 - 1)"
        )
    return stamp


def _rows(path: Path, columns: int | None = None, min_columns: int = 1):
    """(line number, fields) of a CSV file's rows, skipping blank lines and `#` comments; the
    field count checked (`rotlearn.io.read_text_file` raises for a missing or non-text file). The
    lines are split a block at a time (`rotlearn.io.numbered_lines`): a pose file at 200 Hz is
    never held as a list of all its lines, and a line longer than `MAX_LINE_CHARS` is refused."""
    for lineno, line in numbered_lines(read_text_file(path), str(path)):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        if (columns is not None and len(fields) != columns) or len(fields) < min_columns:
            want = f"{columns}" if columns is not None else f"at least {min_columns}"
            raise ValueError(
                f"{path}:{lineno}: expected {want} comma-separated fields, got {len(fields)}"
            )
        yield lineno, fields


def _first_repeat(keys: np.ndarray, same: Callable[[int, int], bool] | None = None):
    """The first row, in file order, whose key an earlier row has, as (the first row with that
    key, it), or None. `keys`: (N,), any sortable dtype (a structured one for several columns);
    `same(i, j)` tells rows i < j apart whose keys are equal hashes of their values (names whose
    hashes collide: x, y, x is a repeat of x)."""
    order = np.argsort(keys, kind="stable")  # equal keys sit together, in file order
    ordered = keys[order]
    at = np.flatnonzero(ordered[1:] == ordered[:-1])
    for k in at[np.argsort(order[at + 1], kind="stable")]:  # the later rows in file order
        later, earlier = int(order[k + 1]), None
        for m in range(k, -1, -1):  # the rows before it with its key, back to the first
            if ordered[m] != ordered[k + 1]:
                break
            if same is None or same(int(order[m]), later):
                earlier = int(order[m])
                if same is None:  # exact keys: the row before is the first (a first repeat)
                    break
        if earlier is not None:
            return earlier, later
    return None


def read_frame_list(path: str | Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Frames of `flea3/data.csv`: timestamps (N,) int64 ns, file names, and line numbers (N,).

    Raises:
        ValueError: naming the file and line of a row that is not "integer,filename", whose
            time stamp is negative or beyond int64, whose file name is not a plain name (a
            path separator, "." or "..": it could leave `flea3/data`), or names a file an
            earlier row names (each would be decoded and cached again).
    """
    path = Path(path)
    stamps, names, lines = pyarray.array("q"), [], pyarray.array("q")  # 8 bytes a number
    for lineno, (stamp, name) in _rows(path, columns=2):
        stamps.append(_time_stamp(stamp, f"{path}:{lineno}"))
        names.append(plain_name(name, f"{path}:{lineno}"))
        lines.append(lineno)
    if not stamps:
        raise ValueError(f"{path}: no frames")
    lines = np.frombuffer(lines, np.int64)
    hashes = np.fromiter(map(hash, names), np.int64, len(names))  # 8 bytes a row, not a set
    if repeat := _first_repeat(hashes, lambda i, j: names[i] == names[j]):
        first, again = repeat
        raise ValueError(
            f"{path}:{lines[again]}: frame file {names[again]!r} is listed again (line "
            f"{lines[first]}); each row names its own frame"
        )
    return np.frombuffer(stamps, np.int64), names, lines


def read_pose_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Poses of `pose/data.csv`: timestamps (M,) int64 ns (sorted) and unit quaternions (M, 4),
    converted to rotlearn's (x, y, z, w) from the file's trailing qw, qx, qy, qz columns.

    Raises:
        ValueError: naming the file and line of a row whose time stamp is not an integer from 0
            to 2^63 - 1, whose quaternion is not four finite numbers or is not unit (to 10 %),
            or whose time stamp repeats another row's with another orientation (a repeat of the
            same pose is kept once).
    """
    path = Path(path)
    stamps, quats, lines = pyarray.array("q"), pyarray.array("d"), pyarray.array("q")
    for lineno, fields in _rows(path, min_columns=5):  # 8 bytes a number, not a Python object
        stamps.append(_time_stamp(fields[0], f"{path}:{lineno}"))
        try:
            quats.extend([float(f) for f in fields[-4:]])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: not a number among {fields[-4:]}") from None
        lines.append(lineno)
    if not stamps:
        raise ValueError(f"{path}: no poses")
    lines = np.frombuffer(lines, np.int64)
    wxyz = np.frombuffer(quats, np.float64).reshape(-1, 4)
    wxyz = require_finite(wxyz, lines, str(path), "qw qx qy qz")
    norm = np.sqrt(np.einsum("ij,ij->i", wxyz, wxyz))  # no (M, 4) temporary
    bad = np.flatnonzero(~((norm > 0.9) & (norm < 1.1)))
    if len(bad):
        raise ValueError(
            f"{path}:{lines[bad[0]]}: the quaternion (qw, qx, qy, qz) is not unit "
            f"(norm {norm[bad[0]]:.4g}); {len(bad)} such row(s) in all"
        )
    stamps = np.frombuffer(stamps, np.int64)
    order = np.argsort(stamps, kind="stable")
    quats = wxyz[order[:, None], [1, 2, 3, 0]]  # sorted, (x, y, z, w): one copy
    stamps, lines, norm = stamps[order], lines[order], norm[order]
    del wxyz, order  # the rows as read: freed before the repeats are looked at
    same = np.flatnonzero(stamps[1:] == stamps[:-1])  # row i + 1 repeats row i's time stamp
    dot = np.abs(np.einsum("ij,ij->i", quats[same], quats[same + 1]))  # q and -q agree
    agree = dot >= (1.0 - 1e-9) * norm[same] * norm[same + 1]
    if not agree.all():
        i = same[~agree][0]
        a, b = sorted((int(lines[i]), int(lines[i + 1])))
        raise ValueError(
            f"{path}:{b}: time stamp {stamps[i]} repeats line {a} with another orientation; "
            f"{int((~agree).sum())} such conflict(s) in all (which pose is right is unknown)"
        )
    if not len(same):
        return stamps, quats
    keep = np.ones(len(stamps), dtype=bool)
    keep[same + 1] = False  # the same pose twice: one is kept
    return stamps[keep], quats[keep]


def match_poses(frame_stamps: np.ndarray, pose_stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each frame, the index of the pose nearest in time and the gap in ns.

    Args:
        frame_stamps: (N,) int64 ns.
        pose_stamps: (M,) int64 ns, sorted.

    Returns:
        (N,) int64 pose indices and (N,) int64 absolute gaps |t_pose - t_frame|, exact (never
        wrapped around, as a plain int64 difference of stamps 2^63 apart is), those beyond
        2^63 - 1 ns (292 years) saturated to 2^63 - 1.
    """
    frame_stamps = np.asarray(frame_stamps, dtype=np.int64)
    pose_stamps = np.asarray(pose_stamps, dtype=np.int64)
    right = np.searchsorted(pose_stamps, frame_stamps).clip(1, len(pose_stamps) - 1)
    left = right - 1
    if len(pose_stamps) == 1:
        left = right = np.zeros_like(frame_stamps)
    gap_left = _abs_difference(frame_stamps, pose_stamps[left])
    gap_right = _abs_difference(pose_stamps[right], frame_stamps)
    nearest = np.where(gap_right < gap_left, right, left)
    gaps = np.minimum(np.minimum(gap_left, gap_right), np.uint64(INT64_MAX))
    return nearest, gaps.astype(np.int64)


def _abs_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| of int64 arrays as uint64, exact: the larger minus the smaller, each taken modulo
    2^64, is the true difference (0 to 2^64 - 1), which an int64 subtraction can wrap."""
    return np.maximum(a, b).astype(np.uint64) - np.minimum(a, b).astype(np.uint64)


def read_pair_file(
    path: str | Path, num_frames: int, frame_list: str = "flea3/data.csv"
) -> np.ndarray:
    """Pairs of a headerless `id1,id2` file as (P, 2) int64.

    Raises:
        ValueError: naming the file and line of a pair that refers to a frame that does not exist
            (also an index beyond int64: refused as it is read), of a pair listed twice (it
            would be trained on or tested twice), or past `MAX_PAIRS` pairs.
    """
    path = Path(path)

    def missing(lineno: int, frame: str) -> str:
        return (f"{path}:{lineno}: frame {frame} does not exist ({frame_list} lists {num_frames} "
                f"frames, 0 to {num_frames - 1})")  # fmt: skip

    pairs, lines = pyarray.array("q"), pyarray.array("q")  # 8 bytes a number
    for lineno, fields in _rows(path, columns=2):
        if len(lines) == MAX_PAIRS:
            raise ValueError(f"{path}:{lineno}: more than {MAX_PAIRS} pairs; a scene lists fewer")
        pair = [strict_int(f, f"{path}:{lineno}") for f in fields]
        for text, i in zip(fields, pair, strict=True):
            if not -INT64_MAX - 1 <= i <= INT64_MAX:
                raise ValueError(missing(lineno, _shown(text)))
        pairs.extend(pair)
        lines.append(lineno)
    if not pairs:
        raise ValueError(f"{path}: no pairs")
    pairs = np.frombuffer(pairs, np.int64).reshape(-1, 2)
    bad = np.flatnonzero(((pairs < 0) | (pairs >= num_frames)).any(axis=1))
    if len(bad):
        row = pairs[bad[0]]
        i = int(row[(row < 0) | (row >= num_frames)][0])
        raise ValueError(f"{missing(lines[bad[0]], str(i))}; {len(bad)} such pair(s) in all")
    if repeat := _first_repeat(pairs.view([("a", np.int64), ("b", np.int64)]).ravel()):
        before, again = repeat
        a, b = pairs[again].tolist()
        raise ValueError(f"{path}:{lines[again]}: the pair {a},{b} again (line {lines[before]}); "
                         "each pair once")  # fmt: skip
    return pairs


class _Frames(NamedTuple):
    R: np.ndarray  # (N, 3, 3) camera-to-world rotation of each frame's nearest pose
    gaps: np.ndarray  # (N,) ns between each frame and that pose
    stamps: np.ndarray  # (N,) frame time stamps, ns
    lines: np.ndarray  # (N,) line of each frame in flea3/data.csv
    cache: Path  # the frame cache (.npy)


@config_target
class MAVDataModule(ImagePairDataModule):
    """MAV frame pairs with their relative rotations (module docstring).

    Args:
        root: dataset root holding `flea3/`, `pose/` and `pairs/`.
        train_scenes: scenes whose training part is trained on (paper: outdoor).
        test_scenes: scenes whose test part is tested on (paper: outdoor; + indoor; + transition).
        test_fraction: the random fraction of each scene's pairs held out for testing (0.1).
        pose_tolerance_ms: the largest frame-to-pose time gap accepted (30 ms).
        resize, image_size: Resize(resize) -> CenterCrop(image_size) (paper: 256, 224).
        pair_channels: channels of a stacked pair; must be 2 (two gray frames).
        cache_dir: frame cache (default `<root>/.rotlearn_cache`).
        mean, std: Normalize(0.45, 0.25) after scaling pixels to [0, 1].
        **kwargs: batch sizes, workers, corruption, validation pairs and seed
            (`ImagePairDataModule`).
    """

    # What data.root holds, checked when a config is validated (rotlearn.config).
    layout = ("flea3/data.csv", "pose/data.csv", "pairs/{train_scenes}.csv",
              "pairs/{test_scenes}.csv")  # fmt: skip
    # What one input is (`ImagePairDataModule.input_keys`), with the scale frames are resized to.
    input_keys = ("resize", "image_size", "pair_channels", "mean", "std")

    def __init__(
        self,
        root: str,
        train_scenes: Annotated[Sequence[str], MinLen(1)] = ("outdoor",),
        test_scenes: Annotated[Sequence[str], MinLen(1)] = ("outdoor",),
        test_fraction: Annotated[float, Gt(0), Lt(1)] = 0.1,
        pose_tolerance_ms: Annotated[float, Gt(0)] = 30.0,
        resize: Annotated[int, Gt(0)] = 256,
        image_size: Annotated[int, Gt(0)] = 224,
        pair_channels: Literal[2] = 2,  # two gray frames
        cache_dir: str | None = None,
        mean: float = 0.45,
        std: Annotated[float, Gt(0)] = 0.25,
        **kwargs,
    ) -> None:
        super().__init__(mean=mean, std=std, **kwargs)
        if image_size > resize:
            raise ConfigError("image_size", f"the crop {image_size} exceeds resize={resize}")
        self.root = Path(root)
        self.train_scenes = plain_names(train_scenes, "train_scenes")
        self.test_scenes = plain_names(test_scenes, "test_scenes")
        self.test_fraction, self.pose_tolerance_ms = float(test_fraction), float(pose_tolerance_ms)
        self.resize, self.image_size = int(resize), int(image_size)
        self.refuse_oversized_batches(pair_channels, self.image_size)
        self.cache_dir = Path(cache_dir) if cache_dir else self.root / ".rotlearn_cache"
        self._frames: _Frames | None = None
        self._scenes: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    gray = True

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        """(H, W) gray frame -> (S, S): Resize(resize) -> CenterCrop(image_size)."""
        return resize_center_crop(image, self.resize, self.image_size)

    def _file(self, *parts: str, where: str = "data.root") -> Path:
        """`root / parts`, checked to resolve inside data.root (symlinks followed)."""
        path = self.root.joinpath(*parts)
        resolve_inside(self.root, path, where)
        return path

    def _frame_files(self, names: list[str], lines: np.ndarray) -> list[Path]:
        """`flea3/data/<name>` of each listed frame (a plain name: `read_frame_list`), each
        there and inside data.root: the folder is resolved once, and a frame only where it is a
        symlink (one `lstat` a frame, not a resolve: 300k frames took 30 s; an error names the
        line of `flea3/data.csv` that lists the frame)."""
        listing, folder = self.root / "flea3" / "data.csv", self._file("flea3", "data")
        files = [folder / name for name in names]
        for path, line in zip(files, lines, strict=True):
            try:  # the first missing frame is named at once (a million missing ones took 14 s)
                mode = os.lstat(path).st_mode
            except FileNotFoundError:
                raise FileNotFoundError(f"{listing}:{line}: no frame file {path}") from None
            if stat.S_ISLNK(mode):
                resolve_inside(self.root, path, f"{listing}:{line}")
        return files

    def _frame_rotations(self) -> _Frames:
        """Every frame's rotation, pose gap, time stamp and `data.csv` line, and the cache; read
        and cached once."""
        if self._frames is None:
            stamps, names, lines = read_frame_list(self._file("flea3", "data.csv"))
            pose_stamps, quats = read_pose_file(self._file("pose", "data.csv"))
            nearest, gaps = match_poses(stamps, pose_stamps)
            q = quat_normalize(torch.from_numpy(quats[nearest]))
            stem = f"flea3_{self.resize}_{self.image_size}"
            cache = cache_file(self.cache_dir, stem, "data.cache_dir", self.root)
            frame_cache(
                self._frame_files(names, lines),
                cache,
                self.preprocess,
                {"resize": self.resize, "center_crop": self.image_size},
                self.image_size,
                gray=True,
                desc="caching MAV frames",
            )
            R = quat_to_rotmat(q).numpy()
            self._frames = _Frames(R, gaps, stamps, lines, cache.with_suffix(".npy"))
        return self._frames

    def _check_gaps(self, pairs: np.ndarray) -> None:
        frames = self._frame_rotations()
        used = np.unique(pairs)
        late = used[frames.gaps[used] > self.pose_tolerance_ms * 1e6]
        if len(late):
            i = int(late[0])
            raise ValueError(
                f"{self.root / 'flea3' / 'data.csv'}:{frames.lines[i]}: frame {i} "
                f"(t = {frames.stamps[i]} ns) has no pose within {self.pose_tolerance_ms:g} ms in "
                f"{self.root / 'pose' / 'data.csv'} (nearest: {frames.gaps[i] / 1e6:.1f} ms; "
                f"data.pose_tolerance_ms); {len(late)} frame(s) in all"
            )

    def _scene(self, scene: str, key: str) -> tuple[np.ndarray, np.ndarray]:
        """A scene's pairs (P, 2), checked, and which are test pairs (P,): read once. `key`,
        the config key listing the scene, is named if its file lies outside data.root."""
        if scene not in self._scenes:
            frames = self._frame_rotations()
            where = f"data.{key} entry {scene!r}"
            pairs = read_pair_file(self._file("pairs", f"{scene}.csv", where=where), len(frames.R))
            self._check_gaps(pairs)
            rng = np.random.default_rng(draw_seed(self.seed, *scene.encode()))
            n_test = max(1, round(self.test_fraction * len(pairs)))
            is_test = np.zeros(len(pairs), dtype=bool)
            is_test[rng.permutation(len(pairs))[:n_test]] = True
            self._scenes[scene] = (pairs, is_test)
        return self._scenes[scene]

    def scene_pairs(self, scene: str, split: str) -> PairIndex:
        """The training or test part of one scene's pairs."""
        frames = self._frame_rotations()
        pairs, is_test = self._scene(scene, "test_scenes" if split == "test" else "train_scenes")
        pairs = pairs[is_test if split == "test" else ~is_test]
        R = torch.from_numpy(frames.R)
        C = relative_rotation(R[pairs[:, 0]], R[pairs[:, 1]])
        return PairIndex(
            caches=[frames.cache],
            source=np.zeros(len(pairs), dtype=np.int64),
            first=pairs[:, 0],
            second=pairs[:, 1],
            R=C.numpy(),
            names=[scene],
        )

    def load(self, split: str) -> PairIndex | None:
        if split == "val":  # the tail of each training scene (`val_fraction`)
            return None
        scenes = self.train_scenes if split == "train" else self.test_scenes
        return PairIndex.concat([self.scene_pairs(scene, split) for scene in scenes])
