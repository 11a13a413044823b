"""Re-fit and re-index (``geoloc refit``): a new generation of the pipeline and of every reference's codes.

Why generations: re-fitting changes every code, and a collection of 10^6 references takes hours to
re-encode, while the service must keep answering and accepting uploads. So the new pipeline is fitted on a
sample of the stored references and saved in the data dir (``pipelines/<config>-g<N>``, written to a
temporary folder and renamed); the new codes go into a table of their own (``next_codes``), one
transaction per batch, resumable; uploads indexed meanwhile by the old pipeline are picked up by the next
pass and deletions are ignored by the join; then one write transaction re-checks completeness and switches
pipeline, generation and fingerprint together, and makes the new codes the ones every reader sees by
renaming their table (constant time; they are copied into ``refs`` afterwards in short transactions).
Every process notices the new generation in its next catch-up (the same read as the index version) and
swaps pipeline and index together. An interrupted
re-index never switched: the old generation keeps serving, and a re-run continues where it stopped.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.imageio import ImageLimits
from app.engine.pipeline import Pipeline, PipelineSource
from app.errors import FitRefused, RefitError, StorageUnavailable
from app.ingestion.encoding.items import Encoded, EncodeItem
from app.ingestion.encoding.local import batched, make_engine
from app.ingestion.writer import write_snapshot_if_free
from app.storage.backend import StorageBackend
from app.storage.feature_files import FeatureFiles, profile_root
from app.storage.generations import ReindexTarget
from app.storage.sqlite import SqliteBackend
from app.storage.store import ReferenceStore
from app.usecases.collection import Collection, pipeline_source
from app.usecases.fitting import FitOptions, FitPhoto, bank_source, capture_group, check_bank_kind, fit_pipeline
from app.usecases.models import named_config

log = logging.getLogger("geoloc.reindex")

#: How many passes over the references may end with rows the storage could not read before giving up.
MAX_RETRY_PASSES = 5


@dataclass(frozen=True)
class RefitOptions:
    config: str | None = None  # None: the data dir's own configuration
    train_manifest: Path | None = None
    sample: int = 2000  # references the codebook, PCA and binariser are fitted on
    calibration_sample: int = 600  # of those, references located against the others to calibrate
    calibrate_rerank: bool = False  # also the rule for verified answers (some of those located with verification)
    svm_bank: str | None = None  # collection | train | none; None: train with a manifest, else collection
    bank_kind: str = "contrastive"
    seed: int = 0
    workers: int = 1  # extraction threads for the fit, encoding threads (or Ray workers) for the re-index
    batch: int = 32  # references re-encoded per transaction
    fresh: bool = False  # discard an interrupted re-index instead of continuing it
    radius_rate: float = 0.9  # the disc every answer states (Settings.radius_rate, Settings.max_radius_m)
    max_radius_m: float = 100.0


@dataclass(frozen=True)
class Target(ReindexTarget):
    """The generation being built (``ReindexTarget``, as the store records it) and where its pipeline is."""

    def source(self, data_dir: Path, models_dir: Path) -> PipelineSource:
        return pipeline_source(data_dir, models_dir, self.pipeline, self.config)


@dataclass
class RefitSummary:
    generation: int
    pipeline: str
    config: str
    fitted_on: int = 0
    reencoded: int = 0
    failed: int = 0
    resumed: bool = False
    bank: str = "none"
    calibration: str = ""
    seconds: dict[str, float] = field(default_factory=dict)


# -- fitting ----------------------------------------------------------------------------------------------
def fit_generation(
    store: ReferenceStore, models_dir: Path, options: RefitOptions, limits: ImageLimits | None = None
) -> tuple[Target, RefitSummary]:
    """Fit the next generation's pipeline (``app.usecases.fitting.fit_pipeline``) on a seeded sample of the stored
    references, read from their stored images (and its SVM bank, from them or from the training photos of
    ``options.train_manifest``), and save it in the data dir atomically; returns the target to re-index
    into."""
    generation, _, current = store.generation_state()
    name = options.config or current or DEFAULT_CONFIG
    cfg = named_config(name, models_dir)
    try:
        source = bank_source(cfg, options.svm_bank, train_photos_given=options.train_manifest is not None)
        check_bank_kind(options.bank_kind)
    except FitRefused as e:
        raise RefitError(str(e)) from None
    if source == "train" and options.train_manifest is None:
        raise RefitError("--svm-bank train needs --train-manifest (geotagged photos that are not references)")
    ids = store.indexed_ids()
    if len(ids) == 0:
        raise RefitError(f"{store.data_dir} has no indexed references to fit on")
    if options.sample < 2:
        raise RefitError("--sample must be at least 2")
    rng = np.random.default_rng(options.seed)
    picked = np.sort(rng.choice(ids, min(options.sample, len(ids)), replace=False))
    rows = store.get_many(picked.tolist())
    photos = [
        FitPhoto(
            store.image_path(i),
            lat=rows[i].lat,
            lon=rows[i].lon,
            group=capture_group(rows[i].lat, rows[i].lon),
            ref_id=i,
            sha256=rows[i].sha256,
            taken=rows[i].captured_at,
        )
        for i in (int(i) for i in picked)
        if i in rows
    ]
    if source != "none":  # the training photos train the bank (and join the calibration's auxiliary fits)
        photos += _train_photos(options.train_manifest)
    fit_options = FitOptions(
        bank=source,
        bank_kind=options.bank_kind,
        seed=options.seed,
        calibration_sample=options.calibration_sample,
        calibrate_verified=options.calibrate_rerank,
        limits=limits or ImageLimits(),
        workers=options.workers,
        skip_unreadable=True,  # a stored image gone or damaged: fit on the others (`geoloc check` reports it)
        radius_rate=options.radius_rate,
        max_radius_m=options.max_radius_m,
    )
    pipe = Pipeline(cfg, models_dir=Path(models_dir))
    try:
        fitted = fit_pipeline(pipe, photos, fit_options)
    except FitRefused as e:
        raise RefitError(str(e)) from None
    extra = {"refit_sample": len(fitted.refs), "svm_bank_source": source}
    target = save_generation(store.data_dir, pipe, generation + 1, extra)
    needs = pipe.calibration.confidence_note(len(ids))
    note = pipe.calibration.note + (f"; {needs}" if needs else "")
    summary = RefitSummary(
        target.generation, target.pipeline, name, fitted_on=len(fitted.refs), bank=source, calibration=note
    )
    summary.seconds.update(fitted.seconds)
    return target, summary


def _fitted_summary(pipeline: Pipeline, references: int) -> tuple[str, str]:
    """The SVM bank's source and the calibration's note of a saved generation, as ``fit_generation`` says
    them after fitting it: a re-run continuing an interrupted re-index reports the pipeline it switches
    to, not the defaults of a fit it never ran."""
    source = pipeline.manifest.get("svm_bank_source")
    bank = "none" if pipeline.bank is None else str(source or "fitted")
    needs = pipeline.calibration.confidence_note(references)
    return bank, pipeline.calibration.note + (f"; {needs}" if needs else "")


def _train_photos(manifest: Path | None) -> list[FitPhoto]:
    """The train rows of ``manifest`` (all its rows when it has none: a manifest of training photos only),
    as training photos that only the bank learns from."""
    from app.manifests import read_manifest

    if manifest is None:
        return []
    rows = read_manifest(manifest)
    rows = [r for r in rows if r.split == "train"] or rows
    return [
        FitPhoto(r.image, lat=r.lat, lon=r.lon, group=f"train:{r.group}", reference=False, in_fit=False) for r in rows
    ]


def save_generation(data_dir: Path, pipe: Pipeline, generation: int, extra: dict) -> Target:
    """Write ``pipelines/<config>-g<generation>`` in the data dir to a temporary folder, then rename: a folder
    named like a generation is always complete (a re-fit's, or the first start's generation 0)."""
    rel = f"pipelines/{pipe.config.name}-g{generation}"
    final = Path(data_dir) / rel
    tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    pipe.save(tmp, {**extra, "generation": generation})
    if final.exists():  # an interrupted re-fit's folder for the same number: never switched to, replace it
        shutil.rmtree(final)
    os.replace(tmp, final)
    return Target(generation, rel, pipe.config.name, pipe.fingerprint)


def resumable_target(store: ReferenceStore, models_dir: Path, config: str | None) -> Target | None:
    """The interrupted re-index recorded in the data dir, when it can continue (same configuration asked,
    its pipeline folder intact, and still the next generation)."""
    recorded = store.reindex_target()
    if recorded is None:
        return None
    target = Target(recorded.generation, recorded.pipeline, recorded.config, recorded.fingerprint)
    if (config and config != target.config) or target.generation != store.generation_state()[0] + 1:
        return None
    return target if (store.data_dir / target.pipeline / "pipeline.json").exists() else None


# -- re-encoding and switching ------------------------------------------------------------------------------
@dataclass
class _EngineHost:
    """What ``make_engine`` needs of a service: the pipeline to encode with (the new one) and the limits."""

    pipeline: Pipeline
    limits: ImageLimits


def reindex(
    store: ReferenceStore,
    target: Target,
    engine,
    batch: int = 32,
    limit: int | None = None,
    on_batch: Callable[[Sequence[Encoded]], None] | None = None,
) -> tuple[int, int]:
    """Encode every indexed reference without a code of ``target`` and record the codes, one transaction per
    batch, pass after pass until a pass finds nothing (uploads indexed meanwhile are found by the next one).
    ``limit``: stop after that many (an interrupted re-index, for tests). Returns (encoded, failed)."""
    done = failed = retry_passes = 0
    keep_stored = stored_features_keeper(store, target.config)
    while True:
        after, found, retried = 0, 0, 0
        while True:
            todo = store.reindex_todo(batch * 8, after)
            if not todo:
                break
            after = todo[-1][0]
            if limit is not None:
                todo = todo[: max(0, limit - done)]
            items = [EncodeItem(i, p) for i, p in todo]
            for results in batched(engine.run(items), batch):
                final = [(r.ref_id, r.float_code, r.binary_code, r.error) for r in results if not r.retry]
                retried += len(results) - len(final)
                keep_stored(results)  # before the codes, as the worker's complete keeps them
                if final:
                    store.put_next_codes(target, final)
                found += len(final)
                done += len(final)
                failed += sum(1 for r in results if r.error is not None)
                if on_batch is not None:
                    on_batch(results)
            if limit is not None and done >= limit:
                return done, failed
        if not found and not retried:
            return done, failed
        if retried and not found:
            retry_passes += 1
            if retry_passes >= MAX_RETRY_PASSES:
                raise StorageUnavailable(f"{retried} stored images could not be read: re-run `geoloc refit` later")
            time.sleep(1.0)


def stored_features_keeper(store: ReferenceStore, config: str) -> Callable[[Sequence[Encoded]], None]:
    """Writes the stored local features the re-encoding made (``Encoded.stored_features``) when the new
    generation's configuration stores them: a re-fit re-makes them with the codes. The files are keyed by
    the image and the folder by the profile, so one that the old generation wrote is replaced by the same
    extractor's bytes, and a profile the old generation lacked is complete by the switch."""
    profile = get_config(config).stored_features
    if profile is None:
        return lambda results: None
    files = FeatureFiles(profile_root(store.data_dir, profile))

    def keep(results: Sequence[Encoded]) -> None:
        for r in results:
            if r.stored_features is not None and r.error is None and not r.retry:
                image = store.image_path(r.ref_id)
                if image is not None:
                    files.write(image.name.split(".", 1)[0], r.stored_features)

    return keep


