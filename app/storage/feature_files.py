"""Stored local features on disk: one small file per reference image, read per candidate, never all in RAM.

Layout: ``<root>/<sha[:3]>/<sha>.lf``, where ``sha`` is the sha256 of the reference's image (the name its
image file has: ``app.storage.files``) and the content is ``app.engine.stored_features.encode``'s bytes.

Why files keyed by the image's sha256: features are a function of the image's bytes and the extractor, as
a thumbnail is, so they follow the image's life the same way (made at encoding, removed when the last row
naming the image goes, deduplicated when two references share an image), and one read by name needs no
database row. Why one file per image rather than a packed array: verification reads only its K candidates
(10 per request), a deletion is one unlink, a crash tears at most the file being written (written to a
temporary name, then renamed), and a back-fill can resume by asking which names exist.

Why 4,096 folders (three hex digits): at 10^7 references that is about 2,400 files a folder (ext4 and XFS
index directories; listing one stays cheap), at 10^5 about 24, and the folders themselves cost 16 MB.

Where they live at scale: the form chosen by measurement is XFeat at 640 px, 900 keypoints, 64-d uint8
descriptors and uint16 positions: 61,224 bytes (59.8 KB) a reference, photo or crop (docs/benchmarks.md,
"Stored local features for verification"; today's RootSIFT at 800 px, 1,500 keypoints, would take 193 KB).
So 10^6 references take 61 GB and 10^7 take 612 GB of disk, beside the images (typically 0.5-3 MB each,
so a few % more), never in memory: a request reads its K candidates' files (K x 60 KB, one random read
each, from the page cache or an SSD).

``root`` is chosen by the caller: the data dir's ``features/<profile>`` for one host; on PostgreSQL, a
folder beside the shared images (``GEOLOC_IMAGES_DIR``), since every host verifies.
``profile`` names the extractor's settings, so a re-fit that changes them writes a new folder beside the
old one and switches, never mixing two extractors' features.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

from app.engine.stored_features import StoredFeaturesError, decode
from app.permissions import private_dir
from app.storage.files import write_image_file

SUFFIX = ".lf"
#: The data dir's folder of profiles: ``<data_dir>/features/<profile>/`` is one ``FeatureFiles`` root.
FEATURES = "features"
_SHA256 = re.compile(r"[0-9a-f]{64}")


def profile_root(data_dir: Path, profile: str) -> Path:
    """Where a profile's files live in a data dir (one folder per profile: two extractors never mix)."""
    return Path(data_dir) / FEATURES / profile


def damage(data: bytes) -> str | None:
    """Why ``data`` is not a stored-features record this code reads (emptied, truncated, bit-flipped: its
    header, sizes and CRC checked as a request's reader checks them), or None when it is one. A damaged
    file exists, so asking only whether it exists would call it done and leave every request to meet it."""
    try:
        decode(data)
    except StoredFeaturesError as e:
        return str(e)
    return None


def delete_everywhere(data_dir: Path, sha: str) -> None:
    """Remove an image's stored features under every profile (with the image: a removal does not know which
    profile the data dir used when the image was encoded; there are a handful of folders, no scan)."""
    folder = Path(data_dir) / FEATURES
    if _SHA256.fullmatch(sha) and folder.is_dir():
        for profile in folder.iterdir():
            if profile.is_dir():
                FeatureFiles(profile).delete(sha)


class FeatureFiles:
    """The stored-features files under ``root`` (made, 0700, on the first write)."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def path(self, sha: str) -> Path:
        if not _SHA256.fullmatch(sha):
            raise ValueError(f"not a sha256 hex digest: {sha!r}")
        return self.root / sha[:3] / f"{sha}{SUFFIX}"

    def write(self, sha: str, data: bytes, sync: bool = False) -> Path:
        """Write ``data`` under a temporary name, then rename: a reader sees the old file or the new one,
        never half of one. ``sync``: flush it before the rename (a batch may instead flush its file system
        once before committing its rows, as the images do)."""
        path = self.path(sha)
        private_dir(self.root, parents=True)
        private_dir(path.parent)
        write_image_file(path, data, sync)  # the images' own atomic write: temporary name, then rename
        return path

    def read(self, sha: str) -> bytes | None:
        """The file's bytes, or None when there is none (not made yet: the back-fill's work)."""
        try:
            return self.path(sha).read_bytes()
        except FileNotFoundError:
            return None

    def read_many(self, shas: Iterable[str]) -> dict[str, bytes]:
        """The files there are among ``shas`` (a request's candidates): one read each, none kept."""
        out = {}
        for sha in shas:
            data = self.read(sha)
            if data is not None:
                out[sha] = data
        return out

    def exists(self, sha: str) -> bool:
        return self.path(sha).is_file()

    def delete(self, sha: str) -> bool:
        """Remove the file; False when there was none. Its (possibly empty) folder stays: another writer
        may be about to use it, and 4,096 empty folders cost nothing."""
        try:
            self.path(sha).unlink()
        except FileNotFoundError:
            return False
        return True

    def names(self) -> Iterator[str]:
        """Every stored sha256, folder by folder, without listing the whole tree at once (backup, check,
        back-fill). Temporary files of interrupted writes are not names."""
        if not self.root.is_dir():
            return
        for shard in sorted(os.scandir(self.root), key=lambda e: e.name):
            if not shard.is_dir() or len(shard.name) != 3:
                continue
            for entry in sorted(os.scandir(shard.path), key=lambda e: e.name):
                stem = entry.name[: -len(SUFFIX)]
                if entry.name.endswith(SUFFIX) and _SHA256.fullmatch(stem) and stem[:3] == shard.name:
                    yield stem

    def temporary_files(self) -> Iterator[Path]:
        """Leftovers of writes a crash interrupted (``.<name>.<pid>.<thread>.tmp``), for a sweep to remove."""
        if not self.root.is_dir():
            return
        for shard in os.scandir(self.root):
            if shard.is_dir():
                for entry in os.scandir(shard.path):
                    if entry.name.startswith(".") and entry.name.endswith(".tmp"):
                        yield Path(entry.path)
