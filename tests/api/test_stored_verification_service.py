"""Stored local features through the service, on penn photos: with ``lite2-hybrid-384-sv`` the
worker writes one small file per reference at ingestion, /locate verifies the top candidates from those files
by default (a reference's own photo first, with many inliers; a far one with few), a candidate without a
file stays unverified, ``rerank=false`` is the global-only answer, a deleted reference's file goes with its
image, ``geoloc check`` names a reference whose file is missing and ``features backfill`` makes it again.
The default configuration stores none."""

from __future__ import annotations

import shutil

import pytest

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.geo import haversine_m
from app.manifests import read_manifest

CONFIG = "lite2-hybrid-384-sv"
BUDGET_BYTES = 64 * 1024


def test_the_default_configuration_stores_no_features():
    assert get_config(DEFAULT_CONFIG).stored_features is None
    assert get_config(CONFIG).stored_features == "xfeat-640-n900"
    # the same pipeline otherwise: only what is stored and how answers are verified differ
    differ = {k for k, v in get_config(CONFIG).model_dump().items() if v != get_config(DEFAULT_CONFIG).model_dump()[k]}
    assert differ == {"name", "description", "stored_features"}


@pytest.fixture()
def sv_models(tmp_path, models_dir, lite2, xfeat):
    """A models dir with the built models (Lite2's maps, XFeat) and no fitted pipeline."""
    d = tmp_path / "models"
    d.mkdir()
    for f in models_dir.glob("*.onnx"):
        shutil.copy(f, d / f.name)
    return d


def test_stored_features_written_verified_and_removed(sv_models, mini_manifest, tmp_path):
    from app.cli import fit
    from app.domain import LocateOptions, Upload
    from app.ingestion.worker import IngestWorker
    from app.storage.feature_files import FeatureFiles, profile_root
    from app.storage.sqlite import SqliteBackend
    from app.usecases.operations import check_data_dir
    from app.usecases.service import GeolocService

    fit(manifest=mini_manifest, config=CONFIG, models_dir=sv_models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    # The fit's calibration located every sampled reference verified from stored records too (without
    # --calibrate-rerank): the rule /locate's verified answers are judged by.
    from app.engine.calibration import Calibration
    from app.engine.pipeline import pipeline_dir

    calibration = Calibration.load(pipeline_dir(sv_models, CONFIG))
    report = calibration.report
    assert report["verified_from"] == "stored features (xfeat-640-n900)"
    assert report["verified_sampled"] == report["sampled"] > 0
    # The verified rule's own walks (the photos' EXIF times), each window located verified from stored records.
    walks = calibration.for_answer(True).report["sequence"]
    assert walks["walks"] == report["sequence"]["walks"] > 0 and walks["photos"] == report["sequence"]["photos"]
    data = tmp_path / "data"
    service = GeolocService.open(data, sv_models, CONFIG)
    photos = [r for r in read_manifest(mini_manifest) if r.split == "db" and r.image.parent.name == "photos"]
    accepted = service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in photos])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(photos)

    # One file per reference, written at ingestion, within the budget.
    files = FeatureFiles(profile_root(data, "xfeat-640-n900"))
    shas = {service.store.get(i).sha256: i for i in accepted.reference_ids}
    assert set(files.names()) == set(shas)
    sizes = [files.path(s).stat().st_size for s in shas]
    assert all(10_000 < n <= BUDGET_BYTES for n in sizes), sizes

    # Verified by default: the reference's own photo first with many inliers; references far away with few.
    q = 4
    own = accepted.reference_ids[q]
    answer = service.locate(photos[q].image.read_bytes(), LocateOptions(top_k=10))
    assert "rerank" in answer.timings_ms
    first = answer.candidates[0]
    assert first.reference_id == own and first.inliers is not None and first.inliers >= 100, first
    assert answer.verification[own].inliers == first.inliers
    # The query captures (not ingested): each candidate is verified until the answer is clear, and those over
    # 100 m away get at most a chance level of inliers (XFeat's: 12 at p90 on penn-photos-40), far below a
    # true match's.
    far = []
    for r in read_manifest(mini_manifest):
        if r.split == "query" and r.image.parent.name == "photos":
            other = service.locate(r.image.read_bytes(), LocateOptions(top_k=10))
            far += [
                c.inliers
                for c in other.candidates
                if c.inliers is not None and haversine_m(r.lat, r.lon, c.lat, c.lon) > 100
            ]
    assert len(far) >= 5 and max(far) <= 20, far

    # rerank=false: the global-only answer, no inliers anywhere.
    plain = service.locate(photos[q].image.read_bytes(), LocateOptions(top_k=10, rerank=False))
    assert "rerank" not in plain.timings_ms and not plain.verification
    assert all(c.inliers is None for c in plain.candidates)

    # A reference whose file is missing is found but unverified, and `geoloc check` names it.
    gone = accepted.reference_ids[q]
    gone_sha = service.store.get(gone).sha256
    saved = files.read(gone_sha)
    assert files.delete(gone_sha)
    answer = service.locate(photos[q].image.read_bytes(), LocateOptions(top_k=10))
    by_id = {c.reference_id: c for c in answer.candidates}
    assert gone in by_id and by_id[gone].inliers is None
    service.collection.write_snapshot()
    report = check_data_dir(data, sv_models, CONFIG, SqliteBackend(data))
    assert any("stored features file is missing" in p and str(gone) in p for p in report.problems), report.problems
    files.write(gone_sha, saved)
    report = check_data_dir(data, sv_models, CONFIG, SqliteBackend(data))
    assert not any("stored features" in p for p in report.problems)

    # A data dir whose references lack their files gets them back (the same bytes ingestion wrote), with
    # progress; a second run finds them all there (a file that exists is the resume marker).
    from app.ingestion.backfill import backfill_stored_features

    written = {s: files.read(s) for s in shas}
    lost = sorted(shas)[:3]
    for s in lost:
        files.delete(s)
    lines: list[str] = []
    report = backfill_stored_features(data, sv_models, say=lines.append, every=2)
    assert (report.seen, report.written, report.present, report.failed) == (len(shas), 3, len(shas) - 3, 0)
    assert {s: files.read(s) for s in shas} == written
    assert len(lines) == len(shas) // 2 + 1 and lines[-1].endswith("(done)"), lines
    again = backfill_stored_features(data, sv_models, say=lines.append)
    assert (again.written, again.present) == (0, len(shas))

    # Deleting a reference removes its file with its image.
    victim = accepted.reference_ids[2]
    victim_sha = service.store.get(victim).sha256
    assert service.delete(victim) == "removed"
    assert not files.exists(victim_sha)
    assert set(files.names()) == set(shas) - {victim_sha}

    # A re-fit re-encodes every reference through the same path and re-makes their files with the codes.
    from app.jobs.refit import RefitOptions, refit

    shutil.rmtree(profile_root(data, "xfeat-640-n900"))
    summary = refit(data, sv_models, RefitOptions(sample=9, svm_bank="none", seed=3), progress=False)
    assert summary.generation == 1
    assert {s: files.read(s) for s in files.names()} == {s: b for s, b in written.items() if s != victim_sha}
