"""Dataset manifests: CSV with ``image,lat,lon,split[,group]``, image paths relative to the manifest.

``group`` ties the rows of one capture (a photo and its crops): a query is never matched against its own
group, and a group always sits on one side of a split, otherwise a crop of the query in the database
would make recognition trivially easy.
"""

from __future__ import annotations

import csv
import os
import random
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
            rows.append(Row(image, lat, lon, split, group))
    return rows


def write_manifest(path: Path, rows: list[Row]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "lat", "lon", "split", "group"])
        for r in rows:
            w.writerow(
                [os.path.relpath(r.image, path.parent.resolve()), f"{r.lat:.8f}", f"{r.lon:.8f}", r.split, r.group]
            )


def penn_campus_rows(
    source: Path, seed: int = 0, query_fraction: float = 0.2, train_fraction: float = 0.2
) -> list[Row]:
    """A seeded split of penn-campus-gps by capture: each of the 81 photos with its five crops goes to
    one side (db, query or train); the crops of the 19 photos without originals go to db."""
    rows = []
    with (source / "index.csv").open(newline="") as f:
        records = list(csv.DictReader(f))
    with_photo = sorted(r["photo_id"] for r in records if r["photo"])
    rng = random.Random(seed)
    rng.shuffle(with_photo)
    n_query = round(len(with_photo) * query_fraction)
    n_train = round(len(with_photo) * train_fraction)
    side = {pid: "query" for pid in with_photo[:n_query]}
    side |= {pid: "train" for pid in with_photo[n_query : n_query + n_train]}
    for r in records:
        pid = r["photo_id"]
        split = side.get(pid, "db")
        lat, lon = float(r["lat"]), float(r["lon"])
        images = ([r["photo"]] if r["photo"] else []) + [c for c in r["crops"].split(";") if c]
        rows += [Row((source / img).resolve(), lat, lon, split, pid) for img in images]
    return rows


def write_shared_manifests(shared_data: Path, out_dir: Path, seed: int = 0) -> list[Path]:
    """Manifests for the sets in ../shared/data that have positions (sf-streetview-toy has none)."""
    written = []
    penn = shared_data / "penn-campus-gps"
    if (penn / "index.csv").exists():
        path = out_dir / "penn-campus-gps.csv"
        write_manifest(path, penn_campus_rows(penn, seed))
        written.append(path)
    return written
