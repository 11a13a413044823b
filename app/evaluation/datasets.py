"""The data sets in ../shared as manifests (``app.manifests``): penn-campus-gps's rows with their splits and
groups, and the manifests `geoloc datasets` writes."""

from __future__ import annotations

import csv
import random
from pathlib import Path

from app.manifests import Row, write_manifest


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
