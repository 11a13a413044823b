"""A reference's local features in the compact form stored beside it: numpy in, bytes out, and back.

Why store them: verification re-extracted every candidate's features from its image on every request
(decode + RootSIFT per candidate: most of what ``rerank=true`` cost, docs/results.md), so it
could not be in every answer. Stored once at ingestion, a candidate's features are one small file read.

The form (version 1, little-endian), ``HEADER`` then two arrays:

- keypoints as uint16 fractions of the extractor's image (x / width, y / height, times 65535): exact to
  1/65535 of a side (0.016 px at 1,024 px), half the bytes of float32 pixels, and independent of size;
- descriptors as uint8, ``round(value * scale)`` clipped to 255. RootSIFT components are square roots of
  L1 shares, so they lie in [0, 1] and in practice below 0.34 on penn photos: ``scale`` 512 keeps 1/1024
  steps without clipping any of them. Unit-length learned descriptors (XFeat, in [-1, 1]) and RootSIFT
  projected on fewer orthonormal directions (``rootsift-pca``, also in [-1, 1]) are stored shifted,
  ``(value + 1) * 127.5`` (``offset`` 1).

The width and height of the image the extractor saw are stored so that positions come back in pixels
(RANSAC's thresholds are in pixels); a CRC32 of the arrays lets ``geoloc check`` and a reader tell a torn or
corrupted file from a valid one. A header names the descriptor's kind, so a reader never matches RootSIFT
against another extractor's descriptors, and ``VERSION`` changes whenever the layout does.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"GLLF"
VERSION = 1
#: magic, version, kind, width, height, dim, n keypoints, descriptor scale, descriptor offset, CRC32 of arrays.
HEADER = struct.Struct("<4sBBHHHIffI")

#: The descriptor kinds a stored file may hold; the number is what the header stores.
KINDS: dict[str, int] = {"rootsift": 1, "xfeat": 2, "rootsift-pca": 3}
_KIND_NAMES = {v: k for k, v in KINDS.items()}
#: How each kind's float descriptors map to uint8: (scale, offset), ``q = round((d + offset) * scale)``.
QUANTISATION: dict[str, tuple[float, float]] = {
    "rootsift": (512.0, 0.0),
    "xfeat": (127.5, 1.0),
    "rootsift-pca": (127.5, 1.0),  # RootSIFT projected on an orthonormal basis: components in [-1, 1]
}
_XY_STEPS = 65535


class StoredFeaturesError(ValueError):
    """Bytes that are not a stored-features record of a version this code reads (torn, corrupt, newer)."""


@dataclass(frozen=True)
class StoredFeatures:
    """A reference's local features as stored: uint16 fractional positions, uint8 descriptors. Kept
    quantised in memory too (132 bytes a RootSIFT keypoint instead of 520), converted only when matched."""

    kind: str
    width: int  # pixels of the image the extractor saw (positions come back in these)
    height: int
    xy_q: np.ndarray  # (N, 2) uint16: x / width and y / height, times 65535
    desc_q: np.ndarray  # (N, D) uint8

    def __len__(self) -> int:
        return len(self.xy_q)

    @property
    def xy_px(self) -> np.ndarray:
        """(N, 2) float32 positions in pixels of the extractor's image."""
        return self.xy_q.astype(np.float32) * (np.array([self.width, self.height], np.float32) / _XY_STEPS)

    @property
    def descriptors(self) -> np.ndarray:
        """(N, D) float32 descriptors on the extractor's own scale (``dequantise``)."""
        return dequantise(self.desc_q, self.kind)


def quantise(descriptors: np.ndarray, kind: str) -> np.ndarray:
    scale, offset = QUANTISATION[kind]
    q = np.rint((np.asarray(descriptors, np.float32) + offset) * scale)
    return np.clip(q, 0, 255).astype(np.uint8)


def dequantise(desc_q: np.ndarray, kind: str) -> np.ndarray:
    scale, offset = QUANTISATION[kind]
    return desc_q.astype(np.float32) * np.float32(1.0 / scale) - np.float32(offset)


def from_pixels(
    xy_px: np.ndarray, descriptors: np.ndarray, width: int, height: int, kind: str = "rootsift"
) -> StoredFeatures:
    """Quantise features whose positions are pixels of a ``width`` x ``height`` image (the extractor's)."""
    if kind not in KINDS:
        raise ValueError(f"unknown descriptor kind {kind!r}; one of {', '.join(KINDS)}")
    if not (0 < width <= 65535 and 0 < height <= 65535):
        raise ValueError(f"image size {width}x{height} px is out of range")
    xy = np.asarray(xy_px, np.float64).reshape(-1, 2) / np.array([width, height], np.float64)
    xy_q = np.clip(np.rint(xy * _XY_STEPS), 0, _XY_STEPS).astype(np.uint16)
    d = np.asarray(descriptors, np.float32)
    if d.ndim != 2 or len(d) != len(xy_q):
        raise ValueError(f"{len(xy_q)} positions but descriptors of shape {d.shape}")
    return StoredFeatures(kind, int(width), int(height), xy_q, quantise(d, kind))


def encode(features: StoredFeatures) -> bytes:
    """The stored bytes: ``HEADER`` then the positions and the descriptors, C order."""
    xy = np.ascontiguousarray(features.xy_q, "<u2")
    d = np.ascontiguousarray(features.desc_q, np.uint8)
    body = xy.tobytes() + d.tobytes()
    scale, offset = QUANTISATION[features.kind]
    dim = d.shape[1] if d.ndim == 2 else 0
    head = HEADER.pack(
        MAGIC, VERSION, KINDS[features.kind], features.width, features.height, dim, len(xy), scale, offset,
        zlib.crc32(body),
    )  # fmt: skip
    return head + body


def decode(data: bytes) -> StoredFeatures:
    """The features back from ``encode``'s bytes; ``StoredFeaturesError`` for anything else."""
    if len(data) < HEADER.size:
        raise StoredFeaturesError(f"{len(data)} bytes: shorter than the {HEADER.size}-byte header")
    magic, version, kind, width, height, dim, n, scale, offset, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise StoredFeaturesError("not a stored-features record (bad magic)")
    if version != VERSION:
        raise StoredFeaturesError(f"stored-features version {version}; this code reads version {VERSION}")
    if kind not in _KIND_NAMES:
        raise StoredFeaturesError(f"unknown descriptor kind {kind}")
    name = _KIND_NAMES[kind]
    if (scale, offset) != QUANTISATION[name]:
        raise StoredFeaturesError(f"{name} stored with scale {scale}, offset {offset}: not this code's")
    body = memoryview(data)[HEADER.size :]
    if len(body) != n * (4 + dim):
        raise StoredFeaturesError(
            f"{len(body)} bytes of arrays; {n} keypoints of {dim} dimensions need {n * (4 + dim)}"
        )
    if zlib.crc32(body) != crc:
        raise StoredFeaturesError("checksum mismatch: the record is corrupt")
    xy = np.frombuffer(body, "<u2", count=2 * n).reshape(n, 2).astype(np.uint16)
    desc = np.frombuffer(body, np.uint8, offset=4 * n).reshape(n, dim)
    return StoredFeatures(name, width, height, xy, desc)


def stored_size(n_keypoints: int, dim: int = 128) -> int:
    """Bytes of a record of ``n_keypoints`` (what a reference costs on disk, before the file system's block)."""
    return HEADER.size + n_keypoints * (4 + dim)
