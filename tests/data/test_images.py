"""rotlearn.data.images and image_header: frames of any bit depth and channel count become the
right uint8 pixels, or are refused naming the frame; every header is checked against the pixel
budget before a pixel is decoded. A refused frame changes no frame (`unchanged`) and leaves no
cache of its sequence."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from rotlearn.data import KittiOdometryDataModule
from rotlearn.data.image_header import MAX_PIXELS, check_frame, image_size
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


def test_every_16_bit_value_rounds_to_the_nearest_8_bit_one(tmp_path):
    """v -> round(v / 257) for all 65536 values (v / 257 is never a half), in any channel."""
    values = np.arange(2**16, dtype=np.uint16).reshape(256, 256)
    image, depth = read_frame(_written(tmp_path, "f.png", values), gray=True)
    expected = np.floor(values / 257 + 0.5).astype(np.uint8)
    assert depth == "16-bit"
    np.testing.assert_array_equal(image, expected)
    rgb, _ = read_frame(_written(tmp_path, "g.png", np.stack([values] * 3, axis=-1)))
    np.testing.assert_array_equal(rgb, np.stack([expected] * 3, axis=-1))


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


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_a_frames_exif_orientation_is_not_applied(tmp_path, suffix):
    """A frame's pose is the sensor's: a PNG or JPEG whose EXIF says "turned 180 degrees" or
    "90 degrees" was read turned (OpenCV applies the orientation), its label unchanged."""
    from PIL import Image

    rgb = np.random.default_rng(0).integers(0, 256, (16, 24, 3), dtype=np.uint8)
    plain = tmp_path / f"plain{suffix}"
    Image.fromarray(rgb).save(plain, quality=95)
    for orientation in (3, 6):
        exif = Image.Exif()
        exif[0x0112] = orientation
        path = tmp_path / f"turned{orientation}{suffix}"
        Image.fromarray(rgb).save(path, exif=exif, quality=95)
        np.testing.assert_array_equal(read_frame(path)[0], read_frame(plain)[0])


def test_floating_point_frames_are_refused_naming_them(tmp_path, monkeypatch):
    """A TIFF's sample type is read from its header and refused before decoding: 7 KB of
    deflated float64 zeros at 8192 x 8192 took 3 GB to decode, then were refused."""
    import cv2

    path = _written(tmp_path, "f.tiff", COLOUR.astype(np.float32) / 255)
    monkeypatch.setattr(cv2, "imdecode", lambda *args: pytest.fail("decoded"))
    with unchanged(tmp_path), pytest.raises(ValueError, match=r"f\.tiff: a TIFF of 32-bit "
                                            r"samples; rotlearn reads 8- and 16-bit integer "
                                            r"images; not decoded$"):  # fmt: skip
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


def test_a_shipped_cache_that_fits_is_not_trusted_over_the_frames(tmp_path):
    """A dataset archive can ship a cache whose manifest matches (the same paths, sizes and
    modification times, which an archive keeps) beside frames other than its PNGs: a model
    trained on pixels no one looked at. The manifest also records each file's inode change
    time, which unpacking sets and no archive carries: a shipped cache is rebuilt."""
    import shutil

    root = write_kitti(tmp_path / "data", {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})

    def cached() -> np.ndarray:
        dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                     image_size=8, num_workers=0)  # fmt: skip
        dm.setup()
        return np.load(next((root / ".rotlearn_cache").glob("00_*.npy")))

    genuine = cached()
    np.testing.assert_array_equal(cached(), genuine)  # reused as it is on this machine
    array = next((root / ".rotlearn_cache").glob("00_*.npy"))
    np.save(array, 255 - genuine)  # the poisoned frames, in the cache the archive ships
    packed = shutil.copytree(root, tmp_path / "archive")  # copy2: sizes and mtimes kept
    shutil.rmtree(root)
    shutil.move(packed, root)  # unpacked where the data was: the same paths
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


def _os2_bmp(width: int, height: int, pixels: bytes = bytes(64)) -> bytes:
    """A BMP with an OS/2 core header (12 bytes: 16-bit width and height), 1 bit per pixel,
    as the auditor's 100-byte file that OpenCV read as 64513 x 65535 (and the header check once
    as 1023 x 65536: 32-bit fields at the offsets of the Windows header)."""
    core = struct.pack("<IHHHH", 12, width, height, 1, 1)
    palette = b"\0\0\0\xff\xff\xff"  # two BGR entries, 3 bytes each in an OS/2 BMP
    return b"BM" + struct.pack("<IHHI", 0, 0, 0, 26 + len(palette)) + core + palette + pixels


HEADERS = {
    "png 30000 x 30000": (_png_header(30000, 30000), "png"),
    "png 40000 x 40000": (_png_header(40000, 40000), "png"),
    "jpeg 60000 x 60000": (_jpeg_header(60000, 60000), "jpg"),
    "bmp 20000 x -20000": (_bmp_header(20000, -20000), "bmp"),
    "bmp 64513 x 65535, OS/2 core header": (_os2_bmp(64513, 65535), "bmp"),
    "pgm 50000 x 50000": (b"P5\n# a comment\n50000 50000\n255\n", "pgm"),
    # OpenCV ends a comment at "\r" too: not 1 x 1 (the "\n" line after the comment)
    "pgm 9000 x 9000, comment ended by CR": (b"P5\n#\r9000 9000 255\n1 1\n", "pgm"),
    # OpenCV takes the byte after a number with it, "#" too: not 9000 x 1 (the next line)
    "pgm 9000 x 9000, width ended by #": (b"P5\n9000#9000\n1\n", "pgm"),
    # the height runs past the header's first 64 bytes: not 9000 x 9
    "pgm 9000 x 9000, height past byte 64": (b"P5\n" + b" " * 55 + b"9000 9000 255\n", "pgm"),
    "webp 16383 x 16383": (b"RIFF\0\0\0\0WEBPVP8X" + bytes(8) + b"\xfe\x3f\0\xfe\x3f\0", "webp"),
}


def _many_scans_jpeg(scans: int, width: int = 64, between: bytes = b"") -> bytes:
    """A progressive gray JPEG whose every AC scan codes each block as end-of-band: a few bytes
    a scan, each a pass over the whole frame for the decoder."""

    def segment(marker: int, body: bytes) -> bytes:
        return bytes([0xFF, marker]) + struct.pack(">H", len(body) + 2) + body

    blocks = (width // 8) ** 2
    return (b"\xff\xd8" + segment(0xDB, b"\0" + b"\1" * 64)
            + segment(0xC2, struct.pack(">BHHB", 8, width, width, 1) + b"\1\x11\0")
            + segment(0xC4, b"\0" + bytes([1] + [0] * 15) + b"\0")
            + segment(0xC4, b"\x10" + bytes([1] + [0] * 15) + b"\xe0") + between
            + segment(0xDA, b"\1\1\0\0\0\0") + bytes(blocks // 8)
            + (segment(0xDA, b"\1\1\0\1\x3f\0") + bytes(2)) * (scans - 1)
            + b"\xff\xd9")  # fmt: skip


def test_a_jpeg_of_too_many_scans_is_refused_before_decoding(tmp_path):
    """OpenCV decodes every scan over the whole frame, with no limit: 10,000 scans in 1.4 MB
    took 50 s at 8192 x 8192 (within the pixel budget). The scans are counted first."""
    from rotlearn.data.image_header import MAX_JPEG_SCANS, jpeg_scans

    few, many = _many_scans_jpeg(12), _many_scans_jpeg(MAX_JPEG_SCANS + 1)
    assert jpeg_scans(few) == 12 and jpeg_scans(many) == MAX_JPEG_SCANS + 1
    (tmp_path / "few.jpg").write_bytes(few)
    assert read_frame(tmp_path / "few.jpg", gray=True)[0].shape == (64, 64)
    # markers a decoder skips (5000 restarts, a stray byte) do not hide the scans after them
    hidden = _many_scans_jpeg(MAX_JPEG_SCANS + 1, between=b"\xff\xd0" * 5000 + b"\0")
    for name, content in (("many.jpg", many), ("hidden.jpg", hidden)):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=rf"{name}: a JPEG of more than {MAX_JPEG_SCANS} "):
            read_frame(tmp_path / name, gray=True)


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


@pytest.mark.parametrize(
    ("content", "size"),
    [
        (_png_header(30000, 30000), "a PNG of 30000 x 30000"),
        (_os2_bmp(64513, 65535), "a BMP of 64513 x 65535"),
    ],
    ids=["png", "os2 bmp"],
)
def test_a_kitti_frame_over_the_budget_names_the_frame(tmp_path, content, size):
    root = write_kitti(tmp_path, {"00": yaw_sequence(4, 1.0), "01": yaw_sequence(3, 1.0)})
    frame = root / "sequences" / "00" / "image_2" / "000001.png"
    frame.write_bytes(content)
    dm = KittiOdometryDataModule(str(root), train_sequences=["01"], test_sequences=["00"],
                                 image_size=8, num_workers=0)  # fmt: skip
    with (
        unchanged(root / "sequences"),
        within(10),
        pytest.raises(ValueError, match=rf"000001\.png: {size} pixels"),
    ):
        dm.setup()
    assert not list((root / ".rotlearn_cache").glob("00_*"))  # sequence 01's cache is whole


def test_headers_of_every_format_give_the_size(tmp_path):
    for ext in ("png", "jpg", "bmp", "ppm", "pgm", "webp", "tiff"):
        image = COLOUR[..., 0] if ext == "pgm" else COLOUR
        assert image_size(_written(tmp_path, f"f.{ext}", image))[:2] == (20, 12), ext


def test_an_os2_bmp_header_gives_the_size_opencv_decodes(tmp_path):
    """The OS/2 core header (12 bytes) holds 16-bit width and height, where the Windows
    header (40 bytes and more) holds 32-bit ones: read as OpenCV reads them."""
    path = tmp_path / "f.bmp"
    path.write_bytes(_os2_bmp(20, 12, bytes(4 * 12)))  # rows of 20 bits, padded to 4 bytes
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape[:2] == (12, 20)
    assert image_size(path) == (20, 12, "BMP")
    assert read_image(path).shape == (12, 20, 3)


def test_a_frame_opencv_fails_on_is_refused_in_one_line_naming_it(tmp_path, monkeypatch):
    """Whatever header OpenCV reads otherwise than `check_frame` (an OS/2 BMP once), its
    cv2.error (not a ValueError: a traceback naming no file) becomes a ValueError naming it."""
    import rotlearn.data.images as images

    path = tmp_path / "000000.bmp"
    path.write_bytes(_os2_bmp(64513, 65535))
    monkeypatch.setattr(images, "check_frame", lambda path, data: None)  # as before the fix
    with unchanged(tmp_path), within(10), pytest.raises(ValueError) as info:
        read_image(path)
    assert str(info.value).startswith(f"{path}: cannot be decoded as an image (")
    assert "\n" not in str(info.value)


PNM_LAYOUTS = {  # headers of a 20 x 12 PGM, each read by OpenCV as 20 x 12
    "plain": b"P5\n20 12\n255\n",
    "comment ended by CR": b"P5\n#\r20 12 255\n",
    "comments ended by LF and CR": b"P5 20 12 #x\n#y\r255 ",
    "width ended by #": b"P5\n20#12\n255\n",
    "width ended by x": b"P5 20x12 255 ",
    "VT, FF and CR as spaces": b"P5\n20\x0b12\x0c255\r",
    "height past byte 64": b"P5\n" + b" " * 55 + b"20 12 255\n",
}


@pytest.mark.parametrize("layout", sorted(PNM_LAYOUTS))
def test_a_pnm_header_gives_the_size_opencv_decodes(tmp_path, layout):
    path = tmp_path / "f.pgm"
    path.write_bytes(PNM_LAYOUTS[layout] + bytes(range(240)))
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape == (12, 20)
    assert image_size(path) == (20, 12, "PNM")


def test_pnm_files_opencv_writes_give_their_size(tmp_path):
    gray16 = COLOUR[..., 0].astype(np.uint16) * 257
    for name, image in (("f.pbm", COLOUR[..., 0]), ("f.pgm", gray16), ("f.ppm", COLOUR)):
        assert image_size(_written(tmp_path, name, image)) == (20, 12, "PNM"), name


def _tiff(entries: list[tuple[int, int, int, bytes]], order: str = "<", tail: bytes = b"") -> bytes:
    """A classic TIFF: its header, one IFD of (tag, type, count, value field) entries, `tail`."""
    magic = b"II*\x00" if order == "<" else b"MM\x00*"
    ifd = struct.pack(order + "H", len(entries)) + b"".join(
        struct.pack(order + "HHI", tag, kind, count) + value.ljust(4, b"\x00")
        for tag, kind, count, value in entries
    )
    return magic + struct.pack(order + "I", 8) + ifd + bytes(4) + tail


Field = tuple[int, int, bytes]  # a TIFF IFD entry's type, count and value field


@pytest.mark.parametrize(
    ("tag", "field", "said"),
    [
        (258, (4, 1, struct.pack("<I", 64)), "a TIFF of 64-bit samples"),  # a LONG
        (258, (1, 3, bytes([32, 32, 32])), "a TIFF of 32-bit samples"),  # BYTEs
        (258, (4, 3, struct.pack("<I", 200)), "a TIFF of 64-bit samples"),  # LONGs elsewhere
        (339, (3, 1, struct.pack("<H", 3)), "a TIFF of floating-point samples"),
        (339, (5, 1, bytes(4)), r"a TIFF header whose tag 339 is 1 value\(s\) of type 5"),
    ],
)
def test_a_tiff_sample_type_is_refused_from_its_header_in_any_integer_type(tmp_path, tag, field,
                                                                           said):  # fmt: skip
    """libtiff reads BitsPerSample and SampleFormat as BYTEs, SHORTs or LONGs: a float64 TIFF
    whose BitsPerSample was a LONG passed the header check and took 3 GB to decode."""
    kind, count, value = field
    size = [(256, 3, 1, struct.pack("<H", 8192)), (257, 3, 1, struct.pack("<H", 8192))]
    tail = struct.pack("<3I", 64, 64, 64)  # three LONGs at byte 200 (after a 4-entry IFD)
    content = _tiff([*size, (tag, kind, count, value), (277, 3, 1, struct.pack("<H", 3))])
    path = tmp_path / "f.tiff"
    path.write_bytes(content.ljust(200, b"\0") + tail)
    with pytest.raises(ValueError, match=rf"f\.tiff: {said}"):
        check_frame(path)


def _gray_tiff(
    width: list[Field], height: list[Field], order: str = "<", extra: bytes = b""
) -> bytes:
    """An 8-bit gray TIFF of 20 x 12 pixels: its ImageWidth and ImageLength entries `width` and
    `height` (in that order, then 7 others), after the IFD `extra`, then the pixels' strip."""
    long, short = (lambda v: struct.pack(order + "I", v)), (lambda v: struct.pack(order + "H", v))
    rest = [(258, 3, 1, short(8)), (259, 3, 1, short(1)), (262, 3, 1, short(1))]
    rest += [(273, 4, 1, b""), (277, 3, 1, short(1)), (278, 4, 1, long(12)), (279, 4, 1, long(240))]
    entries = [(256, *e) for e in width] + [(257, *e) for e in height] + rest
    strip = len(_tiff(entries, order)) + len(extra)
    entries[len(width) + len(height) + 3] = (273, 4, 1, long(strip))
    return _tiff(entries, order, extra + bytes(range(240)))


