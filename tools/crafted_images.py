"""Crafted image files, generated (never stored): the shapes an adversarial pass found, for the
tests that reproduce each defect on a real server and for the benchmark that measures them
(bench/crafted_uploads.py)."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
from PIL import Image


def encoded(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width`` x ``height`` with one row of data: a few dozen bytes."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    )


def noise(width: int, height: int) -> Image.Image:
    return Image.fromarray(np.random.default_rng(0).integers(0, 256, (height, width, 3), np.uint8))


#: The shapes that pass found, each generated here (none is a stored fixture).
STRIPS = {
    "49000x32 png": lambda: encoded(Image.new("RGB", (49000, 32)), "PNG"),
    "32x60000 jpeg": lambda: encoded(Image.new("RGB", (32, 60000), (90, 90, 90)), "JPEG"),
    "png declaring 1000000x33": lambda: png_declaring(1_000_000, 33),
    "8000x32 noise png": lambda: encoded(noise(8000, 32), "PNG"),
}


def tiff_with_frames(tiff: bytes, frames: int) -> bytes:
    """``tiff`` (little-endian, one IFD) followed by ``frames`` - 1 more IFDs that all point at its strip:
    what a crafted file of 11 MB does. Each extra IFD copies the first one's entries."""
    assert tiff[:4] == b"II*\x00"
    first = struct.unpack("<I", tiff[4:8])[0]
    n = struct.unpack("<H", tiff[first : first + 2])[0]
    entries = tiff[first + 2 : first + 2 + 12 * n]
    size = 2 + 12 * n + 4
    out = bytearray(tiff)
    base = len(out)
    # the first IFD's "next" offset -> the first extra IFD
    struct.pack_into("<I", out, first + 2 + 12 * n, base)
    for k in range(frames - 1):
        nxt = base + (k + 1) * size if k < frames - 2 else 0
        out += struct.pack("<H", n) + entries + struct.pack("<I", nxt)
    return bytes(out)
