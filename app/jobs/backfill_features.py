"""``geoloc features backfill``: make the stored local features a data dir's indexed references lack.

Why: the encode path writes a reference's file as it encodes it, but a data dir can hold references without
one (ingested by a version that stored none, a file lost, a crash between the file and its row); those are
found but never verified. This walks the references in id order, a page at a time (never all of them in
memory), and makes each missing file from the stored image with the same decode and extractor the encode
path uses, so a back-filled file is the file ingestion would have written.

Resumable by construction: a file that exists is done, so an interrupted run started again skips what the
last one wrote and goes on. Safe beside a running service: files are written atomically, and a reference
deleted meanwhile has its file removed again (its image's removal may have run before the file existed).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits
from app.engine.pipeline import Pipeline
from app.engine.stored_features import encode
from app.errors import OperationRefused
from app.storage.feature_files import FeatureFiles, profile_root
from app.storage.store import ReferenceStore

PAGE = 500


@dataclass
class BackfillReport:
    profile: str
    seen: int = 0  # indexed references looked at
    present: int = 0  # already had their file (done by ingestion or an earlier run)
    written: int = 0
    failed: int = 0  # image missing or undecodable: left without a file (``geoloc check`` names them)


def backfill_stored_features(
    data_dir: Path,
    models_dir: Path,
    config: str | None = None,
    limits: ImageLimits | None = None,
    say: Callable[[str], None] = print,
    every: int = PAGE,
) -> BackfillReport:
    """Write the missing files of the data dir's configuration's profile; ``say`` gets a progress line every
    ``every`` references and at the end."""
    store = ReferenceStore(data_dir, read_only=True)  # rows are only read; files are written beside them
    try:
        name = store.get_meta("config") or config or DEFAULT_CONFIG
        cfg = get_config(name)
        if cfg.stored_features is None:
            raise OperationRefused(
                f"configuration {name} stores no local features: nothing to back-fill (a configuration that "
                "stores them, such as lite2-hybrid-384-sv, writes them as it encodes)"
            )
        pipeline = Pipeline(cfg, models_dir=models_dir)  # only its decode and stored extractor are used
        extractor = pipeline.stored_extractor
        extractor.load()
        files = FeatureFiles(profile_root(store.data_dir, cfg.stored_features))
        limits = (limits or ImageLimits()).stored()
        report = BackfillReport(cfg.stored_features)
        after = None
        while True:
            page = store.page(after=after, limit=PAGE)
            for ref in page.items:
                if ref.status != "indexed":
                    continue
                report.seen += 1
                if files.exists(ref.sha256):
                    report.present += 1
                else:
                    _make_one(store, pipeline, files, ref.id, ref.sha256, limits, report)
                if report.seen % every == 0:
                    say(_progress(report))
            if page.next_after is None:
                break
            after = page.next_after
        say(_progress(report) + " (done)")
        return report
    finally:
        store.close()


def _make_one(
    store: ReferenceStore,
    pipeline: Pipeline,
    files: FeatureFiles,
    ref_id: int,
    sha: str,
    limits: ImageLimits,
    report: BackfillReport,
) -> None:
    path = store.image_path(ref_id)
    try:
        data = path.read_bytes() if path is not None else None
        if data is None:
            raise FileNotFoundError(ref_id)
        record = pipeline.stored_extractor.record(pipeline.decode(data, limits).rgb)
    except (OSError, GeolocError):
        report.failed += 1
        return
    files.write(sha, encode(record))
    if not store.named_files([path.name]):  # deleted meanwhile: no file outlives its image
        files.delete(sha)
        return
    report.written += 1


def _progress(r: BackfillReport) -> str:
    return (
        f"features backfill ({r.profile}): {r.seen} indexed references, {r.written} written, "
        f"{r.present} already there, {r.failed} failed"
    )