@pytest.mark.parametrize("order", ["<", ">"])
def test_tiff_sizes_as_one_short_or_long_are_read(tmp_path, order):
    short, long = (lambda v: struct.pack(order + "H", v)), (lambda v: struct.pack(order + "I", v))
    for kinds in ((3, 3), (4, 4), (3, 4)):
        path = tmp_path / "f.tiff"
        value = {3: short, 4: long}
        width, height = (kinds[0], 1, value[kinds[0]](20)), (kinds[1], 1, value[kinds[1]](12))
        path.write_bytes(_gray_tiff([width], [height], order))
        assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape == (12, 20), kinds
        assert image_size(path) == (20, 12, "TIFF"), kinds
    for depth, image in (("16-bit gray", COLOUR[..., 0].astype(np.uint16) * 257), ("rgb", COLOUR)):
        assert image_size(_written(tmp_path, "w.tiff", image)) == (20, 12, "TIFF"), depth


@pytest.mark.parametrize("order", ["<", ">"])
def test_a_tiff_naming_its_size_twice_is_refused(tmp_path, order):
    long = lambda v: struct.pack(order + "I", v)  # noqa: E731
    # libtiff (OpenCV) decodes the first, 9000 x 9000; the last says 16 x 16
    path = tmp_path / "000000.tiff"
    twice = [(4, 1, long(9000)), (4, 1, long(16))]
    path.write_bytes(_gray_tiff(twice, twice, order))
    with (
        unchanged(tmp_path),
        within(5),
        pytest.raises(
            ValueError, match=r"000000\.tiff: a TIFF header naming its ImageWidth \(256\) twice"
        ),
    ):
        read_image(path)
    path.write_bytes(_gray_tiff([(4, 1, long(20))], [(4, 1, long(9000)), (4, 1, long(12))], order))
    with pytest.raises(ValueError, match=r"naming its ImageLength \(257\) twice.*; not decoded"):
        check_frame(path)


