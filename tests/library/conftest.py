"""The library tests' fixtures: the served default pipeline (fitted on penn-campus-gps, calibrated), a
library folder of real photos (penn's photos/, the 16 query-split photos with their GPS removed by
exiftool, sf-streetview-toy photos from elsewhere, a text file named .jpg and a photo with broken EXIF),
and penn's 65 geotagged photos as a collection, ingested once per session.

Why the shared collection: each library test scans its own copy of the library (they write sidecars, EXIF
and decisions), but encoding the same 65 references once per test was most of their cost on a two-core
CI machine. A test copies the session's data dir; its scan finds every reference already there (the same
bytes: a duplicate, never encoded again) and locates the others as a first scan does."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.evaluation.datasets import penn_campus_rows
from app.manifests import write_manifest
from bench.library_time_prior import penn_library
from tests.conftest import PENN, REPO, SHARED, built_once

SF = SHARED / "data" / "sf-streetview-toy" / "queries"
ELSEWHERE = ("q1.jpg", "q2.jpg")  # San Francisco: no reference there


def exiftool_ready() -> None:
    if shutil.which("exiftool") is None:
        pytest.fail("exiftool is missing: `make test` installs Debian's libimage-exiftool-perl")


@pytest.fixture(scope="session")
def query_truth() -> dict[str, tuple[float, float]]:
    """The 16 query-split photos of penn (the shared manifest's seed): name -> true position."""
    return {
        r.image.name: (r.lat, r.lon)
        for r in penn_campus_rows(PENN)
        if r.split == "query" and r.image.parent.name == "photos"
    }


@pytest.fixture(scope="session")
def library_models(tmp_path_factory, models_dir, lite2, xfeat) -> Path:
    """The default configuration, fitted as `make fit` fits it: the checkout's when `make fit` ran, else
    fitted here once for the run (about two minutes; one fit shared by the xdist workers, ``built_once``)
    in a models dir beside the session's models (linked)."""
    if (REPO / "models" / "pipelines" / DEFAULT_CONFIG / "pipeline.json").exists():
        return REPO / "models"

    def build(models: Path) -> None:
        for f in models_dir.iterdir():
            if f.is_file():
                (models / f.name).symlink_to(f)
        manifest = models.parent / f"{models.name}-penn-campus-gps.csv"
        write_manifest(manifest, penn_campus_rows(PENN))
        args = ["fit", "--manifest", str(manifest), "--config", DEFAULT_CONFIG, "--models-dir", str(models)]
        done = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stdout + done.stderr

    return built_once(tmp_path_factory, "library-models", build)


@pytest.fixture(scope="session")
def penn_collection(tmp_path_factory, library_models, query_truth) -> Path:
    """A data dir holding penn's 65 geotagged photos (the library's references), made by `geoloc library
    scan` of a folder of them alone (nothing to locate), once for the run (shared by the xdist workers,
    ``built_once``). Copy it (``copy_collection``), never write it."""

    def build(base: Path) -> None:
        refs = base / "refs"
        refs.mkdir()
        for src in sorted((PENN / "photos").glob("*.jpg")):
            if src.name not in query_truth:
                shutil.copyfile(src, refs / src.name)
        args = ["library", "scan", str(refs), "--data-dir", str(base / "data"), "--models-dir",
                str(library_models), "--config", DEFAULT_CONFIG]  # fmt: skip
        done = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=900)
        assert done.returncode == 0 and "65 references" in done.stdout, done.stdout + done.stderr

    return built_once(tmp_path_factory, "penn-collection", build) / "data"


def copy_collection(collection: Path, dest: Path) -> Path:
    """The session's collection as a new data dir (without its library journal: the test's own scans)."""
    shutil.copytree(collection, dest, ignore=shutil.ignore_patterns("library.sqlite*", "library-backups"))
    return dest


def make_library(folder: Path, truth: dict[str, tuple[float, float]]) -> Path:
    """penn's photos with the query photos' GPS removed, two photos from elsewhere, and two bad files."""
    exiftool_ready()
    penn_library(folder, PENN, truth, [SF / n for n in ELSEWHERE])
    (folder / "notes.jpg").write_text("not a photo")  # a file that is not an image
    data = bytearray((PENN / "photos" / "img_00001.jpg").read_bytes())
    at = data.find(b"Exif\x00\x00") + 6
    data[at : at + 400] = bytes((k * 37) & 0xFF for k in range(400))  # the EXIF block garbled
    (folder / "broken-exif.jpg").write_bytes(bytes(data))
    return folder
