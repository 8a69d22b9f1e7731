"""An image file's size from its header, read before any pixel is decoded.

A frame of 30000 x 30000 pixels is under a megabyte as a PNG and several gigabytes decoded, so
every frame's width and height are read from its header first and checked against
`MAX_PIXELS` (`check_frame`). The readers take a few bytes from the file's start (JPEG: they walk
its segment headers, skipping each segment's body), from a regular file only. Formats:
PNG, JPEG, BMP, PNM (PBM, PGM, PPM), WebP and TIFF (not BigTIFF); any other is refused, naming the
file, and so is a header OpenCV may read another size from (a TIFF naming its size twice).
"""

from __future__ import annotations

import os
import re
import stat
import struct
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

__all__ = ["MAX_JPEG_SCANS", "MAX_PIXELS", "check_frame", "image_size", "jpeg_scans"]

MAX_PIXELS = 2**26  # 67 Mpx: an 8K x 8K frame; 16-bit RGB, 400 MB decoded (read_frame: 12 B/px)
_JPEG_FRAMES = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_MAX_JPEG_SEGMENTS = 4096
# Scans of a (progressive) JPEG: OpenCV decodes each over the whole frame, about 5 ms a scan at
# 8192 x 8192, with no limit of its own (10,000 scans of 1.4 MB took 50 s); a genuine one has ~10.
MAX_JPEG_SCANS = 500
# PNM as OpenCV's PxM reader reads it: "P1".."P6", a whitespace byte, then width and height, each
# a run of digits ended by one byte of any other kind (taken with it: "20x12" is 20 x 12), before
# each any whitespace and "#" comments, which end at "\n" or "\r".
_PNM_GAP = rb"(?:[ \t\n\v\f\r]|#[^\r\n]*[\r\n])*"
_PNM_SIZE = re.compile(
    rb"P[1-6](?=[ \t\n\v\f\r])" + _PNM_GAP + rb"(\d+)\D" + _PNM_GAP + rb"(\d+)\D"
)
_PNM_HEADER_BYTES = 4096  # a header longer than this (long comments) is refused, not guessed
_TIFF_SIZE_TAGS = {256: "ImageWidth", 257: "ImageLength"}


class _Refused(ValueError):
    """A header that names a size other readers may not read the same way: refused, not guessed."""