EXTRA = struct.pack("<I", 8 + 2 + 9 * 12 + 4)  # where `_gray_tiff`'s `extra` is, 1 size each
BAD_SIZE_FIELDS = {  # (type, count, value field, what follows the IFD) of ImageWidth
    # LONG8: libtiff reads 9000 from the 8 bytes at `EXTRA`; a 4-byte read took `EXTRA` (122)
    "LONG8": (16, 1, EXTRA, struct.pack("<Q", 9000)),
    "two LONGs": (4, 2, EXTRA, struct.pack("<II", 9000, 9000)),
    "no SHORT": (3, 0, struct.pack("<H", 16), b""),
    "BYTE": (1, 1, bytes([16]), b""),
    "SLONG": (9, 1, struct.pack("<i", 16), b""),
    "RATIONAL": (5, 1, EXTRA, struct.pack("<II", 9000, 1)),
}


@pytest.mark.parametrize("name", sorted(BAD_SIZE_FIELDS))
def test_a_tiff_size_not_one_short_or_long_is_refused(tmp_path, name):
    kind, count, value, extra = BAD_SIZE_FIELDS[name]
    path = tmp_path / "000000.tiff"
    path.write_bytes(
        _gray_tiff([(kind, count, value)], [(4, 1, struct.pack("<I", 12))], "<", extra)
    )
    with (
        unchanged(tmp_path),
        within(5),
        pytest.raises(
            ValueError,
            match=rf"000000\.tiff: a TIFF header whose ImageWidth \(256\) is {count} value\(s\) "
            rf"of type {kind}; a size must be one SHORT \(3\) or LONG \(4\); not decoded",
        ),
    ):
        read_image(path)


