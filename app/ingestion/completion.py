"""The queue's consumer side: pending rows encoded (on this process's threads) and completed, their
thumbnails and stored local features kept beside their images before the rows say they are done. Every
encoder of the write path (the worker, the bulk engines, a re-fit's re-encoding) completes through
``complete``, the one place that records a batch."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from app.ingestion.encoding.items import Encoded, EncodeItem, encode_item
from app.ingestion.thumbnails import keep_thumbnail
from app.storage.feature_files import FeatureFiles, profile_root
from app.usecases.service import GeolocService


def encode_batch(service: GeolocService, batch: Sequence[tuple[int, Path]], workers: int = 1) -> list[Encoded]:
    items = [EncodeItem(i, p, thumbnail_px=service.thumbnail_px) for i, p in batch]
    if workers <= 1 or len(items) <= 1:
        return [encode_item(service.pipeline, service.limits, item) for item in items]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda item: encode_item(service.pipeline, service.limits, item), items))


def complete(service: GeolocService, results: Sequence[Encoded]) -> list[int]:
    """Record a batch in one transaction (storage failures stay pending) and bring the index up to date.
    Results made by a pipeline the data dir no longer uses (a re-fit switched while they were encoded)
    are not recorded: their rows stay pending, and this process loads the new generation before
    returning, so the next batch is encoded by it."""
    kept = _keep_thumbnails(service, results)  # before the rows: a finished job's thumbnail is there
    stored = _keep_stored_features(service, results)  # before the rows too: an indexed row can be verified
    by_pipeline: dict[str | None, list] = {}
    for r in results:
        if not r.retry:
            by_pipeline.setdefault(r.fingerprint, []).append((r.ref_id, r.float_code, r.binary_code, r.error))
    done: list[int] = []
    stale = False
    for fingerprint, final in by_pipeline.items():
        recorded = service.store.complete(final, fingerprint)
        stale |= fingerprint is not None and not recorded and any(e is None for *_, e in final)
        done += recorded
    for ref_id, path in kept.items():  # deleted meanwhile, or left pending: no thumbnail outlives its row
        if ref_id not in done:
            path.unlink(missing_ok=True)
    for ref_id, path in stored.items():
        if ref_id not in done:
            path.unlink(missing_ok=True)
    if stale and service.store.get_meta("fingerprint") != service.pipeline.fingerprint:
        service.collection.refresh_generation(wait=True)
    service.collection.catch_up()
    return done


def _keep_thumbnails(service: GeolocService, results: Sequence[Encoded]) -> dict[int, Path]:
    """Keep the thumbnails the encoder made (``app.ingestion.thumbnails``); returns where, by reference id."""
    kept = {}
    for r in results:
        if r.thumbnail is not None and r.error is None and not r.retry:
            image = service.store.image_path(r.ref_id)
            if image is not None and (path := keep_thumbnail(image, service.thumbnail_px, r.thumbnail)):
                kept[r.ref_id] = path
    return kept


def stored_features_files(service: GeolocService) -> FeatureFiles | None:
    """The configuration's stored local-features files (``data_dir/features/<profile>``), or None when
    it stores none."""
    profile = service.pipeline.config.stored_features
    return None if profile is None else FeatureFiles(profile_root(service.store.data_dir, profile))


def _keep_stored_features(service: GeolocService, results: Sequence[Encoded]) -> dict[int, Path]:
    """Write the stored local features the encoder made, one file per image (keyed by its sha256, as its
    image file is named); returns where, by reference id."""
    files = stored_features_files(service)
    kept: dict[int, Path] = {}
    if files is None:
        return kept
    for r in results:
        if r.stored_features is not None and r.error is None and not r.retry:
            image = service.store.image_path(r.ref_id)
            if image is not None:
                kept[r.ref_id] = files.write(image.name.split(".", 1)[0], r.stored_features)
    return kept
