"""KITTI odometry relative rotations (paper Fig. 6-7 and Table I; section VI-C).

Layout: `<root>/sequences/<XX>/image_2/<frame>.png` (left colour camera; `image_0` is the left gray
one, read as three equal channels) and `<root>/poses/<XX>.txt`, one line per frame holding the
row-major 3x4 camera-to-world matrix [R | t] (12 numbers). The frames are named as KITTI's are,
by their 6-digit zero-padded index, 000000.png to (N - 1); frame i takes line i + 1 of the poses.

The pair (i, i + delta) has the target C_21 = R_{i+delta}^T R_i, the rotation part of
T_21 = T_w(i+delta)^-1 T_wi: it maps camera-i coordinates to camera-(i+delta) coordinates
(`rotlearn.geometry.relative_rotation`). Frames are resized to S x S (224 in the paper) with
OpenCV, cached once per sequence as uint8 (`rotlearn.data.images.frame_cache`) and stacked as
2 x 3 channels; pixels are scaled to [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
import torch

from rotlearn.data.images import frame_cache, resize_square
from rotlearn.data.pairs import ImagePairDataModule, PairIndex
from rotlearn.errors import ConfigError
from rotlearn.geometry import relative_rotation, special_orthogonalize
from rotlearn.io import cache_file, plain_name, plain_names, read_number_rows, resolve_inside
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Gt, MinLen

__all__ = ["KittiOdometryDataModule", "read_kitti_poses", "sequence_name"]

ORTHONORMAL_TOL = 1e-3  # KITTI's poses are printed with 6-7 significant digits
_POSE_BLOCK = 2**16  # poses checked and projected a block at a time: a few MB of temporaries


def sequence_name(sequence: int | str) -> str:
    """ "00" for 0, "00" or "0"; other names (e.g. "my_drive") unchanged."""
    text = str(sequence)
    return f"{int(text):02d}" if text.isdigit() else text


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """The camera-to-world poses of a KITTI `poses/XX.txt` file.

    Args:
        path: a text file, one pose a line: 12 numbers, the row-major 3x4 matrix [R | t].

    Returns:
        (N, 3, 4) float64; each R is projected onto SO(3) (it is orthonormal to 1e-3 already).

    Raises:
        ValueError: naming the file and line of a line that is not 12 finite numbers or whose R
            is not a rotation.
    """
    path = Path(path)
    poses = read_number_rows(path, 12, "a row-major 3x4 [R|t]").reshape(-1, 3, 4)
    for start in range(0, len(poses), _POSE_BLOCK):  # a block at a time: bounded temporaries
        R = poses[start : start + _POSE_BLOCK, :, :3]
        error = np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max(axis=(1, 2))
        bad = np.flatnonzero((error > ORTHONORMAL_TOL) | (np.linalg.det(R) < 0))
        if len(bad):
            i = int(bad[0])
            raise ValueError(
                f"{path}:{start + i + 1}: the rotation is not orthonormal with det +1 "
                f"(max |R^T R - I| = {error[i]:.2e}, det = {np.linalg.det(R[i]):.4f})"
            )
        R[...] = special_orthogonalize(torch.from_numpy(R)).numpy()
    return poses


def _sequence_names(key: str, sequences: Sequence[int | str]) -> list[str]:
    """`sequence_name` of each entry of the config list `key`, each a plain folder name.

    Raises:
        ConfigError: on `key`, for a name with a path separator, "." or "..", or one listed
            twice ("2" and "02" are one sequence).
    """
    return plain_names([sequence_name(s) for s in sequences], key)


@config_target
class KittiOdometryDataModule(ImagePairDataModule):
    """KITTI odometry frame pairs with their relative rotations (module docstring).

    Args:
        root: dataset root holding `sequences/` and `poses/`.
        train_sequences: sequences to train on (paper: 00, 02, 05-10); those also listed in
            `test_sequences` are left out of training (the paper's leave-one-out).
        test_sequences: sequences to test on (paper: one of 00, 02, 05).
        val_sequences: sequences held out whole for validation (never trained or tested on;
            left out of training like the test sequences): streets unseen in training, as the
            test street is. Their pairs join the held-out tail of every training sequence
            (`val_fraction`). Empty by default.
        camera: "image_2" (left colour, the paper's) or "image_0" (left gray).
        delta: frame step of a pair (i, i + delta).
        deltas: frame steps of the training pairs: (i, i + d) for each d (several pairs per
            frame); None: `delta`. The test pairs keep `delta`.
        image_size: S of the S x S frames (paper: 224).
        pair_channels: channels of a stacked pair; must be 6 (two RGB frames). It is a config
            key so that the net can read it (`${data.pair_channels}`).
        cache_dir: frame caches (default `<root>/.rotlearn_cache`).
        **kwargs: batch sizes, workers, corruption, validation pairs and seed
            (`ImagePairDataModule`).
    """

    # What data.root holds, checked when a config is validated (rotlearn.config): each
    # sequence's frames and poses (a number n names the folder "0n").
    layout = (
        "sequences/{train_sequences:0>2}/{camera}",
        "poses/{train_sequences:0>2}.txt",
        "sequences/{test_sequences:0>2}/{camera}",
        "poses/{test_sequences:0>2}.txt",
        "sequences/{val_sequences:0>2}/{camera}",
        "poses/{val_sequences:0>2}.txt",
    )

    def __init__(
        self,
        root: str,
        train_sequences: Sequence[int | str] = ("00", "02", "05", "06", "07", "08", "09", "10"),
        test_sequences: Annotated[Sequence[int | str], MinLen(1)] = ("00",),
        val_sequences: Sequence[int | str] = (),
        camera: Literal["image_2", "image_0"] = "image_2",
        delta: Annotated[int, Gt(0)] = 1,
        deltas: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] | None = None,
        image_size: Annotated[int, Gt(0)] = 224,
        pair_channels: Literal[6] = 6,  # two RGB frames
        cache_dir: str | None = None,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.root, self.camera = Path(root), camera
        self.test_sequences = _sequence_names("test_sequences", test_sequences)
        self.val_sequences = _sequence_names("val_sequences", val_sequences)
        tested = sorted(set(self.val_sequences) & set(self.test_sequences))
        if tested:
            raise ConfigError(
                "val_sequences", f"{tested} are test sequences: validation never comes from test"
            )
        self.train_sequences = [
            name
            for name in _sequence_names("train_sequences", train_sequences)
            if name not in self.test_sequences and name not in self.val_sequences
        ]
        for key, names in (
            ("train_sequences", self.train_sequences),
            ("test_sequences", self.test_sequences),
        ):
            if not names:
                raise ConfigError(key, "no sequence left (train minus test sequences)")
        self.delta, self.image_size = int(delta), int(image_size)
        self.refuse_oversized_batches(pair_channels, self.image_size)
        if deltas is not None and len(set(deltas)) != len(deltas):
            raise ConfigError("deltas", f"must be distinct, got {list(deltas)!r}")
        self.deltas = [int(d) for d in deltas] if deltas is not None else None
        self.cache_dir = Path(cache_dir) if cache_dir else self.root / ".rotlearn_cache"

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) RGB frame -> (S, S, 3), resized with OpenCV's area filter."""
        return resize_square(image, self.image_size)

    def _inside(self, path: Path, sequence: str) -> Path:
        """`path` (of `sequence`) unchanged, if it resolves inside data.root (symlinks followed)."""
        key = "train_sequences" if sequence in self.train_sequences else "test_sequences"
        key = "val_sequences" if sequence in self.val_sequences else key
        resolve_inside(self.root, path, f"data.{key} entry {sequence!r}")
        return path

    def frames(self, sequence: str) -> list[Path]:
        """The image files of a sequence, in order, each checked to lie inside data.root.

        Raises:
            FileNotFoundError: no such folder, or no .png file in it.
            ValueError: naming the folder and the first file whose name is not a frame index,
                when the N .png files are not exactly 000000.png to (N - 1): a name sorted as
                text (0.png, 1.png, 10.png, 2.png, ...) or a missing frame would pair frames
                with the wrong pose lines.
        """
        folder = self._inside(self.root / "sequences" / sequence / self.camera, sequence)
        if not folder.is_dir():
            raise FileNotFoundError(
                f"sequence {sequence}: no directory {folder} (data.root={self.root}, "
                f"data.camera={self.camera}; see data/README.md)"
            )
        names = {f.name for f in folder.glob("*.png")}
        if not names:
            raise FileNotFoundError(f"sequence {sequence}: no .png frames in {folder}")
        expected = [f"{i:06d}.png" for i in range(len(names))]
        odd = sorted(names.difference(expected))
        if odd:
            plain_name(odd[0], str(folder))  # a name that would garble the message: refused
            missing = next(name for name in expected if name not in names)
            raise ValueError(
                f"sequence {sequence}: {folder / odd[0]} is not named as a frame: the "
                f"{len(names)} .png files of {folder} must be 000000.png to {expected[-1]} "
                f"(KITTI's zero-padded frame indices, frame i for pose line i + 1; "
                f"{missing} is missing); {len(odd)} such file(s) in all"
            )
        return [self._inside(folder / name, sequence) for name in expected]

    def sequence_pairs(self, sequence: str, deltas: Sequence[int] | None = None) -> PairIndex:
        """The pairs (i, i + d) of one sequence for each d of `deltas` (None: `delta`), in that
        order, its frames cached."""
        deltas = [self.delta] if deltas is None else list(deltas)
        files = self.frames(sequence)
        poses_path = self._inside(self.root / "poses" / f"{sequence}.txt", sequence)
        if not poses_path.exists():  # a pipe or a folder: named as such by the bounded read
            raise FileNotFoundError(f"sequence {sequence}: no poses file {poses_path}")
        poses = read_kitti_poses(poses_path)
        if len(poses) != len(files):
            raise ValueError(
                f"{poses_path}: {len(poses)} poses, but {files[0].parent} holds {len(files)} "
                "frames (one pose line per frame expected)"
            )
        if len(files) <= max(deltas):
            raise ValueError(
                f"sequence {sequence}: {len(files)} frames, none with a frame {max(deltas)} later"
            )
        cache = cache_file(
            self.cache_dir,
            f"{sequence}_{self.camera}_{self.image_size}",
            f"data.cache_dir (sequence {sequence!r})",
            self.root,
        )
        frame_cache(
            files,
            cache,
            self.preprocess,
            {"resize_square": self.image_size},
            self.image_size,
            desc=f"caching KITTI {sequence}/{self.camera}",
        )
        first = np.concatenate([np.arange(len(files) - d) for d in deltas])
        second = first + np.repeat(deltas, [len(files) - d for d in deltas])
        R = torch.from_numpy(poses[:, :, :3])
        C = relative_rotation(R[first], R[second])
        return PairIndex(
            caches=[cache.with_suffix(".npy")],
            source=np.zeros(len(first), dtype=np.int64),
            first=first,
            second=second,
            R=C.numpy(),
            names=[sequence],
        )

    def load(self, split: str) -> PairIndex | None:
        if split == "train":
            return PairIndex.concat(
                [self.sequence_pairs(n, self.deltas) for n in self.train_sequences]
            )
        if split == "val":
            names = self.val_sequences
            return PairIndex.concat([self.sequence_pairs(n) for n in names]) if names else None
        return PairIndex.concat([self.sequence_pairs(name) for name in self.test_sequences])