def test_a_bigtiff_is_refused_naming_it(tmp_path):
    path = tmp_path / "000000.tiff"
    # BigTIFF: version 43, 8-byte offsets; one IFD of 20-byte entries: ImageWidth, ImageLength
    entries = b"".join(struct.pack("<HHQQ", tag, 16, 1, 9000) for tag in (256, 257))
    path.write_bytes(b"II+\x00" + struct.pack("<HHQ", 8, 0, 16) + struct.pack("<Q", 2) + entries)
    with unchanged(tmp_path), pytest.raises(ValueError, match=r"000000\.tiff: a BigTIFF"):
        read_image(path)
    path.write_bytes(b"MM\x00+" + bytes(12))
    with pytest.raises(ValueError, match=r"000000\.tiff: a BigTIFF .*; not decoded"):
        check_frame(path)


def test_an_unknown_format_a_named_pipe_or_a_directory_is_refused(tmp_path):
    path = tmp_path / "f.gif"
    path.write_bytes(b"GIF89a" + bytes(20))
    with pytest.raises(ValueError, match=r"f\.gif: cannot be read as an image"):
        read_image(path)
    fifo = tmp_path / "000000.png"
    os.mkfifo(fifo)
    with within(5), pytest.raises(ValueError, match="not a regular file"):
        read_image(fifo)
    folder = tmp_path / "000001.png"  # named by the user (rotlearn-predict's frames): named back
    folder.mkdir()
    with pytest.raises(ValueError, match=r"000001\.png: a folder, not a regular file"):
        read_image(folder)