def _png(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return struct.unpack(">II", head[16:24])
    return None


def _jpeg(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if head[:2] != b"\xff\xd8":
        return None
    f.seek(2)
    for _ in range(_MAX_JPEG_SEGMENTS):
        if f.read(1) != b"\xff":
            return None
        marker, fill = f.read(1), 0
        while marker == b"\xff" and fill < 65536:  # fill bytes before a marker
            marker, fill = f.read(1), fill + 1
        if not marker or marker == b"\xff":
            return None
        code = marker[0]
        if code in (0xD8, 0x01) or 0xD0 <= code <= 0xD7:  # markers without a length
            continue
        length_bytes = f.read(2)
        if len(length_bytes) < 2:
            return None
        (length,) = struct.unpack(">H", length_bytes)
        if code in _JPEG_FRAMES:
            data = f.read(5)
            if len(data) < 5:
                return None
            height, width = struct.unpack(">HH", data[1:5])
            return width, height
        if code in (0xD9, 0xDA) or length < 2:  # end of image, or the scan before a frame header
            return None
        f.seek(length - 2, os.SEEK_CUR)
    return None


def jpeg_scans(data: bytes) -> int:
    """How many scans the JPEG `data` may hold: its start-of-scan markers (FF DA), which
    entropy-coded data never holds (an FF there is followed by 00 or a restart code), counted
    wherever they are: a count never below the decoder's, whatever lies between segments."""
    return data.count(b"\xff\xda")


def _bmp(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if head[:2] != b"BM" or len(head) < 26:
        return None
    if struct.unpack("<I", head[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16 bits, unsigned
        return struct.unpack("<HH", head[18:22])
    width, height = struct.unpack("<ii", head[18:26])  # BITMAPINFOHEADER and later: 32, signed
    return abs(width), abs(height)


def _pnm(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if len(head) < 3 or head[0:1] != b"P" or head[1:2] not in b"123456":
        return None
    f.seek(0)
    match = _PNM_SIZE.match(f.read(_PNM_HEADER_BYTES))  # a number cut off at the end: no match
    return (int(match[1]), int(match[2])) if match else None


def _webp(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if head[:4] != b"RIFF" or head[8:12] != b"WEBP" or len(head) < 30:
        return None
    chunk = head[12:16]
    if chunk == b"VP8 ":
        width, height = struct.unpack("<HH", head[26:30])
        return width & 0x3FFF, height & 0x3FFF
    if chunk == b"VP8L":
        bits = int.from_bytes(head[21:25], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":
        return int.from_bytes(head[24:27], "little") + 1, int.from_bytes(head[27:30], "little") + 1
    return None


def _tiff(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    if head[:4] in (b"II+\x00", b"MM\x00+"):
        raise _Refused("a BigTIFF (64-bit offsets), not read here: only classic TIFF headers are")
    order = {b"II*\x00": "<", b"MM\x00*": ">"}.get(head[:4])
    if order is None:
        return None
    (offset,) = struct.unpack(order + "I", head[4:8])
    f.seek(offset)
    count_bytes = f.read(2)
    if len(count_bytes) < 2:
        return None
    (count,) = struct.unpack(order + "H", count_bytes)
    size: dict[int, int] = {}
    for _ in range(min(count, 4096)):
        entry = f.read(12)
        if len(entry) < 12:
            break
        tag, kind, n = struct.unpack(order + "HHI", entry[:8])
        if tag in (258, 339):  # BitsPerSample, SampleFormat: refused before decoding (a float
            _tiff_sample_type(f, order, tag, kind, n, entry[8:])  # frame of 7 KB took 3 GB)
        if tag not in _TIFF_SIZE_TAGS:
            continue
        name = f"{_TIFF_SIZE_TAGS[tag]} ({tag})"
        if tag in size:  # libtiff takes the first, other readers the last
            raise _Refused(f"a TIFF header naming its {name} twice: its size is ambiguous")
        if kind not in (3, 4) or n != 1:  # libtiff also reads LONG8 (16), from another offset
            raise _Refused(
                f"a TIFF header whose {name} is {n} value(s) of type {kind}; "
                "a size must be one SHORT (3) or LONG (4)"
            )
        fmt, value = (order + "H", entry[8:10]) if kind == 3 else (order + "I", entry[8:12])
        size[tag] = struct.unpack(fmt, value)[0]
    if 256 in size and 257 in size:
        return size[256], size[257]
    return None


def _tiff_sample_type(f: BinaryIO, order: str, tag: int, kind: int, n: int, field: bytes):
    """Refuse a TIFF whose samples are over 16 bits (BitsPerSample, 258) or floating point
    (SampleFormat 3, tag 339): what `rotlearn.data.images.read_frame` refuses once decoded.
    Their values may be BYTEs, SHORTs or LONGs (libtiff reads each); another type is refused."""
    width, code = {1: (1, "B"), 3: (2, "H"), 4: (4, "I")}.get(kind, (0, ""))
    if not width or not 0 < n <= 64:
        raise _Refused(f"a TIFF header whose tag {tag} is {n} value(s) of type {kind}; "
                       "rotlearn reads 1 to 64 BYTEs, SHORTs or LONGs there")  # fmt: skip
    if n * width <= 4:
        data = field[: n * width]
    else:  # the values lie elsewhere in the file
        here = f.tell()
        f.seek(struct.unpack(order + "I", field)[0])
        data = f.read(n * width)
        f.seek(here)
    values = struct.unpack(f"{order}{len(data) // width}{code}", data[: len(data) // width * width])
    if tag == 258 and values and max(values) > 16:
        raise _Refused(f"a TIFF of {max(values)}-bit samples; rotlearn reads 8- and 16-bit "
                       "integer images")  # fmt: skip
    if tag == 339 and 3 in values:
        raise _Refused("a TIFF of floating-point samples; rotlearn reads 8- and 16-bit integer "
                       "images")  # fmt: skip


_READERS = {"PNG": _png, "JPEG": _jpeg, "BMP": _bmp, "PNM": _pnm, "WebP": _webp, "TIFF": _tiff}


def image_size(path: str | os.PathLike, data: bytes | None = None) -> tuple[int, int, str]:
    """(width, height, format) of an image file, from its header alone.

    Args:
        path: the file (read, unless `data` is given; named in messages).
        data: the file's bytes, already read: the header is taken from them, not from the file
            again (`rotlearn.data.images.read_frame` decodes the same bytes).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: not a regular file, or not an image in one of the formats
            read here (or a header too damaged to give a size), or a header whose size OpenCV may
            read otherwise (a TIFF naming its size twice, or not as one SHORT or LONG; a BigTIFF).
    """
    path = Path(path)
    if data is not None:
        return _header_size(path, BytesIO(data))
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such image file") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # before fdopen, which refuses a directory
        os.close(fd)  # with "[Errno 21] Is a directory: <fd>", naming no file
        raise ValueError(f"{path}: not a regular file; not read as an image")
    with os.fdopen(fd, "rb") as f:
        return _header_size(path, f)


def _header_size(path: Path, f: BinaryIO) -> tuple[int, int, str]:
    """`image_size` of the open file `f` (from its start)."""
    head = f.read(64)
    for name, reader in _READERS.items():
        f.seek(0)
        try:
            size = reader(f, head)
        except _Refused as refused:
            raise ValueError(f"{path}: {refused}; not decoded") from None
        except (struct.error, OSError, ValueError):
            size = None
        if size is not None:
            return int(size[0]), int(size[1]), name
    known = ", ".join(_READERS)
    raise ValueError(
        f"{path}: cannot be read as an image: no {known} header (empty, damaged, or another format)"
    )


def check_frame(path: str | os.PathLike, data: bytes | None = None) -> tuple[int, int]:
    """(width, height) of an image file (or of its bytes `data`, as `image_size`), if its
    header says at most `MAX_PIXELS` pixels.

    Raises:
        ValueError: naming the file and its size in pixels when it is larger than the budget,
            a JPEG among `data` of more than `MAX_JPEG_SCANS` scans, or as `image_size`.
    """
    width, height, kind = image_size(path, data)
    if width * height > MAX_PIXELS:
        raise ValueError(
            f"{path}: a {kind} of {width} x {height} pixels, over the budget of {MAX_PIXELS} "
            "pixels per frame; not decoded"
        )
    if width == 0 or height == 0:
        raise ValueError(f"{path}: a {kind} of {width} x {height} pixels (empty); not decoded")
    if kind == "JPEG" and data is not None and jpeg_scans(data) > MAX_JPEG_SCANS:
        raise ValueError(f"{path}: a JPEG of more than {MAX_JPEG_SCANS} scans (decoding each "
                         "takes a pass over the whole frame); not decoded")  # fmt: skip
    return width, height
