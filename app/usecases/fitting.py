"""The fit, once, for ``geoloc fit``, the first start of an empty data dir, ``geoloc refit`` and each of the
evaluation's folds: where the SVM bank learns by default, which requests are refused, and the one sequence
of a fit (``fit_pipeline``: extraction, then codebook, PCA-whitening and binariser, then the SVM bank, then
the calibration on the references), with its steps' times and progress.

Why one module: the faces used to decide these each in their own words, and to sequence the fit each in
their own code (refit did it by hand, the evaluation too), so a rule changed in one (say, "a configuration
without local features has no bank") silently stayed old in the others, and what the evaluation measured
was not what `fit` built.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from app.domain import LocateAnswer, LocateOptions, RefInfo, Region
from app.engine.calibration import MAX_RADIUS_M, MIN_QUERIES, RADIUS_RATE, Calibration, Sample, fit_calibration
from app.engine.configs import PipelineConfig
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits
from app.engine.index.references import ReferenceIndex
from app.engine.learned_whitening import Place
from app.engine.pipeline import Features, Pipeline
from app.engine.progress import Progress
from app.engine.svm_bank import KINDS, BankParams, SvmBank
from app.engine.training.svm_training import BANK_SOURCES, Geotagged, NothingToTrainOn, fit_bank_from, index_of
from app.errors import FitRefused
from app.runtime import fit_threads
from app.usecases.extraction import Counter, Extracted, extract_batch
from app.usecases.stored_photos import PhotoStoredFeatures
from app.usecases.walk_calibration import WalkAnswers, capture_seconds, fit_walk_disc, walk_note, walk_windows

log = logging.getLogger("geoloc.fit")

#: References located against the others to calibrate (like the SVM bank's sample: the cost of a fit or a
#: refit does not grow with the collection past it).
CALIBRATION_SAMPLE = 600
#: Where an evaluation's bank learns, per fold (never "none": the evaluation's ``svm_bank=off`` says that).
EVAL_BANK_SOURCES = ("train", "collection")


def bank_source(config: PipelineConfig, asked: str | None, train_photos_given: bool = False) -> str:
    """The bank's source: what was asked, else ``train`` when training photos were given apart from the
    references (``refit --train-manifest``), else ``collection`` for a configuration that wants a bank and
    has local features, else ``none``."""
    source = asked or (
        "train" if train_photos_given else "collection" if config.svm_bank and config.local is not None else "none"
    )
    if source not in BANK_SOURCES:
        raise FitRefused(f"--svm-bank must be one of {', '.join(BANK_SOURCES)}, not {source!r}")
    if source != "none" and config.local is None:
        raise FitRefused(f"configuration {config.name} has no local features: an SVM bank has nothing to select")
    return source


def check_bank_kind(kind: str) -> None:
    if kind not in KINDS:
        raise FitRefused(f"--svm-bank-kind must be one of {', '.join(KINDS)}")


def train_bank(
    pipe: Pipeline,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    source: str,
    kind: str,
    seed: int,
    pos_radius_m: float = 25.0,
    index: ReferenceIndex | None = None,
) -> SvmBank:
    """The bank for ``pipe`` (fitted), retrieved against an in-memory index of ``refs`` encoded by it
    (``index``, when the caller has built it already: the evaluation searches the same one):
    ``collection`` learns from the references (plus ``train``), ``train`` from ``train`` alone."""
    check_bank_kind(kind)
    if source == "train" and not train:
        raise FitRefused(
            "no training photos: --svm-bank train learns from geotagged photos that are not references "
            "(--svm-bank collection learns from the references)"
        )
    if not refs:
        raise FitRefused("no references: the SVM bank needs references to retrieve against")
    if index is None:
        ids = sorted(refs)
        index = index_of(pipe, ids, (refs[i].features for i in ids))
    return fit_bank_from(source, pipe, index, refs, train, BankParams(kind=kind, seed=seed), pos_radius_m=pos_radius_m)


def capture_group(lat: float, lon: float) -> str:
    """Which references count as one capture (a photo and its crops) for the SVM bank's "never learn from
    yourself" rule and the calibration's "place present" answers: the same position to about 0.1 m.

    Why not the capture time as well: a photo's crops carry no EXIF time, so a crop and the photo it was cut
    from were two captures, and ``geoloc refit``'s calibration located each against the other (0 m off): a
    small collection's rule then stated a radius of metres and a near-certain ``p_within_25m`` for answers
    far off (docs/results.md). Two photos taken at one spot, to 0.1 m, count as one capture."""
    return f"@{lat:.6f},{lon:.6f}"


# -- the fit, once --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FitPhoto:
    """One photo a fit learns from.

    ``path``: where to read it; ``features``: its features, extracted already (the evaluation's folds share
    one extraction; ``path`` is then only read to verify, with ``FitOptions.calibrate_verified``).
    ``lat``/``lon`` None: the photo's EXIF position (one with neither is left out); ``group`` None: its
    capture (``capture_group``) from the position.
    ``reference``: one of the collection (the SVM bank retrieves against it, the calibration locates it),
    numbered ``ref_id`` (None: by its place among the references kept); else a training photo: geotagged,
    not a reference. ``in_fit``: whether the codebook, PCA-whitening and binariser learn from it (a
    refit's training photos train the bank only). ``sha256``: of its bytes, when known already (a stored
    reference's); else that of the bytes read. ``taken``: when it was taken (ISO 8601), when known already (a
    manifest's ``time``, a stored reference's ``captured_at``); else the photo's EXIF time where it has one:
    the calibration arranges the references that have one into walks (``app.usecases.walk_calibration``)."""

    path: Path | None = None
    features: Features | None = None
    lat: float | None = None
    lon: float | None = None
    group: str | None = None
    reference: bool = True
    ref_id: int | None = None
    in_fit: bool = True
    sha256: str | None = None
    taken: str | None = None


@dataclass(frozen=True)
class FitOptions:
    """How a fit runs. ``bank``: where the SVM bank learns (``bank_source``: collection, train or none);
    ``bank_select``: which features it keeps (the evaluation's ablation: negative); ``bank_optional``: a
    bank that cannot be trained (too few or too uniform photos) leaves the pipeline without one instead of
    failing the fit (the first start serves all the same). ``pos_radius_m``: the bank's positives.
    ``calibration_sample``: references located to calibrate; ``calibrate_verified``: also the rule for
    verified answers, on the references' photos. ``limits``, ``workers``: the extraction's decode limits
    and threads; ``skip_unreadable``: leave out (logged) a photo that cannot be read or has no position,
    instead of failing. ``keep_index``: return the references encoded by the fitted pipeline (the
    evaluation searches them). ``fixed_threads``: the numerical steps on ``fit_threads`` (the same fit on
    any machine); the evaluation's folds keep the machine's threads, as its recorded figures were measured
    (on 2 cores, one thread moved a fold's bank on the mini manifest, and with it Recall@5).
    """

    bank: str = "none"
    bank_kind: str = "contrastive"
    bank_select: str = "positive"
    bank_optional: bool = False
    pos_radius_m: float = 25.0
    seed: int = 0
    calibration_sample: int = CALIBRATION_SAMPLE
    calibrate_verified: bool = False
    limits: ImageLimits | None = None
    workers: int = 1
    skip_unreadable: bool = False
    keep_index: bool = False
    fixed_threads: bool = True
    radius_rate: float = RADIUS_RATE
    max_radius_m: float = MAX_RADIUS_M


@dataclass
class FittedPipeline:
    """What a fit made: the pipeline (fitted, with its bank and calibration), the references it learnt from
    (by id), where its bank learnt (``none`` without one), each step's seconds (``extract``, ``codebook,
    PCA, binariser``, ``SVM bank``, ``calibration``: where a fit's time goes) and, with ``keep_index``, the
    references encoded by the pipeline before its bank."""

    pipeline: Pipeline
    refs: dict[int, Geotagged]
    bank: str
    seconds: dict[str, float]
    index: ReferenceIndex | None = None

    @property
    def fit_seconds(self) -> str:
        """The fitting steps' times, for a log line (``codebook, PCA, binariser 3.7 s, ...``)."""
        return ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items() if k != "extract")


class FitProgress:
    """What a fit tells as it goes: the extraction's progress (a bar on a terminal, else a line every tenth),
    then one line before the fitting steps, to ``say`` (none: silent). The first start overrides both to
    show them on /ready."""

    def __init__(self, say: Callable[[str], None] | None = None, desc: str = "fit: extract"):
        self.say, self.desc = say, desc

    def extraction(self, total: int) -> Counter:
        return Progress(total, desc=self.desc, every=max(1, total // 10))

    def fitting(self, config: str, photos: int, extract_seconds: float) -> None:
        if self.say is not None:
            self.say(f"fit: extracted {photos} images in {extract_seconds:.0f} s; fitting {config} ...")


def fit_pipeline(
    pipe: Pipeline,
    photos: Sequence[FitPhoto],
    options: FitOptions,
    progress: FitProgress | None = None,
    stored: PhotoStoredFeatures | None = None,
) -> FittedPipeline:
    """Fit ``pipe`` on ``photos``, every step in order: extract the features of those not extracted yet,
    fit the codebook, PCA-whitening and binariser on the photos ``in_fit`` (in the order given), then, unless
    ``options.bank`` is ``none``, the SVM bank from the references and the training photos, then the
    confidence rule and ``p_within_25m`` on the references themselves (``calibrate_collection``, with the
    training photos in its auxiliary fits). What `geoloc fit`, the first start, `geoloc refit` and each of
    the evaluation's folds run: one fit, so what the evaluation measures is what the others build.

    ``stored``: the references' stored-profile features made already (the evaluation's cache), for a
    configuration with ``stored_features``; else the calibration makes them from the photos.

    Raises ``FitRefused`` when fewer than 2 photos are left to fit on, or the bank cannot be trained (unless
    ``bank_optional``). The numerical steps run on ``fit_threads`` (unless ``options.fixed_threads`` is
    off); the extraction keeps its own threads."""
    if options.bank != "none":
        check_bank_kind(options.bank_kind)
    progress = progress or FitProgress()
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    kept = _extracted(pipe, photos, options, progress)
    seconds["extract"] = time.perf_counter() - t0
    fit_on = [p for p in kept if p.in_fit]
    if len(fit_on) < 2:
        asked = sum(p.in_fit for p in photos)
        raise FitRefused(f"{len(fit_on)} of the {asked} photos to fit on could be read: a fit needs at least 2")
    progress.fitting(pipe.config.name, len(kept), seconds["extract"])
    refs: dict[int, Geotagged] = {}
    hashes: dict[int, str] = {}
    images: dict[int, Path] = {}
    taken: dict[int, str] = {}
    for p in kept:
        if not p.reference:
            continue
        i = len(refs) if p.ref_id is None else p.ref_id
        refs[i] = Geotagged(p.features, p.lat, p.lon, p.group)
        if p.sha256:
            hashes[i] = p.sha256
        if p.path is not None:
            images[i] = p.path
        if p.taken:
            taken[i] = p.taken
    ids = sorted(refs)
    train = [Geotagged(p.features, p.lat, p.lon, p.group) for p in kept if not p.reference]
    source, index = options.bank, None
    # One BLAS and OpenMP thread: the same fit on any machine (app.runtime).
    with fit_threads() if options.fixed_threads else nullcontext():
        t0 = time.perf_counter()
        places = [Place(p.lat, p.lon, p.group) for p in fit_on]  # a configuration with learned whitening uses them
        pipe.fit([p.features for p in fit_on], seed=options.seed, places=places)
        seconds["codebook, PCA, binariser"] = time.perf_counter() - t0
        if options.keep_index:
            index = index_of(pipe, ids, (refs[i].features for i in ids))
        if source != "none":
            t0 = time.perf_counter()
            try:
                pipe.bank = train_bank(
                    pipe, refs, train, source, options.bank_kind, options.seed, options.pos_radius_m, index
                )
            except (FitRefused, NothingToTrainOn) as e:
                if not options.bank_optional:
                    raise
                log.warning("no SVM bank (%s); the pipeline is fitted without one", e)
                source = "none"  # and calibrated on these photos all the same: never judged by another's figures
            seconds["SVM bank"] = time.perf_counter() - t0
        pipe.bank_select = options.bank_select
        t0 = time.perf_counter()
        pipe.calibration = calibrate_collection(
            pipe,
            refs,
            [t.features for t in train],
            options.calibration_sample,
            seed=options.seed,
            images=images if options.calibrate_verified or pipe.config.stored_features else None,
            hashes=hashes,
            stored=stored,
            radius_rate=options.radius_rate,
            max_radius_m=options.max_radius_m,
            times=capture_seconds(taken),
        )
        seconds["calibration"] = time.perf_counter() - t0
    return FittedPipeline(pipe, refs, source, seconds, index)


@dataclass(frozen=True)
class _Ready:
    """A ``FitPhoto`` with its features, position and capture known."""

    path: Path | None
    features: Features
    lat: float
    lon: float
    group: str
    reference: bool
    ref_id: int | None
    in_fit: bool
    sha256: str | None
    taken: str | None = None


def _extracted(pipe: Pipeline, photos: Sequence[FitPhoto], options: FitOptions, progress: FitProgress) -> list[_Ready]:
    """The photos with their features (extracted now, ``extract_batch``, for those without), position and
    capture; those left out (unreadable, no position) logged, with ``skip_unreadable``."""
    todo = [k for k, p in enumerate(photos) if p.features is None]
    extracted: list[Extracted | None] = [None] * len(photos)
    if todo:
        pipe.load_models()
        done = extract_batch(
            pipe,
            [photos[k].path for k in todo],
            limits=options.limits,
            workers=options.workers,
            progress=progress.extraction(len(todo)),
            skip_unreadable=options.skip_unreadable,
        )
        for k, e in zip(todo, done, strict=True):
            extracted[k] = e
    out = []
    for p, e in zip(photos, extracted, strict=True):
        if p.features is None and e is None:
            continue  # unreadable: logged by extract_batch
        position = (p.lat, p.lon) if p.lat is not None and p.lon is not None else (e.gps if e else None)
        if position is None:
            if not options.skip_unreadable:
                raise FitRefused(f"{p.path}: no GPS position, in its row or in the photo")
            log.warning("%s: not used (no GPS position)", p.path)
            continue
        lat, lon = position
        group = p.group or capture_group(lat, lon)
        features = p.features if p.features is not None else e.features
        sha256 = p.sha256 or (e.sha256 if e else None)
        taken = p.taken or (e.captured_at if e else None)
        out.append(_Ready(p.path, features, lat, lon, group, p.reference, p.ref_id, p.in_fit, sha256, taken))
    return out


# -- calibration on the collection itself -------------------------------------------------------------------
#: Of the references located to calibrate (``CALIBRATION_SAMPLE``), how many are located once more with
#: verification (``--calibrate-rerank``) for the rule that judges verified answers: each costs its own photo's
#: matcher features and up to 20 verified pairs (the candidates' features are computed once per reference):
#: the sample bounds that cost.
VERIFY_CALIBRATION_SAMPLE = 300
#: At most this many references' matcher features are kept while calibrating (RootSIFT's 1,500 keypoints
#: take about 0.8 MB each, so about 320 MB), the oldest dropped first: a large collection's candidates then
#: recur less, but memory stays bounded whatever its size.
FEATURES_KEPT = 400


class BoundedCache(dict):
    """A dict that forgets its oldest entries beyond ``size`` (what ``verify_candidate_pairs`` keeps)."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        while len(self) > self.size:
            del self[next(iter(self))]


#: A place counts as absent when no reference lies within this many metres of it.
ABSENT_RADIUS_M = 100.0
#: The collection is dealt into this many parts; each auxiliary fit leaves one out (calibrate_collection).
HOLDOUT_PARTS = 4


class GeotaggedReferences:
    """Geotagged photos (id -> ``Geotagged``) as the core's ``ReferenceSource``: what locate reads of them.
    ``image_bytes`` (for verification) reads ``paths`` when given."""

    def __init__(self, refs: dict[int, Geotagged], paths: dict[int, Path] | None = None):
        self.refs = refs
        self.paths = paths or {}

    def info(self, ids) -> dict[int, RefInfo]:
        return {int(i): RefInfo(self.refs[int(i)].lat, self.refs[int(i)].lon) for i in ids if int(i) in self.refs}

    def in_region(self, region: Region) -> np.ndarray:
        ids = np.array(sorted(self.refs), np.int64)
        lats = np.array([self.refs[i].lat for i in ids])
        lons = np.array([self.refs[i].lon for i in ids])
        return ids[region.contains(lats, lons)] if len(ids) else ids

    def image_bytes(self, ref_id: int) -> bytes | None:
        path = self.paths.get(int(ref_id))
        try:
            return path.read_bytes() if path is not None else None
        except OSError:
            return None


def calibration_sample(
    answer: LocateAnswer, lat: float, lon: float, absent: bool, radius_m: float = 25.0, group: str | None = None
):
    """One located answer as a calibration ``Sample`` (None when it had nothing to say: no features, no
    candidates). The answer must show its fused candidates (``top_k`` = ``ESTIMATE_CANDIDATES``)."""
    ev, e = answer.evidence, answer.estimate
    if ev is None or len(ev.values) == 0 or e.lat is None:
        return None
    cands = answer.candidates[: len(ev.values)]
    within = haversine_m(lat, lon, np.array([c.lat for c in cands]), np.array([c.lon for c in cands])) <= radius_m
    members = np.zeros(len(ev.values), bool)
    m = np.asarray(e.members, bool)[: len(members)]
    members[: len(m)] = m
    error_m = float(haversine_m(lat, lon, e.lat, e.lon))
    return Sample(ev, within, members, error_m <= radius_m, absent, error_m, group)


def collection_extent_m(refs: dict[int, Geotagged]) -> float:
    """The collection's extent: the diagonal of the box its references lie in (a disc is informative only
    when it is small against it)."""
    lats = np.array([r.lat for r in refs.values()])
    lons = np.array([r.lon for r in refs.values()])
    return float(haversine_m(lats.min(), lons.min(), lats.max(), lons.max())) if len(lats) else 0.0


def near_ids(refs: dict[int, Geotagged], lat: float, lon: float, radius_m: float) -> list[int]:
    ids = np.array(sorted(refs), np.int64)
    lats = np.array([refs[i].lat for i in ids])
    lons = np.array([refs[i].lon for i in ids])
    return ids[haversine_m(lat, lon, lats, lons) <= radius_m].tolist()


def calibration_parts(refs: dict[int, Geotagged], sample: int, seed: int) -> list[list[int]]:
    """The references the calibration locates, in parts: whole captures (a photo and its crops) dealt in a
    seeded order into ``HOLDOUT_PARTS`` parts, each of which one auxiliary fit leaves out; only as many parts
    as hold ``sample`` references are used (so a large collection costs one or two fits, a small one is
    located whole)."""
    groups: dict[str, list[int]] = {}
    for i in sorted(refs):
        groups.setdefault(refs[i].group, []).append(i)
    names = sorted(groups)
    np.random.default_rng(seed).shuffle(names)
    parts: list[list[int]] = [[] for _ in range(HOLDOUT_PARTS)]
    for k, g in enumerate(names):
        parts[k % HOLDOUT_PARTS] += groups[g]
    out, n = [], 0
    for p in parts:
        if n >= sample or not p:
            break
        take = p[: max(0, sample - n)]
        out.append(sorted(take))
        n += len(take)
    return out


def calibrate_collection(
    pipe: Pipeline,
    refs: dict[int, Geotagged],
    extra: Sequence[Features] = (),
    sample: int = CALIBRATION_SAMPLE,
    absent_radius_m: float = ABSENT_RADIUS_M,
    seed: int = 0,
    images: Mapping[int, Path] | None = None,
    verify_sample: int = VERIFY_CALIBRATION_SAMPLE,
    hashes: Mapping[int, str] | None = None,
    stored: PhotoStoredFeatures | None = None,
    radius_rate: float = RADIUS_RATE,
    max_radius_m: float = MAX_RADIUS_M,
    times: Mapping[int, float] | None = None,
) -> Calibration:
    """The confidence rule and ``p_within_25m`` for ``pipe`` (fitted, with its bank), fitted on the collection
    ``refs`` itself.

    Why a second, auxiliary fit: a reference that was in the sample the codebook and the PCA-whitening were
    fitted on scores lower against the other references than any new photo does (full whitening spreads its
    own sample apart), so a rule learned from references located against each other under ``pipe`` did not
    hold for real queries (on held-out queries it was never confident).
    So a held-out set of captures (``calibration_holdout``) is left out of an auxiliary fit of the same
    configuration on the rest (plus ``extra``, the other photos ``pipe`` was fitted on), sharing ``pipe``'s
    SVM bank; every reference is encoded by it, and each held-out reference is located through
    ``app.usecases.locate.locate_features`` (the path /locate serves) with its own capture left out (the place is
    present, when another capture shows it) and with every reference within ``absent_radius_m`` removed
    (the place is absent). Cost: one more fit and one encoding of ``refs`` (the refit's sample, bounded),
    plus two searches per held-out reference (at most ``sample``).

    ``images`` (reference id -> its photo): the first ``verify_sample`` held-out references are located
    twice more with verification by the configuration's matcher (their place present and absent), and a
    second rule is fitted on those verified answers (``Calibration.verified``), which /locate applies to
    answers with ``rerank``: verification's evidence then counts in ``p_within_25m`` and the confidence.

    A configuration with ``stored_features`` verifies as /locate does by default, from stored records: every
    held-out reference (not only ``verify_sample``) is located verified, from records made once per
    reference from its photo (``stored``, else made here from ``images`` by the profile's extractor:
    ``PhotoStoredFeatures``), so the verified rule is fitted on as many answers as the unverified one, at the
    cost of one extraction per reference located or retrieved and the matching (``report["verified_seconds"]``).

    ``hashes`` (reference id -> the sha256 of its photo): recorded as ``Calibration.references`` (those of the
    located sample), so that a data dir judged by this pipeline can tell whether the figures are its own.

    The disc every answer states (``fit_disc``) is fitted on the same answers, the absent ones counting as
    held by no disc, at ``radius_rate``, an estimate stated up to ``max_radius_m`` and a share of the
    collection's extent (``collection_extent_m``).

    ``times`` (reference id -> its capture time in seconds, on one clock): the held-out references that have
    one are also located as walks (``app.usecases.walk_calibration``), and the disc a sequence's answers state
    is fitted on them (``Calibration.sequence_disc``)."""
    from app.usecases.locate import ESTIMATE_CANDIDATES, MIN_LOCAL_FEATURES, Excluding, locate_features

    ids = sorted(refs)
    parts = calibration_parts(refs, sample, seed)
    held = sum(parts, [])
    if len(held) < MIN_QUERIES:
        return Calibration.conservative(
            f"the collection is too small to calibrate ({len(held)} references sampled; at least {MIN_QUERIES} needed)",
            {"sampled": len(held), "too_small": True},
        )
    by_group: dict[str, list[int]] = {}
    by_spot: dict[str, list[int]] = {}  # a manifest without groups names each crop its own group
    spot_of = {i: capture_group(refs[i].lat, refs[i].lon) for i in ids}
    for i in ids:
        by_group.setdefault(refs[i].group, []).append(i)
        by_spot.setdefault(spot_of[i], []).append(i)
    source = GeotaggedReferences(refs, dict(images) if images else None)
    options = LocateOptions(top_k=ESTIMATE_CANDIDATES, rerank=False)  # the unverified rule, whatever the default
    verified_options = LocateOptions(top_k=ESTIMATE_CANDIDATES, rerank=True)
    if pipe.config.stored_features is not None:
        stored_limits = ImageLimits().stored()  # the references' decode, as the encode path's
        if stored is None and images:
            stored = PhotoStoredFeatures(pipe.stored_extractor, lambda i: _photo(pipe, images.get(i), stored_limits))
        to_verify = {i for i in held if i in stored.queries or (images and i in images)} if stored else set()
    else:
        stored = None
        to_verify = set([i for i in held if i in images][: max(0, verify_sample)] if images else [])
    verified_seconds = 0.0
    features_cache = BoundedCache(FEATURES_KEPT)
    samples, verified_samples, verified_refs = [], [], 0
    walks: list[WalkAnswers] = []
    verified_walks: list[WalkAnswers] = []
    for k, part in enumerate(parts):
        out = {g for i in part for g in [refs[i].group]}
        kept = [i for i in ids if refs[i].group not in out]
        fit_on = [refs[i].features for i in kept] + list(extra)
        if len(fit_on) < 2:
            continue
        places = [Place(refs[i].lat, refs[i].lon, refs[i].group) for i in kept] + [None] * len(extra)
        aux = Pipeline(pipe.config, pipe.global_model, models_dir=pipe.models_dir)
        aux.fit(fit_on, seed=seed + 1 + k, codebook=pipe.codebook, places=places)
        aux.bank, aux.bank_select = pipe.bank, pipe.bank_select
        if to_verify and stored is not None:
            aux._stored_extractor = pipe.stored_extractor  # one extractor (its network loads once)
        elif to_verify:
            aux._matcher = pipe.matcher  # one matcher (a learned one loads its networks once) for every part
        # Only the references it was fitted on are searched, as every reference is for a real query.
        rest = [i for i in ids if refs[i].group not in out]
        index = index_of(aux, rest, (refs[i].features for i in rest))
        # Per located reference of the part, what its walk reuses: its codes, the references near it, and
        # (when it was located verified) its stored query features (None: it is verified from its photo).
        part_codes, part_near, part_verified = {}, {}, {}
        for i in part:
            r = refs[i]
            if aux.config.local is not None and r.features.n_local < MIN_LOCAL_FEATURES:
                continue
            codes = aux.encode_features(r.features, aux.select(r.features))  # once for every search
            part_codes[i] = codes
            # Its capture left out: its group, and every reference taken at the same spot (``capture_group``).
            own = sorted(set(by_group[r.group]) | set(by_spot[spot_of[i]]))
            t0 = time.perf_counter()
            rgb = query = None
            if i in to_verify and stored is not None:
                query = stored.query(i)
            elif i in to_verify:
                rgb = _photo(aux, images[i])
            verify = rgb is not None or query is not None
            verified_refs += verify
            verified_seconds += time.perf_counter() - t0
            if verify:
                part_verified[i] = query
            part_near[i] = near_ids(refs, r.lat, r.lon, absent_radius_m)
            for absent, excluded in ((False, own), (True, own + part_near[i])):
                searched = Excluding(index, excluded)
                answer = locate_features(aux, searched, source, r.features, options, codes=codes)
                s = calibration_sample(answer, r.lat, r.lon, absent, group=r.group)
                if s is not None:
                    samples.append(s)
                if not verify:
                    continue
                t0 = time.perf_counter()
                answer = locate_features(
                    aux,
                    searched,
                    source,
                    r.features,
                    verified_options,
                    rgb,
                    codes=codes,
                    features_cache=features_cache,
                    stored=stored,
                    stored_query=query,
                )
                verified_seconds += time.perf_counter() - t0
                s = calibration_sample(answer, r.lat, r.lon, absent, group=r.group)
                if s is not None:
                    verified_samples.append(s)
        # The part's references with a time, as walks: each window located with all of its captures left out
        # (and, where every photo of it can be, verified too, for the verified rule's own disc).
        for window in walk_windows([i for i in part if i in part_codes], refs, times or {}):
            own = sorted({j for i in window for j in by_group[refs[i].group] + by_spot[spot_of[i]]})
            near = sorted({j for i in window for j in part_near[i]})
            verify = all(i in part_verified for i in window)
            if verify:  # each photo's verification input read once for both searches (a photo decoded again)
                t0 = time.perf_counter()
                inputs = {i: (None if stored is not None else _photo(aux, images[i]), part_verified[i]) for i in window}
                verified_seconds += time.perf_counter() - t0
            for absent, excluded in ((False, own), (True, own + near)):
                searched = Excluding(index, excluded)
                answers = [
                    locate_features(aux, searched, source, refs[i].features, options, codes=part_codes[i])
                    for i in window
                ]
                walks.append(WalkAnswers(window, answers, absent))
                if not verify:
                    continue
                t0 = time.perf_counter()
                answers = []
                for i in window:
                    rgb, query = inputs[i]
                    answers.append(
                        locate_features(
                            aux,
                            searched,
                            source,
                            refs[i].features,
                            verified_options,
                            rgb,
                            codes=part_codes[i],
                            features_cache=features_cache,
                            stored=stored,
                            stored_query=query,
                        )
                    )
                verified_walks.append(WalkAnswers(window, answers, absent))
                verified_seconds += time.perf_counter() - t0
    extent_m = collection_extent_m(refs)
    cal = fit_calibration(samples, seed, radius_rate, max_radius_m, extent_m)
    if times:
        cal.sequence_disc, cal.report["sequence"] = fit_walk_disc(
            cal, walks, refs, times, rate=radius_rate, max_radius_m=max_radius_m, extent_m=extent_m
        )
        if cal.calibrated:
            cal.note += f"; {walk_note(cal.sequence_disc, cal.report['sequence'])}"
    cal.references = sorted({hashes[i] for i in held if i in hashes}) if hashes else []
    cal.report["absent_radius_m"] = absent_radius_m
    cal.report["sampled"] = len(held)
    cal.report["auxiliary_fits"] = len(parts)
    if to_verify:
        verified = fit_calibration(verified_samples, seed, radius_rate, max_radius_m, extent_m)
        if times and verified.calibrated:
            verified.sequence_disc, verified.report["sequence"] = fit_walk_disc(
                verified, verified_walks, refs, times, rate=radius_rate, max_radius_m=max_radius_m, extent_m=extent_m
            )
        cal.report["verified_sampled"] = verified_refs  # those whose photo could be read
        # What locating them verified added to the calibration's time (the stored records made, included).
        cal.report["verified_seconds"] = round(verified_seconds, 1)
        how = "from stored features" if stored is not None else "with verification"
        if stored is not None:
            cal.report["verified_from"] = f"stored features ({stored.profile})"
        if verified.calibrated:
            verified.note = f"fitted on {verified_refs} references of this collection, located {how}"
            if "sequence" in verified.report:
                verified.note += f"; {walk_note(verified.sequence_disc, verified.report['sequence'])}"
            cal.verified = asdict(verified)
            which = "verified answers" if stored is not None else "verified answers (rerank)"
            cal.note += f"; {which} by their own rule, {verified_refs} located {how}"
            cal.report["verified_confident_p"] = verified.report.get("confident_p")
            cal.report["verified_brier"] = verified.report.get("brier")
        else:
            cal.report["verified"] = verified.note
    return cal


def _photo(pipe: Pipeline, path: Path | None, limits: ImageLimits | None = None) -> np.ndarray | None:
    """A reference's photo for verification, decoded as /locate decodes an upload (None when unreadable or
    unknown: that reference is then located without verification only)."""
    from app.engine.errors import GeolocError

    if path is None:
        return None
    try:
        return pipe.decode(Path(path).read_bytes(), limits).rgb
    except (OSError, GeolocError):
        return None
