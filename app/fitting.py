"""The fitting rules, once, for ``geoloc fit``, ``geoloc refit``, the first start of an empty data dir and the
evaluation: where the SVM bank learns by default, which requests are refused, and how a pipeline and its
bank are fitted against the references.

Why one module: the three faces used to decide these each in their own words, and a rule changed in one
(say, "a configuration without local features has no bank") silently stayed old in the others, so what
the evaluation measured was not what `fit` built.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from app.domain import LocateAnswer, LocateOptions, RefInfo, Region
from app.engine.calibration import MIN_QUERIES, Calibration, Sample, fit_calibration
from app.engine.configs import PipelineConfig
from app.engine.geo import haversine_m
from app.engine.index.references import ReferenceIndex
from app.engine.learned_whitening import Place
from app.engine.pipeline import Features, Pipeline
from app.engine.svm_bank import KINDS, BankParams, SvmBank
from app.engine.training.svm_training import BANK_SOURCES, Geotagged, fit_bank_from, index_of
from app.errors import FitRefused
from app.runtime import fit_threads

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


def fit_pipeline(
    pipe: Pipeline,
    features: Sequence[Features],
    refs: dict[int, Geotagged],
    train: Sequence[Geotagged],
    source: str,
    kind: str = "contrastive",
    seed: int = 0,
    calibration_sample: int | None = None,
    images: Mapping[int, Path] | None = None,
    hashes: Mapping[int, str] | None = None,
    seconds: dict[str, float] | None = None,
    places: Sequence[Place | None] | None = None,
) -> Pipeline:
    """Fit ``pipe`` (codebook, PCA-whitening, binariser) on ``features`` (every photo it learns from), then,
    unless ``source`` is ``none``, its SVM bank from ``refs`` (the references, by id) and ``train`` (geotagged
    photos that are not references), then its confidence rule and ``p_within_25m`` on ``refs``
    (``calibrate_collection``, at most ``calibration_sample`` of them located; with ``images``, the references'
    photos, also the rule for verified answers; ``hashes``, the sha256 of each reference's photo, recorded with
    the calibration): what `geoloc fit` and the first start of an empty data dir both run. ``seconds`` gets
    each step's time (``codebook, PCA, binariser``, ``SVM bank``, ``calibration``): where a fit's time goes.
    ``places``: where each of ``features`` was taken (a configuration with learned whitening learns from
    their GPS pairs)."""
    check_bank_kind(kind)
    seconds = {} if seconds is None else seconds
    with fit_threads():  # one BLAS and OpenMP thread: the same fit on any machine (app.runtime)
        t0 = time.perf_counter()
        pipe.fit(list(features), seed=seed, places=places)
        seconds["codebook, PCA, binariser"] = time.perf_counter() - t0
        if source != "none":
            t0 = time.perf_counter()
            pipe.bank = train_bank(pipe, refs, list(train), source, kind, seed)
            seconds["SVM bank"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pipe.calibration = calibrate_collection(
            pipe,
            refs,
            [t.features for t in train],
            CALIBRATION_SAMPLE if calibration_sample is None else calibration_sample,
            seed=seed,
            images=images,
            hashes=hashes,
        )
        seconds["calibration"] = time.perf_counter() - t0
    return pipe


# -- calibration on the collection itself -------------------------------------------------------------------
#: References located against the others to calibrate (like the SVM bank's sample: the cost of a fit or a
#: refit does not grow with the collection past it).
CALIBRATION_SAMPLE = 600
#: Of those, how many are located once more with verification (``--calibrate-rerank``) for the rule that
#: judges verified answers: each costs its own photo's matcher features and up to 20 verified pairs (the
#: candidates' features are computed once per reference), about 0.2 s with RootSIFT on 2 cores.
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


def calibration_sample(answer: LocateAnswer, lat: float, lon: float, absent: bool, radius_m: float = 25.0):
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
    return Sample(ev, within, members, bool(haversine_m(lat, lon, e.lat, e.lon) <= radius_m), absent)


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
) -> Calibration:
    """The confidence rule and ``p_within_25m`` for ``pipe`` (fitted, with its bank), fitted on the collection
    ``refs`` itself.

    Why a second, auxiliary fit: a reference that was in the sample the codebook and the PCA-whitening were
    fitted on scores lower against the other references than any new photo does (full whitening spreads its
    own sample apart: 0.556 against 0.628 on penn-campus-gps), so a rule learned from references located
    against each other under ``pipe`` did not hold for real queries (held-out Brier 0.352, never confident).
    So a held-out set of captures (``calibration_holdout``) is left out of an auxiliary fit of the same
    configuration on the rest (plus ``extra``, the other photos ``pipe`` was fitted on), sharing ``pipe``'s
    SVM bank; every reference is encoded by it, and each held-out reference is located through
    ``app.locate.locate_features`` (the path /locate serves) with its own capture left out (the place is
    present, when another capture shows it) and with every reference within ``absent_radius_m`` removed
    (the place is absent). Cost: one more fit and one encoding of ``refs`` (the refit's sample, bounded),
    plus two searches per held-out reference (at most ``sample``).

    ``images`` (reference id -> its photo): the first ``verify_sample`` held-out references are located
    twice more with verification by the configuration's matcher (their place present and absent), and a
    second rule is fitted on those verified answers (``Calibration.verified``), which /locate applies to
    answers with ``rerank``: verification's evidence then counts in ``p_within_25m`` and the confidence.

    ``hashes`` (reference id -> the sha256 of its photo): recorded as ``Calibration.references`` (those of the
    located sample), so that a data dir judged by this pipeline can tell whether the figures are its own."""
    from app.locate import ESTIMATE_CANDIDATES, MIN_LOCAL_FEATURES, Excluding, locate_features

    ids = sorted(refs)
    parts = calibration_parts(refs, sample, seed)
    held = sum(parts, [])
    if len(held) < MIN_QUERIES:
        return Calibration.conservative(
            f"the collection is too small to calibrate ({len(held)} references sampled; at least {MIN_QUERIES} needed)",
            {"sampled": len(held), "too_small": True},
        )
    by_group: dict[str, list[int]] = {}
    for i in ids:
        by_group.setdefault(refs[i].group, []).append(i)
    source = GeotaggedReferences(refs, dict(images) if images else None)
    options = LocateOptions(top_k=ESTIMATE_CANDIDATES, rerank=False)  # the unverified rule, whatever the default
    verified_options = LocateOptions(top_k=ESTIMATE_CANDIDATES, rerank=True)
    to_verify = set([i for i in held if i in images][: max(0, verify_sample)] if images else [])
    features_cache = BoundedCache(FEATURES_KEPT)
    samples, verified_samples, verified_refs = [], [], 0
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
        if to_verify:
            aux._matcher = pipe.matcher  # one matcher (a learned one loads its networks once) for every part
        # Only the references it was fitted on are searched, as every reference is for a real query.
        rest = [i for i in ids if refs[i].group not in out]
        index = index_of(aux, rest, (refs[i].features for i in rest))
        for i in part:
            r = refs[i]
            if aux.config.local is not None and r.features.n_local < MIN_LOCAL_FEATURES:
                continue
            codes = aux.encode_features(r.features, aux.select(r.features))  # once for both searches
            own = by_group[r.group]
            rgb = _photo(aux, images[i]) if i in to_verify else None
            verified_refs += rgb is not None
            for absent, excluded in ((False, own), (True, own + near_ids(refs, r.lat, r.lon, absent_radius_m))):
                searched = Excluding(index, excluded)
                answer = locate_features(aux, searched, source, r.features, options, codes=codes)
                s = calibration_sample(answer, r.lat, r.lon, absent)
                if s is not None:
                    samples.append(s)
                if rgb is None:
                    continue
                answer = locate_features(
                    aux, searched, source, r.features, verified_options, rgb, codes=codes, features_cache=features_cache
                )
                s = calibration_sample(answer, r.lat, r.lon, absent)
                if s is not None:
                    verified_samples.append(s)
    cal = fit_calibration(samples, seed)
    cal.references = sorted({hashes[i] for i in held if i in hashes}) if hashes else []
    cal.report["absent_radius_m"] = absent_radius_m
    cal.report["sampled"] = len(held)
    cal.report["auxiliary_fits"] = len(parts)
    if to_verify:
        verified = fit_calibration(verified_samples, seed)
        cal.report["verified_sampled"] = verified_refs  # those whose photo could be read
        if verified.calibrated:
            verified.note = f"fitted on {verified_refs} references of this collection, located with verification"
            cal.verified = asdict(verified)
            cal.note += f"; verified answers (rerank) by their own rule, {verified_refs} located with verification"
            cal.report["verified_confident_p"] = verified.report.get("confident_p")
            cal.report["verified_brier"] = verified.report.get("brier")
        else:
            cal.report["verified"] = verified.note
    return cal


def _photo(pipe: Pipeline, path: Path) -> np.ndarray | None:
    """A reference's photo for verification, decoded as /locate decodes an upload (None when unreadable:
    that reference is then located without verification only)."""
    from app.engine.errors import GeolocError

    try:
        return pipe.decode(Path(path).read_bytes()).rgb
    except (OSError, GeolocError):
        return None