def test_the_frame_decoded_is_the_one_whose_header_was_checked(tmp_path, monkeypatch):
    """The header was read from the path, then OpenCV opened the path again: a file renamed over
    it in between (one over the pixel budget, say) was decoded unchecked. Now one read feeds
    both."""
    import rotlearn.data.image_header as header

    path, other = tmp_path / "000000.png", tmp_path / "other.png"
    cv2.imwrite(str(path), np.full((12, 20), 7, np.uint8))
    cv2.imwrite(str(other), np.full((30, 30), 9, np.uint8))
    png = header._READERS["PNG"]

    def swapped_after_the_header(f, head):
        size = png(f, head)
        if other.exists():
            os.replace(other, path)
        return size

    monkeypatch.setitem(header._READERS, "PNG", swapped_after_the_header)
    image = read_image(path, gray=True)
    assert not other.exists()  # the swap happened
    assert image.shape == (12, 20) and (image == 7).all()


def test_a_frame_file_over_its_byte_cap_is_refused_unread(tmp_path, monkeypatch):
    """A header of a few pixels before gigabytes of anything: OpenCV read through all of it.
    Every frame file is read up to `MAX_BYTES["camera frame"]` (1 GiB; here lowered)."""
    from rotlearn.io import MAX_BYTES

    path = tmp_path / "000000.png"
    cv2.imwrite(str(path), np.zeros((12, 20), np.uint8))
    monkeypatch.setitem(MAX_BYTES, "camera frame", path.stat().st_size)
    assert read_image(path, gray=True).shape == (12, 20)  # at the cap: read
    with path.open("ab") as f:
        f.write(b"\0")
    cap = path.stat().st_size - 1
    with within(5), pytest.raises(ValueError, match=rf"000000\.png: too large for a camera frame "
                                  rf"\(over {cap} bytes\); not read"):  # fmt: skip
        read_image(path)
