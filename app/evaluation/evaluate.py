"""The evaluation protocol of method.md: Recall@N within d metres, estimate error, time per stage, bytes.

Every image is decoded and its features extracted once; each fold then fits the pipeline on its own db
and train rows, indexes the db rows in memory and queries the query rows through
``app.usecases.locate.locate_features``,
the function /locate calls. With ``folds`` > 1 the query role rotates over the non-train groups (a capture and its
crops move together), because on a set this small one query moves Recall@1 by points.
"""

from __future__ import annotations

import hashlib
import io
import json
import pickle
import statistics
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from app.domain import LocateOptions, RefInfo, Region
from app.engine.artifacts import atomic_write_bytes
from app.engine.calibration import Calibration, reliability
from app.engine.configs import PipelineConfig
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits
from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.pipeline import DECODE_OVERSAMPLE, Pipeline
from app.engine.progress import Progress
from app.engine.stored_features import StoredFeatures
from app.engine.stored_features import decode as decode_stored
from app.engine.stored_features import encode as encode_stored
from app.errors import ManifestCannotBeEvaluated
from app.evaluation.confidence_ranking import query_record, rank_confidence, ranking_lines
from app.evaluation.sequences import SequenceWindow, answer_in_windows
from app.manifests import Row, read_manifest
from app.usecases.extraction import Extracted, extract_batch
from app.usecases.fitting import EVAL_BANK_SOURCES, FitOptions, FitPhoto, fit_pipeline, near_ids
from app.usecases.locate import ESTIMATE_CANDIDATES, MIN_LOCAL_FEATURES, Excluding, locate_features
from app.usecases.stored_photos import PhotoStoredFeatures

RECALL_AT = (1, 5, 10, 20)


class EstimateErrors(BaseModel):
    """The fused estimate's error over the queries, and how often it was confident and then right."""

    median: float | None
    p90: float | None
    confident_fraction: float
    confident_within_radius: float | None
    all_within_radius: float | None


class WithoutRerank(BaseModel):
    """With ``rerank``: the same queries located without verification, and the time verification adds."""

    recall_at: dict[str, float]
    recall_at_per_fold: list[dict[str, float]]
    rerank_ms_median: float
    rerank_ms_p90: float


class BankSummary(BaseModel):
    selection: str
    kind: str | None
    source: str | None
    kept_fraction_median: float | None
    folds: list[dict]  # each fold's bank manifest entries, as the bank wrote them


class AnswerQuality(BaseModel):
    """How far the answers can be trusted: confident answers' precision (estimate within the
    radius) and coverage, and the Brier score and reliability of ``p_within_25m`` over the first candidates;
    ``absent``: the same queries with every reference within ``absent_radius_m`` of them removed."""

    coverage: float
    precision: float | None
    #: The confident estimates within twice the radius: how far off the "wrong" ones are (on penn they are
    #: mostly the same facade photographed from across a street or quad, 29-47 m away).
    precision_at_2x_radius: float | None = None
    #: Of the confident answers: the truth within the stated radius, overall and in the quartile with the
    #: weakest evidence; the median radius stated; the rate stated (None: the constant rule's radii).
    radius_coverage: float | None = None
    radius_coverage_weakest_quartile: float | None = None
    median_radius_m: float | None = None
    p90_radius_m: float | None = None
    radius_rate: float | None = None
    #: The share of queries with an estimate (``coverage``, by its plain name).
    estimate_share: float | None = None
    #: Of the no_match answers (present queries and simulated absent places): how many, and the share whose
    #: place was absent (no reference searched within ``no_match_absent_at_m`` of the truth).
    no_match_answers: int | None = None
    no_match_absent_share: float | None = None
    no_match_absent_at_m: float | None = None
    brier: float | None
    reliability: list[dict]
    reason_codes: dict[str, int]
    absent_radius_m: float | None = None
    absent_confident: float | None = None
    absent_mean_best_p: float | None = None
    absent_brier: float | None = None
    absent_reason_codes: dict[str, int] | None = None


class ConfidenceRankings(BaseModel):
    """How each confidence score ranks the present queries (``app.evaluation.confidence_ranking``): for the
    answers as served (``answers``: verified when the run verifies) and, in a verified run, the same queries'
    answers without verification (``without_verification``)."""

    answers: dict
    without_verification: dict | None = None


class EvalResult(BaseModel):
    """One evaluation run. Its JSON form (``model_dump``) is the report ``geoloc eval --out`` writes and
    docs/results.md is made from."""

    config: str
    manifest: str
    folds: int
    #: The one fold run (0-based; ``--fold``), None when every fold ran.
    fold: int | None = None
    n_db: int
    n_query: int
    radius_m: float
    mode: str
    rerank: bool
    region_radius_m: float | None
    recall_at: dict[str, float]
    recall_at_per_fold: list[dict[str, float]]
    without_rerank: WithoutRerank | None
    recall_curve: list[float]
    ms_per_query: dict[str, float]
    ms_per_query_note: str
    bytes_per_reference: float
    estimate_error_m: EstimateErrors
    svm_bank: BankSummary
    answers: AnswerQuality | None = None
    answers_per_fold: list[AnswerQuality] = []
    calibration_per_fold: list[dict] = []
    confidence_ranking: ConfidenceRankings | None = None
    config_definition: dict
    queries: list[dict]  # per query: image, group, fold, position, candidates, estimate (the report's rows)
    #: With ``--sequence-window``: ``recall_at`` and ``answers`` are the sequences'; these, the same photos
    #: answered alone; ``sequence``, the window, the motion bounds, per-fold recall and how many answers rest
    #: on the sequence.
    single_recall_at: dict[str, float] | None = None
    single_answers: AnswerQuality | None = None
    sequence: dict | None = None