def switch(store: ReferenceStore, target: Target) -> int | None:
    """The switch transaction (``ReferenceStore.switch_generation``); None while references are missing."""
    return store.switch_generation(target)


def refit(
    data_dir: Path,
    models_dir: Path,
    options: RefitOptions,
    ray: str | None = None,
    limits: ImageLimits | None = None,
    progress: bool = True,
    backend: StorageBackend | None = None,
) -> RefitSummary:
    """The whole use case: fit (or continue an interrupted re-index), re-encode, switch, snapshot.
    ``backend``: the process's (``Settings.backend``; None: SQLite in ``data_dir``)."""
    limits = limits or ImageLimits()
    backend = backend or SqliteBackend(data_dir)
    store = ReferenceStore(data_dir, backend=backend)
    target = None if options.fresh else resumable_target(store, models_dir, options.config)
    if target is not None:
        summary = RefitSummary(target.generation, target.pipeline, target.config, resumed=True)
        log.info("continuing the interrupted re-index into generation %d", target.generation)
    else:
        target, summary = fit_generation(store, models_dir, options, limits)
    already = store.start_reindex(target)
    t0 = time.perf_counter()
    pipeline = target.source(data_dir, models_dir).load()
    if pipeline.fingerprint != target.fingerprint:
        store.abandon_reindex()
        raise RefitError(f"{target.pipeline} is not the pipeline its re-index started with: run `geoloc refit --fresh`")
    if summary.resumed:  # the fit ran in an earlier process: what it made is in the saved pipeline, not in hand
        summary.bank, summary.calibration = _fitted_summary(pipeline, store.count("indexed"))
    engine = make_engine(_EngineHost(pipeline, limits), ray=ray, workers=options.workers)  # type: ignore[arg-type]
    try:
        while True:
            with tqdm(
                total=already + store.reindex_missing(), initial=already, desc="re-encode", unit="img", disable=None
            ) as bar:
                n, failed = reindex(store, target, engine, options.batch, on_batch=lambda r: bar.update(len(r)))
            summary.reencoded += n
            summary.failed += failed
            t1 = time.perf_counter()
            switched = switch(store, target)
            summary.seconds["switch"] = time.perf_counter() - t1  # the one write transaction
            if switched is not None:
                break
            already = 0  # uploads indexed between the last pass and the switch: one more pass
    finally:
        engine.close()
    summary.seconds["reindex"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    while store.migrate_switched():  # the new codes into refs, a few thousand per short transaction
        pass
    summary.seconds["copy"] = time.perf_counter() - t1
    # With no server or worker holding the writer role, nothing writes snapshots here now: write the new
    # generation's one.
    write_snapshot_if_free(backend, lambda: Collection.open(data_dir, models_dir, target.config, backend=backend))
    store.close()
    return summary
