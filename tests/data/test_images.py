"""rotlearn.data.images and image_header: frames of any bit depth and channel count become the
right uint8 pixels, or are refused naming the frame; every header is checked against the pixel
budget before a pixel is decoded. A refused frame changes no frame (`unchanged`) and leaves no
cache of its sequence."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from rotlearn.data import KittiOdometryDataModule
from rotlearn.data.image_header import MAX_PIXELS, image_size
from rotlearn.data.images import read_frame, read_image
from tests.conftest import unchanged, within, write_kitti, yaw_sequence

cv2 = pytest.importorskip("cv2")
RNG = np.random.default_rng(0)
COLOUR = RNG.integers(0, 256, (12, 20, 3), dtype=np.uint8)  # BGR, as OpenCV writes it


def _written(tmp_path: Path, name: str, image: np.ndarray) -> Path:
    path = tmp_path / name
    assert cv2.imwrite(str(path), image)
    return path


def test_16_bit_frames_holding_8_bit_values_are_not_read_as_black(tmp_path):
    """OpenCV's 8-bit reading shifts 16-bit values right by 8: such frames became all zeros."""
    path = _written(tmp_path, "f.png", COLOUR.astype(np.uint16))
    assert cv2.imread(str(path), cv2.IMREAD_COLOR).max() == 0  # what the landed code read
    image, depth = read_frame(path)
    assert depth == "8-bit values in 16 bits"
    np.testing.assert_array_equal(image, COLOUR[..., ::-1])  # RGB


def test_full_range_16_bit_frames_are_scaled_to_8_bits(tmp_path):
    wide = (COLOUR.astype(np.uint32) * 257).astype(np.uint16)  # 0..65535
    image, depth = read_frame(_written(tmp_path, "f.png", wide))
    assert depth == "16-bit"
    np.testing.assert_array_equal(image, COLOUR[..., ::-1])


@pytest.mark.parametrize("ext", ["png", "jpg", "bmp", "ppm", "webp", "tiff"])
def test_every_channel_count_becomes_rgb_or_gray(tmp_path, ext):
    lossless = ext not in ("jpg", "webp")
    gray = COLOUR[..., 1]
    bgra = np.dstack([COLOUR, np.full(COLOUR.shape[:2], 7, np.uint8)])
    for image, rgb, as_gray in [
        (COLOUR, COLOUR[..., ::-1], cv2.cvtColor(COLOUR, cv2.COLOR_BGR2GRAY)),
        (gray, np.dstack([gray] * 3), gray),
        (bgra, COLOUR[..., ::-1], cv2.cvtColor(COLOUR, cv2.COLOR_BGR2GRAY)),
    ]:
        if ext in ("ppm", "jpg", "bmp") and image.ndim == 3 and image.shape[2] == 4:
            continue  # formats without alpha
        if ext == "ppm" and image.ndim == 2:
            continue  # PPM is colour only (PGM is its gray form)
        path = _written(tmp_path, f"f.{ext}", image)
        got_rgb, got_gray = read_image(path), read_image(path, gray=True)
        assert got_rgb.shape == (12, 20, 3) and got_gray.shape == (12, 20)
        assert got_rgb.dtype == got_gray.dtype == np.uint8
        if lossless:
            np.testing.assert_array_equal(got_rgb, rgb)
            np.testing.assert_array_equal(got_gray, as_gray)


def test_floating_point_frames_are_refused_naming_them(tmp_path):
    path = _written(tmp_path, "f.tiff", COLOUR.astype(np.float32) / 255)
    with unchanged(tmp_path), pytest.raises(ValueError, match=r"f\.tiff: float32 samples"):
        read_image(path)


def test_a_16_bit_kitti_sequence_caches_the_same_pixels_as_an_8_bit_one(tmp_path):
    rotations = {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)}
    plain, wide = write_kitti(tmp_path / "a", rotations), write_kitti(tmp_path / "b", rotations)
    for path in (wide / "sequences").rglob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path)).astype(np.uint16))  # 8-bit values, 16 bits
    frames = []
    for root in (plain, wide):
        dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                     image_size=8, num_workers=0)  # fmt: skip
        dm.setup()
        frames.append(np.load(next((root / ".rotlearn_cache").glob("00_*.npy"))))
    assert frames[0].any()
    np.testing.assert_array_equal(frames[0], frames[1])


