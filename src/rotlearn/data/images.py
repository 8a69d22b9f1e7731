"""Image decoding, resizing and the once-only uint8 frame cache shared by the image datasets.

A frame cache is an `.npy` array (N, C, S, S) uint8 beside a `.json` manifest (the source files,
their sizes and modification times, and the preprocessing). It is reused, memory-mapped, while
the manifest matches; otherwise it is rebuilt with a progress bar. It is written to a temporary
file and renamed into place, so an error or an interrupt never leaves a half-written cache.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rotlearn.extras import import_extra
from rotlearn.io import atomic_write, write_text_atomic

__all__ = [
    "frame_cache",
    "read_image",
    "resize_center_crop",
    "resize_square",
]

Preprocess = Callable[[np.ndarray], np.ndarray]


def read_image(path: Path, gray: bool = False) -> np.ndarray:
    """An image file as uint8: (H, W, 3) RGB, or (H, W) for `gray`.

    Raises:
        FileNotFoundError: naming the file, if it is missing.
        ValueError: naming the file, if it is not a decodable image (empty, truncated, garbage).
    """
    cv2 = import_extra("cv2", "reading and resizing images")

    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise ValueError(f"{path}: cannot be read as an image (empty, truncated or corrupt)")
    return image if gray else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def resize_square(image: np.ndarray, size: int) -> np.ndarray:
    """KITTI (paper VI-C): resize to size x size, ignoring the aspect ratio (area filter)."""
    cv2 = import_extra("cv2", "reading and resizing images")

    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)


def resize_center_crop(image: np.ndarray, resize: int, crop: int) -> np.ndarray:
    """MAV (paper section VI-D): the shorter side to `resize` (aspect kept), then the central
    crop x crop window, as torchvision's Resize(resize) -> CenterCrop(crop)."""
    cv2 = import_extra("cv2", "reading and resizing images")

    height, width = image.shape[:2]
    scale = resize / min(height, width)
    new_w, new_h = max(crop, round(width * scale)), max(crop, round(height * scale))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    top, left = round((new_h - crop) / 2), round((new_w - crop) / 2)
    return resized[top : top + crop, left : left + crop]


def require_same_size(image: np.ndarray, first: np.ndarray, files: Sequence[Path], i: int) -> None:
    """Refuse frame `i` of one sequence if its (H, W) differs from frame 0's: a stray image
    would be resized with another aspect ratio and silently distort the geometry.

    Raises:
        ValueError: naming the file, the frame index and both sizes.
    """
    if image.shape[:2] != first.shape[:2]:
        (h, w), (h0, w0) = image.shape[:2], first.shape[:2]
        raise ValueError(
            f"{files[i]}: frame {i} is {w}x{h} pixels, but frame 0 ({files[0].name}) is "
            f"{w0}x{h0}: the frames of one sequence must share one size"
        )


def _stat(files: Sequence[Path], i: int) -> os.stat_result:
    """The stat of frame `i`; a missing one raises a FileNotFoundError naming it."""
    try:
        return files[i].stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"{files[i]}: frame {i}: no such image file") from None


def _manifest(files: Sequence[Path], recipe: dict) -> dict:
    stats = [_stat(files, i) for i in range(len(files))]
    return {
        "recipe": recipe,
        "files": [str(f) for f in files],
        "sizes": [s.st_size for s in stats],
        "mtimes_ns": [s.st_mtime_ns for s in stats],
    }


def frame_cache(
    files: Sequence[Path],
    cache: Path,
    preprocess: Preprocess,
    recipe: dict,
    gray: bool = False,
    desc: str = "caching frames",
) -> np.ndarray:
    """The preprocessed frames of `files` as a read-only memory map (N, C, S, S) uint8.

    Args:
        files: image files, in order.
        cache: path stem of the cache; `.npy` and `.json` are added.
        preprocess: (H, W[, 3]) uint8 -> (S, S[, 3]) uint8, the same S for every frame.
        recipe: JSON-able description of `preprocess` (a different recipe rebuilds the cache).
        gray: decode as one channel (C = 1) instead of RGB (C = 3).
        desc: the progress bar's label.

    Raises:
        FileNotFoundError: naming the first missing file (nothing is left in the cache).
        ValueError: naming the first file that cannot be decoded, or whose size differs from
            the first frame's (nothing is left in the cache).
    """
    array_path, manifest_path = cache.with_suffix(".npy"), cache.with_suffix(".json")
    manifest = _manifest(files, {**recipe, "gray": gray})
    if (
        manifest_path.is_file()
        and array_path.is_file()
        and json.loads(manifest_path.read_text()) == manifest
    ):
        return np.load(array_path, mmap_mode="r")
    from tqdm import tqdm

    manifest_path.unlink(missing_ok=True)
    with atomic_write(array_path) as tmp:
        out = first = None
        for i, path in enumerate(tqdm(files, desc=desc, unit="frame", mininterval=1.0)):
            image = read_image(path, gray)
            first = image if first is None else first
            require_same_size(image, first, files, i)
            frame = preprocess(image)
            frame = frame[None] if gray else frame.transpose(2, 0, 1)
            if out is None:
                out = np.lib.format.open_memmap(
                    tmp, mode="w+", dtype=np.uint8, shape=(len(files), *frame.shape)
                )
            out[i] = frame
        if out is None:
            raise ValueError(f"{cache}: no frames to cache")
        out.flush()
        del out
    write_text_atomic(manifest_path, json.dumps(manifest))
    return np.load(array_path, mmap_mode="r")