def extract_cached(pipeline: Pipeline, rows: list[Row], cache_dir: Path | None, workers: int = 2) -> list[Extracted]:
    """Every row's features (``app.usecases.extraction.extract_batch``), with an optional on-disk cache keyed by the
    images and the extraction settings, so parameter sweeps that change only aggregation or codes skip the
    expensive part. Stage times of work done in parallel are inflated; the report says so."""

    def extract() -> list[Extracted]:
        progress = Progress(len(rows), desc="extract", every=max(1, len(rows) // 10))
        done = extract_batch(pipeline, [r.image for r in rows], workers=workers, progress=progress)
        return [e for e in done if e is not None]  # none is left out: an unreadable row raises

    if cache_dir is None:
        return extract()
    # The decode scale is part of the key: features of a pipeline-scale decode differ from a 1600 px one; and
    # so is the record's type (a cache of an older one would not load).
    decode = f"decode={pipeline.decode_sides}x{DECODE_OVERSAMPLE}"
    key = hashlib.sha256(
        (pipeline.config.extraction_key() + decode + "record=app.usecases.extraction.Extracted").encode()
    )
    for r in rows:
        st = r.image.stat()
        key.update(f"{r.image}:{st.st_size}:{st.st_mtime_ns}".encode())
    path = cache_dir / f"features-{key.hexdigest()[:20]}.pkl"
    if path.exists():
        with path.open("rb") as f:
            return pickle.load(f)
    extracted = extract()
    cache_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, pickle.dumps(extracted, protocol=pickle.HIGHEST_PROTOCOL))
    return extracted


def stored_cached(
    pipeline: Pipeline, rows: list[Row], cache_dir: Path | None
) -> list[tuple[StoredFeatures, PixelFeatures]]:
    """Every row's stored record and query features by the configuration's stored profile
    (``StoredExtractor.record_and_query`` on the pipeline's decode of the photo under the stored references'
    limits: the encode path's record), made once per photo and cached in ``cache_dir`` (one file per photo,
    keyed by the profile, the decode scale and the photo's path, size and time), so every fold, the
    calibration's held-out references and later runs read them instead of extracting again."""
    extractor = pipeline.stored_extractor
    limits = ImageLimits().stored()
    folder = None
    if cache_dir is not None:
        folder = cache_dir / f"stored-{extractor.profile.name}"
        folder.mkdir(parents=True, exist_ok=True)
    progress = Progress(len(rows), desc="stored features", every=max(1, len(rows) // 10))
    out = []
    for r in rows:
        path = None
        if folder is not None:
            st = r.image.stat()
            key = f"{extractor.profile.name}:decode={pipeline.decode_sides}x{DECODE_OVERSAMPLE}:"
            key += f"{r.image.resolve()}:{st.st_size}:{st.st_mtime_ns}"
            path = folder / f"{hashlib.sha256(key.encode()).hexdigest()[:24]}.npz"
        if path is not None and path.exists():
            with np.load(path) as z:
                made = (decode_stored(z["record"].tobytes()), PixelFeatures(z["xy"], z["desc"]))
        else:
            made = extractor.record_and_query(pipeline.decode(r.image.read_bytes(), limits).rgb)
            if path is not None:
                record = np.frombuffer(encode_stored(made[0]), np.uint8)
                buf = io.BytesIO()
                np.savez(buf, record=record, xy=made[1].xy, desc=made[1].descriptors)
                atomic_write_bytes(path, buf.getvalue())
        out.append(made)
        progress.update(1)
    progress.close()
    return out


def _hits(rows: list[Row], i: int, lat, lon, candidates, top_n: int, radius_m: float) -> list[bool]:
    """Recall@1..top_n of one query: is a candidate within ``radius_m`` among the first n."""
    ids_ = np.array([c.reference_id for c in candidates], np.int64)
    d = haversine_m(rows[i].lat, rows[i].lon, lat[ids_], lon[ids_]) if len(ids_) else np.zeros(0)
    return [bool(np.any(d[:n] <= radius_m)) for n in range(1, top_n + 1)]


class RowReferences:
    """The evaluation's references (one fold's database rows) as the core's ``ReferenceSource``."""

    def __init__(self, rows: list[Row], db_idx: list[int]):
        self.rows = rows
        self.db = np.array(db_idx, np.int64)
        self.lat = np.array([rows[i].lat for i in db_idx])
        self.lon = np.array([rows[i].lon for i in db_idx])

    def info(self, ids) -> dict[int, RefInfo]:
        return {int(i): RefInfo(self.rows[i].lat, self.rows[i].lon, self.rows[i].image.name) for i in ids}

    def in_region(self, region: Region) -> np.ndarray:
        return self.db[region.contains(self.lat, self.lon)]

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.rows[ref_id].image.read_bytes()


def assign_folds(rows: list[Row], folds: int, seed: int = 0) -> list[list[str]]:
    """Split the non-train groups into ``folds`` query sets (sorted, then shuffled with ``seed``)."""
    groups = sorted({r.group for r in rows if r.split != "train"})
    rng = np.random.default_rng(seed)
    rng.shuffle(groups)
    return [groups[f::folds] for f in range(folds)]


def check_folds(manifest: Path, rows: list[Row], query_sets: list[list[str]]) -> None:
    """Refuse, naming the manifest's problem, a fold with no query or with no db row left once its
    queries' groups are set aside (a db row sharing a group with a query is never a reference for it):
    fitting on nothing would otherwise die deep in numpy."""
    db_groups = {r.group for r in rows if r.split != "train"}
    for f, qgroups in enumerate(query_sets):
        qset = set(qgroups)
        where = f"fold {f + 1} of {len(query_sets)}" if len(query_sets) > 1 else "the query rows"
        if not any(r.group in qset and r.split != "train" for r in rows):
            raise ManifestCannotBeEvaluated(
                f"{manifest}: {where} has no query ({len(db_groups | qset)} groups for {len(query_sets)} "
                "folds); use fewer folds or more capture groups"
            )
        if not any(r.group not in qset and r.split != "train" for r in rows):
            shared = sorted(db_groups & qset)
            raise ManifestCannotBeEvaluated(
                f"{manifest}: {where} leaves no db row to fit on and search: every db row shares a group with "
                f"a query (groups {', '.join(shared[:5])}{' ...' if len(shared) > 5 else ''}). A group is one "
                "capture and its crops; give the references groups of their own, or use --folds to rotate "
                "the query role over the groups"
            )


def evaluate(
    manifest: Path,
    config: PipelineConfig,
    radius_m: float = 25.0,
    folds: int = 1,
    seed: int = 0,
    workers: int = 2,
    top_n: int = max(RECALL_AT),
    mode: str | None = None,
    cache_dir: Path | None = None,
    svm_bank: str = "off",
    bank_kind: str = "contrastive",
    rerank: bool | None = None,
    region_radius_m: float | None = None,
    bank_source: str = "train",
    models_dir: Path | None = None,
    absent_radius_m: float | None = None,
    partial: Path | None = None,
    fold: int | None = None,
    sequence: SequenceWindow | None = None,
) -> EvalResult:
    """``models_dir``: where the built models are (the global model through the registry, XFeat).
    ``svm_bank``: off (all features), positive (features the bank predicts useful) or negative (only
    the ones it predicts confusing): the thesis ablation. The bank is trained per fold, never on that
    fold's queries: ``bank_source`` train (the train rows only) or collection (the fold's db rows as
    training photos, plus the train rows: the rule ``geoloc fit`` serves). ``rerank`` and
    ``region_radius_m`` (a circle of that radius around each query's true position) ask the same of the
    core as /locate's ``rerank`` and region do: queries go through ``app.usecases.locate.locate_features``.
    ``rerank`` None: as /locate's default, verified when the configuration stores local features, from each
    photo's stored record (``stored_cached``: made once, cached in ``cache_dir``) over the fold's db rows.
    Verified, each query is also located without verification (the same search), so one run reports recall
    with and without it and the time it adds per query; and how each confidence score ranks the answers
    (``app.evaluation.confidence_ranking``) with and without it. ``partial``: a JSON file rewritten after each
    fold with the folds finished so far (their per-fold figures and per-query rows), so a run stopped before
    its end still reports them. ``fold`` (0-based): run only that one of the ``folds`` (a quick look; the
    figures of record pool every fold).

    Each answer is judged as /locate states it: its estimate's disc (``radius_m`` at ``radius_rate``), and,
    for ``no_match``, whether its place is absent: no reference of the fold (less those removed, for a
    simulated absent place) within ``absent_radius_m`` of the truth, else within ``radius_m``.
    ``sequence``: each query also answered with the photos around it in its
    sequence (``app.evaluation.sequences``); ``recall_at`` and ``answers`` are then the sequence's, and the
    same photos answered alone sit beside them (``single_recall_at``, ``single_answers``)."""
    if svm_bank not in ("off", "positive", "negative"):
        raise ValueError(f"svm_bank must be off, positive or negative, not {svm_bank!r}")
    if bank_source not in EVAL_BANK_SOURCES:
        raise ValueError(f"bank_source must be one of {EVAL_BANK_SOURCES}, not {bank_source!r}")
    rows = read_manifest(manifest)
    query_sets = [[r.group for r in rows if r.split == "query"]] if folds <= 1 else assign_folds(rows, folds, seed)
    check_folds(manifest, rows, query_sets)  # before the expensive extraction
    if fold is not None and not 0 <= fold < len(query_sets):
        raise ValueError(f"fold must be from 0 to {len(query_sets) - 1}, not {fold}")
    chosen = [fold] if fold is not None else list(range(len(query_sets)))
    base = Pipeline(config, models_dir=models_dir)
    extracted = extract_cached(base, rows, cache_dir, workers)
    verify = rerank if rerank is not None else config.stored_features is not None
    # A configuration that stores local features: every photo's record and query features, made once (the
    # folds' calibration verifies its held-out db rows from them whether or not the queries are verified).
    made = stored_cached(base, rows, cache_dir) if config.stored_features is not None else None

    lat = np.array([r.lat for r in rows])
    lon = np.array([r.lon for r in rows])
    per_fold, all_hits, est_err, est_conf, stage_times = [], [], [], [], []
    per_fold_plain, rerank_ms = [], []  # with rerank: recall without it, and the time it adds
    bank_reports, kept_fractions, per_query = [], [], []
    quality, all_present, all_absent, calibration_reports = [], [], [], []
    ranked_served, ranked_plain = [], []  # per present query: confidence_ranking.query_record
    seq_per_fold, seq_present, rests_on = [], [], []  # with ``sequence``: the sequences' answers
    n_db = n_query = 0
    bytes_per_ref = 0.0
    for f in chosen:
        qset = set(query_sets[f])
        q_idx = [i for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
        db_idx = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        train_idx = [i for i, r in enumerate(rows) if r.split == "train"]
        # The fold's fit (``app.usecases.fitting.fit_pipeline``, what `geoloc fit` runs): on its db and train rows
        # (never
        # on its queries), the bank (with ``svm_bank``) from them, the confidence rule and p_within_25m on the
        # db rows alone, as `geoloc fit` calibrates on the collection; with rerank (in the default search mode:
        # /locate reads no calibration in another) the rule for verified answers too, as
        # `geoloc fit --calibrate-rerank` fits it.
        photos = [
            FitPhoto(
                rows[i].image,
                extracted[i].features,
                rows[i].lat,
                rows[i].lon,
                rows[i].group,
                ref_id=i,
                taken=rows[i].time or extracted[i].captured_at,
            )
            for i in db_idx
        ] + [
            FitPhoto(rows[i].image, extracted[i].features, rows[i].lat, rows[i].lon, rows[i].group, reference=False)
            for i in train_idx
        ]
        fit_options = FitOptions(
            bank="none" if svm_bank == "off" else bank_source,
            bank_kind=bank_kind,
            bank_select="positive" if svm_bank == "off" else svm_bank,
            pos_radius_m=radius_m,
            seed=seed + f,
            calibrate_verified=verify and mode in (None, config.modes[0]),
            keep_index=True,
            fixed_threads=False,  # the machine's threads, as the recorded figures were measured
        )
        pipe = Pipeline(config, base.global_model, models_dir=models_dir)  # one session for every fold
        stored = None
        if made is not None:
            pipe._stored_extractor = base.stored_extractor
            # The fold's db rows' records (what its references store) and their query features (the
            # calibration locates them): the only records its queries are verified against.
            stored = PhotoStoredFeatures(
                base.stored_extractor, records={i: made[i][0] for i in db_idx}, queries={i: made[i][1] for i in db_idx}
            )
        fitted = fit_pipeline(pipe, photos, fit_options, stored=stored)
        index, geotagged = fitted.index, fitted.refs
        if pipe.bank is not None:
            bank_reports.append(
                {
                    k: pipe.bank.manifest.get(k)
                    for k in ("training", "chosen_keep_fraction", "threshold_trials", "train_seconds", "source")
                }
            )
        calibration_reports.append(
            {"source": pipe.calibration.source, **pipe.calibration.report, "fit_seconds": fitted.seconds}
        )
        refs = RowReferences(rows, db_idx)
        hits, hits_plain = [], []
        fold_present, fold_absent = [], []
        singles = {}  # with ``sequence``: each query's single answer, for its windows
        for i in q_idx:
            region = Region(rows[i].lat, rows[i].lon, region_radius_m) if region_radius_m else None
            options = LocateOptions(top_k=top_n, mode=mode, rerank=verify, region=region)
            rgb = pipe.decode(rows[i].image.read_bytes()).rgb if verify and stored is None else None
            q_stored = made[i][1] if stored is not None else None  # the query's, extracted once (cached)
            f_i = extracted[i].features
            codes = (
                pipe.encode_features(f_i, pipe.select(f_i))
                if pipe.config.local is None or f_i.n_local >= MIN_LOCAL_FEATURES
                else None
            )  # once for every search of this query (with and without rerank, its place present and absent)
            res = locate_features(
                pipe, index, refs, f_i, options, rgb, cluster_radius_m=radius_m, codes=codes, stored=stored,
                stored_query=q_stored,
            )  # fmt: skip
            ranked_served.append(query_record(res, rows[i].lat, rows[i].lon, radius_m))
            hits.append(_hits(rows, i, lat, lon, res.candidates, top_n, radius_m))
            verified = None
            if verify:
                plain = LocateOptions(top_k=top_n, mode=mode, rerank=False, region=region)
                res0 = locate_features(pipe, index, refs, f_i, plain, cluster_radius_m=radius_m, codes=codes)
                ranked_plain.append(query_record(res0, rows[i].lat, rows[i].lon, radius_m))
                hits_plain.append(_hits(rows, i, lat, lon, res0.candidates, top_n, radius_m))
                rerank_ms.append(res.timings_ms.get("rerank", 0.0))
                # What bench/verification.py analyses: the retrieval order, and each verified pair's outcome.
                verified = {
                    "retrieval": [
                        [
                            c.reference_id,
                            round(c.score, 6),
                            int(haversine_m(rows[i].lat, rows[i].lon, c.lat, c.lon) <= radius_m),
                        ]
                        for c in res0.candidates
                    ],
                    "pairs": {
                        str(r): None if v is None else [v.n_matches, v.h_inliers, v.f_inliers, v.mean_confidence]
                        for r, v in res.verification.items()
                    },
                }
            to_refs = haversine_m(rows[i].lat, rows[i].lon, lat[db_idx], lon[db_idx])
            fold_present.append(_answer_record(res, rows[i], radius_m, float(to_refs.min(initial=np.inf))))
            if sequence is not None:
                singles[i] = res
            if absent_radius_m:
                gone = near_ids(geotagged, rows[i].lat, rows[i].lon, absent_radius_m)
                left = to_refs[~np.isin(np.asarray(db_idx), gone)]
                res_absent = locate_features(
                    pipe, Excluding(index, gone), refs, f_i, options, rgb, cluster_radius_m=radius_m, codes=codes,
                    stored=stored, stored_query=q_stored,
                )  # as the present answer is located: verified with rerank  # fmt: skip
                fold_absent.append(_answer_record(res_absent, rows[i], radius_m, float(left.min(initial=np.inf))))
            e = res.estimate
            if e.lat is not None:
                err = float(haversine_m(rows[i].lat, rows[i].lon, e.lat, e.lon))
                est_err.append(err)
                est_conf.append((res.reason is None, err <= radius_m))
            stage_times.append({"decode": extracted[i].decode_ms, **res.timings_ms})
            per_query.append(
                {
                    "image": rows[i].image.name,
                    "group": rows[i].group,
                    "fold": f,
                    "lat": rows[i].lat,
                    "lon": rows[i].lon,
                    "candidates": [[round(c.lat, 7), round(c.lon, 7), round(c.score, 5)] for c in res.candidates],
                    "estimate": None
                    if e.lat is None
                    else {
                        "lat": e.lat,
                        "lon": e.lon,
                        "confidence": round(e.confidence, 4),
                        "confident": res.reason is None,
                        "answer_p": None if res.answer_p is None else round(res.answer_p, 4),
                        "radius_m": round(e.radius_m, 1),
                        "radius_rate": e.radius_rate,
                    },
                }
            )
            per_query[-1]["confidence"] = ranked_served[-1]
            if verified is not None:
                per_query[-1]["verification"] = verified
                per_query[-1]["confidence_without_verification"] = ranked_plain[-1]
            if res.features_extracted:
                kept_fractions.append(res.features_kept / res.features_extracted)
        if sequence is not None:
            # The rule the fold's single answers were judged by (``locate_features``'s choice).
            rule = pipe.calibration.for_answer(verify)
            if mode not in (None, config.modes[0]):
                rule = Calibration.conservative("the calibration judges the default search mode only")
            answered = answer_in_windows(rows, q_idx, singles, rule, sequence, LocateOptions(top_k=top_n, mode=mode))
            seq_hits = np.array([_hits(rows, i, lat, lon, answered[i][0].candidates, top_n, radius_m) for i in q_idx])
            seq_per_fold.append({str(n): float(seq_hits[:, n - 1].mean()) for n in RECALL_AT})
            seq_present += [_answer_record(answered[i][0], rows[i], radius_m) for i in q_idx]
            rests_on += [answered[i][1] for i in q_idx]
        quality.append(answer_quality(fold_present, fold_absent, absent_radius_m, radius_m))
        all_present += fold_present
        all_absent += fold_absent
        hits_arr = np.array(hits, bool)
        all_hits.append(hits_arr)
        per_fold.append({str(n): float(hits_arr[:, n - 1].mean()) for n in RECALL_AT})
        if verify:
            plain_arr = np.array(hits_plain, bool)
            per_fold_plain.append({str(n): float(plain_arr[:, n - 1].mean()) for n in RECALL_AT})
        n_db += len(db_idx)
        n_query += len(q_idx)
        bytes_per_ref = index.bytes_per_reference()
        if partial is not None:
            done = {
                "folds_done": len(quality),
                "folds": len(chosen),
                "recall_at_per_fold": per_fold,
                "without_rerank_recall_at_per_fold": per_fold_plain,
                "answers_per_fold": quality,
                "calibration_per_fold": calibration_reports,
                "estimates": [{"confident": c, "within_radius": ok} for c, ok in est_conf],
                "present": all_present,
                "queries": per_query,
            }
            partial.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(partial, json.dumps(done, default=float).encode())

    hits_all = np.vstack(all_hits)
    recall_curve = hits_all.mean(axis=0)
    stages = sorted({k for t in stage_times for k in t})
    ms = {s: float(statistics.median([t.get(s, 0.0) for t in stage_times])) for s in stages}
    ms["total"] = float(statistics.median([sum(t.values()) for t in stage_times]))
    conf = [ok for c, ok in est_conf if c]
    result = EvalResult.model_validate(
        {
            "config": config.name,
            "manifest": str(manifest),
            "folds": len(query_sets),
            "fold": fold,
            "n_db": n_db // len(chosen),
            "n_query": n_query,
            "radius_m": radius_m,
            "mode": mode or config.modes[0],
            "rerank": verify,
            "region_radius_m": region_radius_m,
            "recall_at": {str(n): float(np.mean([p[str(n)] for p in per_fold])) for n in RECALL_AT},
            "recall_at_per_fold": per_fold,
            "without_rerank": None
            if not verify
            else {
                "recall_at": {str(n): float(np.mean([p[str(n)] for p in per_fold_plain])) for n in RECALL_AT},
                "recall_at_per_fold": per_fold_plain,
                "rerank_ms_median": float(statistics.median(rerank_ms)) if rerank_ms else 0.0,
                "rerank_ms_p90": float(np.percentile(rerank_ms, 90)) if rerank_ms else 0.0,
            },
            "recall_curve": [float(x) for x in recall_curve],
            "ms_per_query": ms,
            "ms_per_query_note": "median over queries; extraction ran on a 2-thread pool, so per-stage times "
            "include contention"
            + (
                "; verified from stored features: rerank excludes the query's extraction by the stored profile "
                "(made once per photo, cached)"
                if made is not None and verify
                else ""
            ),
            "bytes_per_reference": bytes_per_ref,
            "estimate_error_m": {
                "median": float(np.median(est_err)) if est_err else None,
                "p90": float(np.percentile(est_err, 90)) if est_err else None,
                "confident_fraction": len(conf) / max(len(est_conf), 1),
                "confident_within_radius": float(np.mean(conf)) if conf else None,
                "all_within_radius": float(np.mean([ok for _, ok in est_conf])) if est_conf else None,
            },
            "svm_bank": {
                "selection": svm_bank,
                "kind": bank_kind if svm_bank != "off" else None,
                "source": bank_source if svm_bank != "off" else None,
                "kept_fraction_median": float(np.median(kept_fractions)) if kept_fractions else None,
                "folds": bank_reports,
            },
            "answers": answer_quality(all_present, all_absent, absent_radius_m, radius_m),
            "answers_per_fold": quality,
            "calibration_per_fold": calibration_reports,
            "confidence_ranking": {
                "answers": rank_confidence(ranked_served),
                "without_verification": rank_confidence(ranked_plain) if verify else None,
            },
            "config_definition": config.model_dump(),
            "queries": per_query,
        }
    )
    if sequence is not None:
        result.single_recall_at, result.single_answers = result.recall_at, result.answers
        result.recall_at = {str(n): float(np.mean([p[str(n)] for p in seq_per_fold])) for n in RECALL_AT}
        result.answers = AnswerQuality.model_validate(answer_quality(seq_present, [], None))
        result.sequence = {
            "window": sequence.window,
            "online": sequence.online,
            "max_speed_mps": sequence.motion.speed_mps,
            "max_step_m": sequence.motion.step_m,
            "recall_at_per_fold": seq_per_fold,
            "rests_on_sequence": rests_on.count("sequence"),
            "photos": len(rests_on),
        }
    return result


def _answer_record(res, row: Row, radius_m: float, nearest_m: float | None = None) -> dict:
    """What the answer-quality figures need of one answer: an estimate or not and then right, its reason
    code, the first candidates' p_within_25m with whether each lies within the radius, and how far the truth
    lies from the nearest reference searched (``nearest_m``: whether a no_match's place was absent)."""
    e = res.estimate
    cands = [c for c in res.candidates[:ESTIMATE_CANDIDATES] if c.p_within_25m is not None]
    d = haversine_m(row.lat, row.lon, np.array([c.lat for c in cands]), np.array([c.lon for c in cands]))
    error = float(haversine_m(row.lat, row.lon, e.lat, e.lon)) if e.lat is not None else float("inf")
    return {
        "confident": res.reason is None,
        "right": error <= radius_m,
        "right_2x": error <= 2 * radius_m,
        "code": res.reason_code or "confident",
        "error_m": error,
        "radius_m": e.radius_m,
        "radius_rate": e.radius_rate,
        # The evidence strength the stated radius is binned by (the calibrated answer_p; else the group's share).
        "strength": res.answer_p if res.answer_p is not None else e.confidence,
        "p": [c.p_within_25m for c in cands],
        "within": [bool(x) for x in np.atleast_1d(d <= radius_m)] if cands else [],
        "nearest_m": nearest_m,
    }


def answer_quality(
    present: list[dict], absent: list[dict], absent_radius_m: float | None, radius_m: float = 25.0
) -> dict:
    """The answers' figures: the estimate share (``coverage``) and its precision at ``radius_m``, the stated
    discs (``stated_radius_quality``), the Brier score and reliability of ``p_within_25m``, the reason codes,
    how often a no_match's place was absent (``no_match_absent``), and, with simulated absent places
    (``absent_radius_m``), how they were answered."""

    def codes(records):
        out: dict[str, int] = {}
        for r in records:
            out[r["code"]] = out.get(r["code"], 0) + 1
        return out

    def brier(records):
        p = np.array([x for r in records for x in r["p"]], float)
        y = np.array([x for r in records for x in r["within"]], float)
        return (float(np.mean((p - y) ** 2)) if len(p) else None), p, y

    conf = [r["right"] for r in present if r["confident"]]
    near = [r.get("right_2x", False) for r in present if r["confident"]]
    b, p, y = brier(present)
    out = {
        "coverage": len(conf) / max(len(present), 1),
        "precision": float(np.mean(conf)) if conf else None,
        "precision_at_2x_radius": float(np.mean(near)) if near else None,
        "estimate_share": len(conf) / max(len(present), 1),
        **stated_radius_quality([r for r in present if r["confident"]]),
        **no_match_absent(present + absent, absent_radius_m or radius_m),
        "brier": b,
        "reliability": reliability(p, y),
        "reason_codes": codes(present),
    }
    if absent_radius_m:
        ab, _, _ = brier(absent)
        out.update(
            {
                "absent_radius_m": absent_radius_m,
                "absent_confident": float(np.mean([r["confident"] for r in absent])) if absent else None,
                "absent_mean_best_p": float(np.mean([max(r["p"], default=0.0) for r in absent])) if absent else None,
                "absent_brier": ab,
                "absent_reason_codes": codes(absent),
            }
        )
    return out


def no_match_absent(records: list[dict], absent_at_m: float) -> dict:
    """Of the no_match answers (the present queries' and the simulated absent places'), the share whose place
    is absent: no reference searched within ``absent_at_m`` of the truth. What no_match's words may claim."""
    rows = [r for r in records if r["code"] == "no_match" and r.get("nearest_m") is not None]
    return {
        "no_match_answers": len(rows),
        "no_match_absent_share": float(np.mean([r["nearest_m"] > absent_at_m for r in rows])) if rows else None,
        "no_match_absent_at_m": absent_at_m,
    }


def stated_radius_quality(confident: list[dict]) -> dict:
    """Whether the confident answers' stated radii hold: the share whose truth lies within the radius stated,
    overall and in the quartile with the weakest evidence (lowest ``strength``, ties broken by order), the
    median radius stated, and the rate stated (None when the radii were the constant rule's)."""
    rows = [r for r in confident if r.get("radius_m") is not None]
    if not rows:
        return {}
    held = np.array([r["error_m"] <= r["radius_m"] for r in rows])
    weakest = np.argsort([r["strength"] for r in rows], kind="stable")[: max(1, len(rows) // 4)]
    rates = {r["radius_rate"] for r in rows}
    return {
        "radius_coverage": float(held.mean()),
        "radius_coverage_weakest_quartile": float(held[weakest].mean()),
        "median_radius_m": float(np.median([r["radius_m"] for r in rows])),
        "p90_radius_m": float(np.percentile([r["radius_m"] for r in rows], 90)),
        "radius_rate": rates.pop() if len(rates) == 1 else None,
    }


def write_report(result: EvalResult, out: Path) -> Path:
    """Write the JSON and a Recall@N plot beside it; return the plot's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result.model_dump(), indent=1))
    png = out.with_suffix(".png")
    n = np.arange(1, len(result.recall_curve) + 1)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(n, result.recall_curve, marker="o", ms=3)
    ax.set_xlabel("N")
    ax.set_ylabel(f"Recall@N within {result.radius_m:.0f} m")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.set_title(f"{result.config} ({result.n_query} queries, {result.folds} fold(s))")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


def format_summary(result: EvalResult | dict) -> str:
    """The summary the CLI prints; takes a report's JSON form too (bench/results.py reads reports back)."""
    if isinstance(result, EvalResult):
        result = result.model_dump()
    r = result["recall_at"]
    ms = result["ms_per_query"]
    e = result["estimate_error_m"]
    lines = [
        f"config {result['config']}  db {result['n_db']}  queries {result['n_query']}  folds {result['folds']}"
        + (f" (fold {result['fold']} only)" if result.get("fold") is not None else "")
        + "  "
        f"radius {result['radius_m']:.0f} m  mode {result['mode']}"
        + ("  rerank" if result.get("rerank") else "")
        + (f"  region {result['region_radius_m']:.0f} m" if result.get("region_radius_m") else ""),
        "Recall@1/5/10/20: " + " / ".join(f"{r[k]:.3f}" for k in ("1", "5", "10", "20")),
        *(
            [
                "without rerank: " + " / ".join(f"{w['recall_at'][k]:.3f}" for k in ("1", "5", "10", "20")),
                f"rerank adds {w['rerank_ms_median']:.1f} ms per query (median; p90 {w['rerank_ms_p90']:.1f} ms)",
            ]
            if (w := result.get("without_rerank"))
            else []
        ),
        "ms per query (median): " + ", ".join(f"{k} {v:.1f}" for k, v in ms.items()),
        f"bytes per reference: {result['bytes_per_reference']:.0f}",
        *(
            [
                f"SVM bank ({result['svm_bank']['kind']}): {result['svm_bank']['selection']} features, median kept "
                f"fraction {result['svm_bank']['kept_fraction_median']:.2f}"
            ]
            if result["svm_bank"]["selection"] != "off"
            else []
        ),
        f"estimate error: median {e['median']:.1f} m, p90 {e['p90']:.1f} m; confident "
        f"{e['confident_fraction']:.0%} of the time, and then within the radius "
        + (f"{e['confident_within_radius']:.0%}" if e["confident_within_radius"] is not None else "n/a"),
        *_quality_lines(result),
        *_ranking_lines(result),
        *_sequence_lines(result),
    ]
    return "\n".join(lines)


def _sequence_lines(result: dict) -> list[str]:
    """With ``--sequence-window``: the sequences' answers beside the same photos answered alone."""
    seq = result.get("sequence")
    if not seq:
        return []
    r, r1 = result["recall_at"], result["single_recall_at"]
    a, a1 = result["answers"], result["single_answers"]
    how = "online (the photos before each)" if seq["online"] else "centred"
    return [
        f"sequences: windows of {seq['window']} photos, {how}; max {seq['max_speed_mps']:g} m/s with times, "
        f"{seq['max_step_m']:g} m a step without; {seq['rests_on_sequence']} of {seq['photos']} answers rest on "
        "the sequence",
        f"  Recall@1/5, sequence vs alone: {r['1']:.3f} / {r['5']:.3f}  vs  {r1['1']:.3f} / {r1['5']:.3f}",
        f"  estimates (share of photos): {_pct(a['coverage'])} vs {_pct(a1['coverage'])}; within 25 m "
        f"{_pct(a['precision'])} vs {_pct(a1['precision'])}; truth within the stated radius "
        f"{_pct(a.get('radius_coverage'))} vs {_pct(a1.get('radius_coverage'))}",
    ]


def _ranking_lines(result: dict) -> list[str]:
    """How each confidence score ranks the answers (``confidence_ranking``), served and without verification."""
    c = result.get("confidence_ranking")
    if not c:
        return []
    served = "verified answers" if result.get("rerank") else "answers"
    return ranking_lines(c["answers"], f"confidence ranking, {served}") + ranking_lines(
        c.get("without_verification"), "confidence ranking, the same queries without verification"
    )


def _pct(x) -> str:
    return "n/a" if x is None else f"{x:.1%}"


def _num0(x) -> str:
    return "n/a" if x is None else f"{x:.0f}"


def _num(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _quality_lines(result: dict) -> list[str]:
    """Answer quality per fold and pooled: confident precision / coverage, Brier, absent places."""
    a = result.get("answers")
    if not a:
        return []
    out = [
        "answers (estimates: within the radius / share of queries; Brier of p_within_25m"
        + ("; absent places: confident, mean best p, Brier" if a.get("absent_radius_m") else "")
        + "):"
    ]
    for name, q in [*((f"  fold {k + 1}", q) for k, q in enumerate(result.get("answers_per_fold", []))), ("  all", a)]:
        line = (
            f"{name}: {_pct(q['precision'])} / {_pct(q['coverage'])} (within twice the radius "
            f"{_pct(q.get('precision_at_2x_radius'))}), Brier {_num(q['brier'])}"
        )
        if q.get("radius_coverage") is not None:
            line += (
                f"; truth within the stated radius {_pct(q['radius_coverage'])} (weakest quartile "
                f"{_pct(q['radius_coverage_weakest_quartile'])}, median radius {q['median_radius_m']:.0f} m, "
                f"p90 {_num0(q.get('p90_radius_m'))} m, rate stated {_pct(q.get('radius_rate'))})"
            )
        if q.get("no_match_answers"):
            line += (
                f"; no_match {q['no_match_answers']}, of which the place was absent (no reference within "
                f"{q['no_match_absent_at_m']:.0f} m) {_pct(q['no_match_absent_share'])}"
            )
        if q.get("absent_radius_m"):
            line += (
                f"; absent {_pct(q['absent_confident'])} confident, mean best p {_num(q['absent_mean_best_p'])}, "
                f"Brier {_num(q['absent_brier'])}"
            )
        out.append(line)
    out.append(
        "  reliability (bin: predicted -> observed, n): "
        + ", ".join(f"{r['bin']}: {r['predicted']:.2f} -> {r['observed']:.2f} ({r['n']})" for r in a["reliability"])
    )
    out.append(
        "  reason codes: "
        + ", ".join(f"{k} {v}" for k, v in sorted(a["reason_codes"].items()))
        + (
            "; absent: " + ", ".join(f"{k} {v}" for k, v in sorted(a["absent_reason_codes"].items()))
            if a.get("absent_reason_codes")
            else ""
        )
    )
    return out