def test_a_shipped_frame_cache_that_does_not_fit_is_rebuilt(tmp_path):
    """A dataset may ship its `.rotlearn_cache`: a matching manifest beside an array of another
    dtype, frame count, channel count or a non-square frame, or a named pipe as the manifest,
    is not used (nor does it hang): the frames are decoded again, the same pixels result."""
    import json
    import os

    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})

    def cached() -> np.ndarray:
        dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                     image_size=8, num_workers=0)  # fmt: skip
        with within(60):
            dm.setup()
        return np.load(next((root / ".rotlearn_cache").glob("00_*.npy")))

    genuine = cached()
    array = next((root / ".rotlearn_cache").glob("00_*.npy"))
    manifest = array.with_suffix(".json")
    record = manifest.read_text()
    for foreign in (genuine.astype(np.float32), genuine[:2], genuine[:, :1], genuine[..., :4]):
        np.save(array, foreign)
        manifest.write_text(record)  # the manifest still matches the frames
        got = cached()
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, genuine)
        assert json.loads(manifest.read_text()) == json.loads(record)
    manifest.unlink()
    os.mkfifo(manifest)
    np.testing.assert_array_equal(cached(), genuine)


def test_a_sequence_mixing_bit_depths_is_refused_naming_the_frame(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    frame = root / "sequences" / "00" / "image_2" / "000002.png"
    cv2.imwrite(str(frame), (cv2.imread(str(frame)).astype(np.uint16) * 257))
    dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                 image_size=8, num_workers=0)  # fmt: skip
    with (
        unchanged(root / "sequences"),
        pytest.raises(ValueError, match=r"000002\.png: frame 2 holds 16-bit, but frame 0"),
    ):
        dm.setup()
    assert not list((root / ".rotlearn_cache").glob("00_*"))  # sequence 01's cache is whole


# ---- headers and the pixel budget ---------------------------------------------------------------


def _png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = lambda kind, data: (  # noqa: E731
        struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    )
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def _jpeg_header(width: int, height: int) -> bytes:
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + app0 + sof + b"\xff\xd9"


def _bmp_header(width: int, height: int) -> bytes:
    return b"BM" + bytes(16) + struct.pack("<ii", width, height) + bytes(28)


HEADERS = {
    "png 30000 x 30000": (_png_header(30000, 30000), "png"),
    "png 40000 x 40000": (_png_header(40000, 40000), "png"),
    "jpeg 60000 x 60000": (_jpeg_header(60000, 60000), "jpg"),
    "bmp 20000 x -20000": (_bmp_header(20000, -20000), "bmp"),
    "pgm 50000 x 50000": (b"P5\n# a comment\n50000 50000\n255\n", "pgm"),
    "webp 16383 x 16383": (b"RIFF\0\0\0\0WEBPVP8X" + bytes(8) + b"\xfe\x3f\0\xfe\x3f\0", "webp"),
}


@pytest.mark.parametrize("name", sorted(HEADERS))
def test_a_frame_over_the_pixel_budget_is_refused_before_decoding(tmp_path, name):
    content, ext = HEADERS[name]
    path = tmp_path / f"000000.{ext}"
    path.write_bytes(content)
    width, height, _ = image_size(path)
    assert width * height > MAX_PIXELS
    with unchanged(tmp_path), within(5), pytest.raises(ValueError, match="over the budget") as info:
        read_image(path)
    assert str(path) in str(info.value) and f"{width} x {height} pixels" in str(info.value)


def test_a_kitti_frame_over_the_budget_names_the_frame(tmp_path):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    frame = root / "sequences" / "00" / "image_2" / "000001.png"
    frame.write_bytes(_png_header(30000, 30000))
    dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                 image_size=8, num_workers=0)  # fmt: skip
    with (
        unchanged(root / "sequences"),
        within(10),
        pytest.raises(ValueError, match=r"000001\.png: a PNG of 30000 x 30000"),
    ):
        dm.setup()
    assert not list((root / ".rotlearn_cache").glob("00_*"))  # sequence 01's cache is whole


def test_headers_of_every_format_give_the_size(tmp_path):
    for ext in ("png", "jpg", "bmp", "ppm", "pgm", "webp", "tiff"):
        image = COLOUR[..., 0] if ext == "pgm" else COLOUR
        assert image_size(_written(tmp_path, f"f.{ext}", image))[:2] == (20, 12), ext


def test_an_unknown_format_a_named_pipe_or_a_directory_is_refused(tmp_path):
    path = tmp_path / "f.gif"
    path.write_bytes(b"GIF89a" + bytes(20))
    with pytest.raises(ValueError, match=r"f\.gif: cannot be read as an image"):
        read_image(path)
    fifo = tmp_path / "000000.png"
    import os

    os.mkfifo(fifo)
    with within(5), pytest.raises(ValueError, match="not a regular file"):
        read_image(fifo)
    folder = tmp_path / "000001.png"  # named by the user (rotlearn-predict's frames): named back
    folder.mkdir()
    with pytest.raises(ValueError, match=r"000001\.png: not a regular file"):
        read_image(folder)
