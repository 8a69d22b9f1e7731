"""Image decoding, resizing and the once-only uint8 frame cache shared by the image datasets.

A frame cache is an `.npy` array (N, C, S, S) uint8 beside a `.json` manifest (the source files,
their sizes, modification and inode change times, and the preprocessing:
`rotlearn.io.cache_manifest`; a cache shipped with a dataset does not match). It is reused,
memory-mapped, while the manifest matches and the array is (N, C, S, S) uint8 for the N frames
(a dataset may ship a foreign or hostile cache); otherwise it is rebuilt with a progress bar. It
is written to a temporary file and renamed into place, so an error or an interrupt never leaves a
half-written cache.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rotlearn.data.image_header import MAX_PIXELS, check_frame
from rotlearn.extras import import_extra
from rotlearn.io import (
    atomic_write,
    cache_manifest,
    read_bytes,
    read_cached_array,
    read_manifest,
    remove_stale_temporaries,
    write_text_atomic,
)

__all__ = [
    "DECODER",
    "frame_cache",
    "read_frame",
    "read_image",
    "resize_center_crop",
    "resize_square",
]

Preprocess = Callable[[np.ndarray], np.ndarray]
_SPARE_BYTES = 2**28  # a frame cache leaves this much of its disk free (256 MiB)
# In each cache's manifest: caches of an earlier decoder are rebuilt (1: 16-bit frames read as
# black; 2: frames turned as their EXIF orientation says)
DECODER = 3


def read_frame(path: Path, gray: bool = False) -> tuple[np.ndarray, str]:
    """An image file as uint8, and how its values were stored.

    The file is read once, up to `rotlearn.io.MAX_BYTES["camera frame"]` bytes (a regular
    file only), and its header checked against the pixel budget before anything is decoded
    (`rotlearn.data.image_header.check_frame`): what is decoded is what was checked, even if
    the file is replaced meanwhile. It is decoded as stored (an EXIF orientation is a display
    hint, not applied: a pose is the sensor's), at its own bit depth and channel count, then
    converted: 16-bit values are scaled to 8 bits (v / 257, rounded), except when every value
    fits in 8 bits (8-bit values stored in 16-bit files, as some exports write them: OpenCV's
    own 8-bit reading would shift them to black), which are kept; colour to gray with OpenCV's
    luma weights, gray to three equal channels, an alpha channel dropped.

    Returns:
        (H, W, 3) RGB, or (H, W) for `gray`, uint8; and "8-bit", "16-bit" or "8-bit values in
        16 bits".

    Raises:
        FileNotFoundError: naming the file, if it is missing.
        ValueError: naming the file: not a regular file, over the byte cap or the pixel budget,
            not an image format rotlearn reads, not decodable (empty, truncated, garbage), or of
            another sample type (floating point, 32-bit).
    """
    cv2 = import_extra("cv2", "reading and resizing images")

    data = read_bytes(path, "camera frame")  # one read: the header checked is the one decoded
    check_frame(path, data)
    try:
        flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR | cv2.IMREAD_IGNORE_ORIENTATION
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:  # a header OpenCV reads otherwise than check_frame: not a traceback
        lines = str(exc).strip().splitlines()
        reason = f" ({lines[-1].strip()})" if lines else ""
        raise ValueError(f"{path}: cannot be decoded as an image{reason}") from None
    if image is None or image.size == 0:
        raise ValueError(f"{path}: cannot be read as an image (empty, truncated or corrupt)")
    if image.dtype == np.uint16:
        if int(image.max()) <= 255:
            image, depth = image.astype(np.uint8), "8-bit values in 16 bits"
        else:
            image = cv2.convertScaleAbs(image, alpha=1 / 257)  # round(v / 257), no uint32 copy
            depth = "16-bit"
    elif image.dtype == np.uint8:
        depth = "8-bit"
    else:
        raise ValueError(
            f"{path}: {image.dtype} samples; rotlearn reads 8- and 16-bit integer images"
        )
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels not in (1, 3, 4):
        raise ValueError(f"{path}: {channels} channels; rotlearn reads 1, 3 or 4")
    if channels == 1:
        image = image.reshape(image.shape[:2])
        return (image if gray else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)), depth
    codes = {(3, True): cv2.COLOR_BGR2GRAY, (4, True): cv2.COLOR_BGRA2GRAY,
             (3, False): cv2.COLOR_BGR2RGB, (4, False): cv2.COLOR_BGRA2RGB}  # fmt: skip
    code = codes[channels, gray]
    return cv2.cvtColor(image, code), depth


def read_image(path: Path, gray: bool = False) -> np.ndarray:
    """An image file as uint8: (H, W, 3) RGB, or (H, W) for `gray` (`read_frame`, any bit
    depth and channel count, the pixel budget checked before decoding).

    Raises:
        FileNotFoundError: naming the file, if it is missing.
        ValueError: naming the file, if it is too large, not a decodable image (empty,
            truncated, garbage) or of a sample type rotlearn does not read.
    """
    return read_frame(path, gray)[0]


def _resized(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """`image` resized to width x height (area filter). ValueError where that is over
    `MAX_PIXELS` (a size from a config: 30000 x 30000 would take 2.7 GB)."""
    cv2 = import_extra("cv2", "reading and resizing images")

    if width * height > MAX_PIXELS:
        h, w = image.shape[:2]
        raise ValueError(f"a {w}x{h} frame resized to {width}x{height} is over the pixel "
                         f"budget ({MAX_PIXELS} pixels)")  # fmt: skip
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def resize_square(image: np.ndarray, size: int) -> np.ndarray:
    """KITTI (paper VI-C): resize to size x size, ignoring the aspect ratio (area filter).
    ValueError where size x size is over `MAX_PIXELS`."""
    return _resized(image, size, size)


def resize_center_crop(image: np.ndarray, resize: int, crop: int) -> np.ndarray:
    """MAV (paper section VI-D): the shorter side to `resize` (aspect kept), then the central
    crop x crop window, as torchvision's Resize(resize) -> CenterCrop(crop). ValueError where
    the resized frame would be over `MAX_PIXELS` (a thin frame, its shorter side scaled up)."""
    height, width = image.shape[:2]
    scale = resize / min(height, width)
    new_w, new_h = max(crop, round(width * scale)), max(crop, round(height * scale))
    resized = _resized(image, new_w, new_h)
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


def _require_space(path: Path, size: int) -> None:
    """ValueError naming `path` unless its file system (that of its nearest existing folder)
    has `size` bytes free and `_SPARE_BYTES` to spare."""
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if size + _SPARE_BYTES > free:
        raise ValueError(
            f"{path}: the frame cache takes {size / 1e9:.2f} GB, but its disk has "
            f"{free / 1e9:.2f} GB free (and {_SPARE_BYTES >> 20} MiB are kept spare); free "
            "space, or set data.cache_dir to a folder with room"
        )


def frame_cache(
    files: Sequence[Path],
    cache: Path,
    preprocess: Preprocess,
    recipe: dict,
    size: int,
    gray: bool = False,
    desc: str = "caching frames",
) -> np.ndarray:
    """The preprocessed frames of `files` as a read-only memory map (N, C, S, S) uint8.

    Args:
        files: image files, in order.
        cache: path stem of the cache; `.npy` and `.json` are added.
        preprocess: (H, W[, 3]) uint8 -> (S, S[, 3]) uint8.
        size: S, the side of every preprocessed frame (a cache of frames of another size is
            rebuilt, whatever its manifest says).
        recipe: JSON-able description of `preprocess` (a different recipe rebuilds the cache).
        gray: decode as one channel (C = 1) instead of RGB (C = 3).
        desc: the progress bar's label.

    Raises:
        FileNotFoundError: naming the first missing file (nothing is left in the cache).
        ValueError: naming the first file that cannot be decoded or is over the pixel budget,
            or whose size or bit depth differs from the first frame's (nothing is left in the
            cache); naming the cache when its disk lacks the space the cache takes (checked
            before anything is decoded: a dataset of many small files can ask for a cache
            thousands of times its size).
    """
    array_path, manifest_path = cache.with_suffix(".npy"), cache.with_suffix(".json")
    shape = (len(files), 1 if gray else 3, size, size)  # what the cache holds
    manifest = cache_manifest(files, {**recipe, "gray": gray, "decoder": DECODER}, "frame")
    if read_manifest(manifest_path) == manifest:
        cached = read_cached_array(array_path, np.uint8, shape)
        if cached is not None:
            return cached
    from tqdm import tqdm

    remove_stale_temporaries(array_path)  # a killed build's: its disk space counts as free
    _require_space(array_path, math.prod(shape))
    manifest_path.unlink(missing_ok=True)
    with atomic_write(array_path) as tmp:
        out = first = depth = None
        for i, path in enumerate(tqdm(files, desc=desc, unit="frame", mininterval=1.0)):
            image, kind = read_frame(path, gray)
            first, depth = (image, kind) if first is None else (first, depth)
            require_same_size(image, first, files, i)
            if kind != depth:
                raise ValueError(
                    f"{path}: frame {i} holds {kind}, but frame 0 ({files[0].name}) holds "
                    f"{depth}: the frames of one sequence must share one bit depth"
                )
            try:
                frame = preprocess(image)
            except ValueError as exc:
                raise ValueError(f"{path}: frame {i}: {exc}") from None
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
