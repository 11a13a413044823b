"""A library given as a manifest (image,lat,lon,split): its db rows are the collection at the manifest's
positions (crops without EXIF included), its query rows are located whatever GPS their EXIF holds."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.evaluation.datasets import penn_campus_rows
from app.manifests import Row, write_manifest
from tests.conftest import PENN

#: A whole library scanned with the fitted default pipeline: make test, not make test-quick.
pytestmark = pytest.mark.library


def test_a_manifest_library(tmp_path, library_models):
    rows = penn_campus_rows(PENN)
    queries = [r for r in rows if r.split == "query" and r.image.parent.name == "photos"][:3]
    crops = [r for r in rows if r.group == queries[0].group and r.image.parent.name == "crops"][:2]
    db = [r for r in rows if r.split == "db" and r.image.parent.name == "photos"][:20]
    db += [r for r in rows if r.split == "db" and r.image.parent.name == "crops"][:5]  # no EXIF: the CSV's position
    photos = tmp_path / "photos"
    photos.mkdir()
    copied = []
    for r in db + queries + crops:
        shutil.copyfile(r.image, photos / r.image.name)
        copied.append(Row(photos / r.image.name, r.lat, r.lon, r.split, r.group))
    manifest = tmp_path / "survey.csv"
    write_manifest(manifest, copied)
    args = ["library", "scan", str(manifest), "--data-dir", str(tmp_path / "data"), "--models-dir",
            str(library_models), "--config", DEFAULT_CONFIG, "--geojson", str(tmp_path / "out.geojson")]  # fmt: skip
    p = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "30 photos: 25 references (with a position), 5 located now" in p.stdout, p.stdout
    features = json.loads((tmp_path / "out.geojson").read_text())["features"]
    assert sorted(Path(f["properties"]["file"]).name for f in features) == sorted(r.image.name for r in queries + crops)

    # Resumable: a run that dies after two photos leaves them journalled; the next run locates the rest only.
    from app.library.scan import ScanOptions, scan_library
    from app.storage.library import LibraryJournal
    from app.usecases.service import GeolocService

    class Dies:
        def __init__(self, total: int, desc: str):
            self.n = 0

        def update(self, n: int) -> None:
            self.n += n
            if self.n == 2:
                raise KeyboardInterrupt

        def close(self) -> None:
            pass

    service = GeolocService.open(tmp_path / "data", library_models, DEFAULT_CONFIG)
    journal = LibraryJournal(tmp_path / "journal")
    with pytest.raises(KeyboardInterrupt):
        scan_library(service, manifest, ScanOptions(workers=1), journal, progress=Dies)
    sid = journal.scan_id_of(manifest)
    assert journal.scan(sid)["state"] == "failed" and len(journal.photos(sid)) == 2
    again = scan_library(service, manifest, ScanOptions(workers=1), journal)
    assert (again.unchanged, again.located) == (2, 3)
    journal.close()
