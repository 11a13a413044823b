"""What `geoloc ingest SOURCE` reads: a folder of photos, a CSV of ``image,lat,lon[,...]`` rows, or a
dataset manifest (a CSV with a ``split`` column).

Why lazily: users bring 10^5-10^6 photos, so a source yields one ``SourceItem`` at a time (a path and the
metadata the source knows) and never lists everything in memory; ``count`` walks the source once more,
cheaply (names only), so that the progress bar can show an ETA. A row that cannot be used (a position out
of range) is yielded with its ``problem`` so the run reports it beside the bad files, instead of stopping.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from app.engine.geo import valid_position

#: File names a folder source reads (case-insensitive); other files (sidecars, notes) are not photos.
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".mpo", ".heic", ".heif"})
CSV_COLUMNS = ("image", "lat", "lon")
OPTIONAL_COLUMNS = ("heading", "captured_at", "label")


class SourceError(ValueError):
    """The source itself cannot be read (missing, not a folder or CSV, columns missing)."""


@dataclass(frozen=True)
class SourceItem:
    """One photo to ingest. ``lat``/``lon`` None: the position comes from the photo's EXIF GPS."""

    path: Path
    lat: float | None = None
    lon: float | None = None
    heading: float | None = None
    captured_at: str | None = None
    label: str | None = None
    problem: str | None = None  # why this row cannot be ingested (reported and skipped)


@dataclass(frozen=True)
class Source:
    """A source: ``kind`` is folder, csv or manifest (rows of ``split``); it is also each reference's
    ``source`` field, so a listing tells where references came from."""

    kind: str
    path: Path
    split: str | None = None
    #: The folder every file must stay in, links not followed (a library scan's folder); None: any file.
    within: Path | None = None

    @property
    def exif_heading(self) -> bool:
        """A folder has no other metadata than EXIF; CSV rows say the heading when they know it."""
        return self.kind == "folder"

    def items(self) -> Iterator[SourceItem]:
        if self.kind == "folder":
            return (SourceItem(p) for p in _walk(self.path))
        return _csv_items(self.path, self.split)

    def count(self) -> int:
        if self.kind == "folder":
            return sum(1 for _ in _walk(self.path))
        with self.path.open(newline="") as f:
            rows = csv.DictReader(f)
            if self.split is None:
                return sum(1 for _ in rows)
            return sum(1 for r in rows if (r.get("split") or "").strip() == self.split)


def open_source(path: Path | None, manifest: Path | None = None, split: str = "db") -> Source:
    """Tell what SOURCE is: a folder, a CSV with a ``split`` column (a manifest: only ``split``'s rows), or a
    CSV of ``image,lat,lon[,heading,captured_at,label]``. ``--manifest M`` is the older spelling of SOURCE."""
    if path is not None and manifest is not None:
        raise SourceError("give SOURCE or --manifest, not both")
    path = path if path is not None else manifest
    if path is None:
        raise SourceError("give SOURCE: a folder of photos or a CSV (image,lat,lon[,heading,captured_at,label])")
    path = Path(path).resolve()
    if path.is_dir():
        return Source("folder", path)
    if not path.is_file():
        raise SourceError(f"{path} does not exist")
    try:
        with path.open(newline="") as f:
            columns = [c.strip() for c in (next(csv.reader(f), None) or [])]
    except (OSError, UnicodeDecodeError) as e:
        raise SourceError(f"{path} is not a readable CSV ({e})") from None
    missing = [c for c in CSV_COLUMNS if c not in columns]
    if missing:
        raise SourceError(
            f"{path}: missing columns {missing}; a CSV source needs image,lat,lon[,heading,captured_at,label] "
            "(image paths relative to the CSV), or give a folder of photos"
        )
    if "split" in columns:
        return Source("manifest", path, split)
    return Source("csv", path)


def _walk(root: Path) -> Iterator[Path]:
    """Photos under ``root``, recursively, in a stable order (sorted names); hidden files are not photos."""
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if not name.startswith(".") and os.path.splitext(name)[1].lower() in IMAGE_SUFFIXES:
                yield Path(folder) / name


def _csv_items(path: Path, split: str | None) -> Iterator[SourceItem]:
    with path.open(newline="") as f:
        for n, row in enumerate(csv.DictReader(f), start=2):
            row = {(k or "").strip(): (v or "").strip() for k, v in row.items()}
            if split is not None and row.get("split") != split:
                continue
            yield _row_item(path, n, row, manifest=split is not None)


def _row_item(path: Path, n: int, row: dict[str, str], manifest: bool) -> SourceItem:
    image = (path.parent / row["image"]).resolve() if row["image"] else path.parent
    where = f"{path.name} line {n}"
    if not row["image"]:
        return SourceItem(image, problem=f"{where}: the image column is empty")
    try:
        lat, lon = float(row["lat"]), float(row["lon"])
    except ValueError:
        return SourceItem(image, problem=f"{where}: lat/lon {row['lat']!r},{row['lon']!r} are not numbers")
    if not valid_position(lat, lon):
        return SourceItem(image, problem=f"{where}: position {lat},{lon} is out of range")
    heading = None
    if row.get("heading"):
        try:
            heading = float(row["heading"])
        except ValueError:
            heading = math.nan
        if not (math.isfinite(heading) and 0 <= heading < 360):
            return SourceItem(image, problem=f"{where}: heading {row['heading']!r} is not a number in [0, 360)")
    label = image.name if manifest else (row.get("label") or None)
    return SourceItem(image, lat, lon, heading, row.get("captured_at") or None, label)
