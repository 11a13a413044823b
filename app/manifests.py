"""The manifest format: a CSV with ``image,lat,lon,split[,group][,sequence,time]``, image paths relative to
the manifest.

``group`` ties the rows of one capture (a photo and its crops): a query is never matched against its own
group, and a group always sits on one side of a split, otherwise a crop of the query in the database
would make recognition trivially easy. Read by every face that takes a manifest (fit, eval, ingest, the
library); the data sets that write such files are ``app.evaluation.datasets``.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

from app.engine.geo import valid_position

SPLITS = ("db", "query", "train")


class ManifestError(ValueError):
    pass


@dataclass(frozen=True)
class Row:
    image: Path  # absolute
    lat: float
    lon: float
    split: str
    group: str
    #: Query rows of one walk, drive or video share a ``sequence`` (``geoloc eval --sequence-window``), in
    #: ``time`` order (ISO 8601) where given, else in row order. Optional columns; None when absent.
    sequence: str | None = None
    time: str | None = None


def read_manifest(path: Path) -> list[Row]:
    path = Path(path)
    if not path.exists():
        raise ManifestError(f"manifest {path} does not exist")
    rows = []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = {"image", "lat", "lon", "split"} - set(reader.fieldnames or [])
        if missing:
            raise ManifestError(f"{path}: missing columns {sorted(missing)}; need image,lat,lon,split[,group]")
        for n, r in enumerate(reader, start=2):
            try:
                lat, lon = float(r["lat"]), float(r["lon"])
            except ValueError:
                raise ManifestError(f"{path}:{n}: lat/lon are not numbers") from None
            if not valid_position(lat, lon):
                raise ManifestError(f"{path}:{n}: position {lat},{lon} is out of range")
            split = r["split"].strip()
            if split not in SPLITS:
                raise ManifestError(f"{path}:{n}: split {split!r} is not one of {SPLITS}")
            image = (path.parent / r["image"]).resolve()
            group = (r.get("group") or "").strip() or r["image"]
            sequence = (r.get("sequence") or "").strip() or None
            time = (r.get("time") or "").strip() or None
            rows.append(Row(image, lat, lon, split, group, sequence, time))
    return rows


def write_manifest(path: Path, rows: list[Row]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        sequences = any(r.sequence is not None or r.time is not None for r in rows)
        w.writerow(["image", "lat", "lon", "split", "group"] + (["sequence", "time"] if sequences else []))
        for r in rows:
            w.writerow(
                [os.path.relpath(r.image, path.parent.resolve()), f"{r.lat:.8f}", f"{r.lon:.8f}", r.split, r.group]
                + ([r.sequence or "", r.time or ""] if sequences else [])
            )
