"""What the time prior and the runs of a library scan are worth: the penn-campus-gps photos as a library,
the 16 query-split photos with their GPS removed (exiftool), the 65 others keeping theirs; located without
the time prior, with it alone, and with it and each camera's runs read as walks (``app.library.joint``);
each answer scored against the true position.

    .venv/bin/python bench/library_time_prior.py [--config lite2-hybrid-384] [--json out.json]
    .venv/bin/python bench/library_time_prior.py --data-dir index [--no-anchors]

Without ``--data-dir`` the collection is the library's 65 geotagged photos (not the collection the pipeline
was calibrated on, so its answers carry no probabilities and the runs read nothing); ``--data-dir index``
locates against a copy of the demo collection `make demo` builds (calibrated; it holds the 65 already).
``--no-anchors``: the library is the 16 photos alone, none with GPS: runs of photos with no geotagged photo
near them in time, where the time prior has nothing to give.

Prints per mode: placed, confident, confident and within the stated radius of the truth (and within 25 m),
and what each answer rests on. ``penn_library`` is also the tests' library folder."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import tempfile
from pathlib import Path

from app.engine.geo import haversine_m
from app.manifests import read_manifest

REPO = Path(__file__).resolve().parents[1]


def query_photos(manifest: Path) -> dict[str, tuple[float, float]]:
    """The query split's photos (not their crops): file name -> true (lat, lon)."""
    return {
        r.image.name: (r.lat, r.lon)
        for r in read_manifest(manifest)
        if r.split == "query" and r.image.parent.name == "photos"
    }


def penn_library(dest: Path, penn: Path, truth: dict[str, tuple[float, float]], extra: list[Path] = ()) -> Path:
    """A copy of penn's photos/ in ``dest`` with GPS stripped (exiftool ``-gps:all=``) from the photos named
    in ``truth``; ``extra`` files are copied in beside them (photos from elsewhere, broken files)."""
    dest.mkdir(parents=True, exist_ok=True)
    for src in sorted((penn / "photos").glob("*.jpg")):
        shutil.copyfile(src, dest / src.name)
    stripped = [str(dest / name) for name in sorted(truth)]
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-gps:all=", *stripped], check=True)
    for src in extra:
        shutil.copyfile(src, dest / src.name)
    return dest


def score(results: list[dict], truth: dict[str, tuple[float, float]]) -> dict:
    """Placed, confident, and confident within the stated radius (and 25 m) of the truth; by basis."""
    out = {"photos": 0, "placed": 0, "placed_within_radius": 0, "confident": 0, "confident_within_radius": 0,
           "confident_within_25m": 0}  # fmt: skip
    basis: dict[str, int] = {}
    for r in results:
        name = Path(r["file"]).name
        if name not in truth:
            continue
        out["photos"] += 1
        if not r["placed"]:
            continue
        out["placed"] += 1
        basis[r["basis"]] = basis.get(r["basis"], 0) + 1
        d = float(haversine_m(r["lat"], r["lon"], *truth[name]))
        out["placed_within_radius"] += d <= r["radius_m"]
        if r["confident"]:
            out["confident"] += 1
            out["confident_within_radius"] += d <= r["radius_m"]
            out["confident_within_25m"] += d <= 25
    out["basis"] = basis
    return out


MODES = {  # name -> (time prior, runs)
    "without": (False, False),
    "time prior": (True, False),
    "time prior and runs": (True, True),
}


def main() -> None:
    from app.library.scan import ScanOptions, scan_library
    from app.settings import Settings
    from app.storage.library import LOCATED, LibraryJournal
    from app.usecases.service import GeolocService

    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=Settings().config)
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--manifest", type=Path, default=REPO / "data" / "manifests" / "penn-campus-gps.csv")
    ap.add_argument("--penn", type=Path, default=REPO.parent / "shared" / "data" / "penn-campus-gps")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rerank", action="store_true", help="geometric verification of the top candidates")
    ap.add_argument("--data-dir", type=Path, default=None, help="locate against a copy of this collection")
    ap.add_argument("--no-anchors", action="store_true", help="the 16 photos alone (against --data-dir)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    truth = query_photos(args.manifest)
    with tempfile.TemporaryDirectory() as tmp:
        folder = penn_library(Path(tmp) / "library", args.penn, truth)
        data = Path(tmp) / "data"
        if args.no_anchors:
            if args.data_dir is None:
                raise SystemExit("--no-anchors locates against a collection: give --data-dir (`make demo`: index)")
            for f in folder.iterdir():
                if f.name not in truth:
                    f.unlink()
        if args.data_dir is not None:
            shutil.copytree(args.data_dir, data, ignore=shutil.ignore_patterns("*.lock"))
        service = GeolocService.open(data, args.models_dir, args.config)
        report = {}
        for name, (prior, runs) in MODES.items():
            journal = LibraryJournal(Path(tmp) / f"journal-{name}")
            options = ScanOptions(workers=args.workers, time_prior=prior, runs=runs, rerank=args.rerank)
            scan_library(service, folder, options, journal)
            sid = journal.scan_id_of(folder)
            report[name] = score([r.result for r in journal.photos(sid, LOCATED)], truth)
            journal.close()
    print(json.dumps(report, indent=1))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
