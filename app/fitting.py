"""The fitting rules, once, for ``geoloc fit``, ``geoloc refit`` and the evaluation: where the SVM bank
learns by default, which requests are refused, and how a bank is trained against the references.

Why one module: the three faces used to decide these each in their own words, and a rule changed in one
(say, "a configuration without local features has no bank") silently stayed old in the others, so what
the evaluation measured was not what `fit` built.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.domain import LocateAnswer, LocateOptions, RefInfo, Region
from app.engine.calibration import Calibration, Sample, fit_calibration
from app.engine.configs import PipelineConfig
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline
from app.engine.svm_bank import KINDS, BankParams, SvmBank
from app.engine.training.svm_training import BANK_SOURCES, Geotagged, fit_bank_from, index_of
from app.errors import FitRefused

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


# -- calibration on the collection itself -------------------------------------------------------------------
#: References located against the others to calibrate (like the SVM bank's sample: the cost of a fit or a
#: refit does not grow with the collection past it).
CALIBRATION_SAMPLE = 600
#: A place counts as absent when no reference lies within this many metres of it.
ABSENT_RADIUS_M = 100.0


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


def calibrate_collection(
    pipe: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    sample: int = CALIBRATION_SAMPLE,
    absent_radius_m: float = ABSENT_RADIUS_M,
    seed: int = 0,
    paths: dict[int, Path] | None = None,
    rerank: bool = False,
) -> Calibration:
    """Fit ``pipe.calibration`` on the collection ``refs`` (searched through ``index``, encoded by ``pipe``
    with its bank): each of a seeded sample of at most ``sample`` references is located through
    ``app.locate.locate_features``, the path /locate serves, against the others with its own capture left
    out (present) and with every reference within ``absent_radius_m`` removed (absent). ``rerank``: verify
    as /locate does with rerank=true (needs ``paths``), so the rule learns the verified evidence."""
    from app.locate import ESTIMATE_CANDIDATES, MIN_LOCAL_FEATURES, Excluding, locate_features

    ids = sorted(refs)
    rng = np.random.default_rng(seed)
    picked = sorted(rng.choice(ids, min(sample, len(ids)), replace=False).tolist()) if ids else []
    by_group: dict[str, list[int]] = {}
    for i in ids:
        by_group.setdefault(refs[i].group, []).append(i)
    source = GeotaggedReferences(refs, paths)
    samples = []
    for i in picked:
        r = refs[i]
        data = source.image_bytes(i) if rerank else None
        rgb = load_image(data).rgb if data is not None else None
        options = LocateOptions(top_k=ESTIMATE_CANDIDATES, rerank=rgb is not None)
        own = by_group[r.group]
        codes = None
        for absent, excluded in ((False, own), (True, own + near_ids(refs, r.lat, r.lon, absent_radius_m))):
            if codes is None and (pipe.config.local is None or r.features.n_local >= MIN_LOCAL_FEATURES):
                codes = pipe.encode_features(r.features, pipe.select(r.features))  # once for both searches
            answer = locate_features(pipe, Excluding(index, excluded), source, r.features, options, rgb, codes=codes)
            s = calibration_sample(answer, r.lat, r.lon, absent)
            if s is not None:
                samples.append(s)
    cal = fit_calibration(samples, seed)
    cal.report["absent_radius_m"] = absent_radius_m
    cal.report["sampled"] = len(picked)
    return cal
