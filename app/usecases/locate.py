"""The one locate path, for every face (/locate, `geoloc locate`, the evaluation, the benchmarks), so that
what the evaluation measures is what /locate serves.

``locate_features`` searches (restricted to a region when asked), verifies geometrically when asked, fuses
the estimate, then reads the candidates' metadata in one batched read. It works on anything that searches
(a live ``Collection`` or an in-memory ``ReferenceIndex``) and anything that knows the references (the
store, or the evaluation's rows), so the evaluation calls it unchanged.

The estimate rule, one for every face: fuse the first ``ESTIMATE_CANDIDATES`` candidates after the region
filter and verification, before ``min_score`` and before cutting to ``top_k``, so the estimate never
depends on how many candidates the caller asked for.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Protocol

import cv2
import numpy as np

from app.domain import Candidate, LocateAnswer, LocateOptions, RefInfo, Region
from app.engine.calibration import NO_FEATURES, NO_MATCH, NO_REFERENCES, Calibration, Decision
from app.engine.errors import GeolocError
from app.engine.estimate import Estimate, fuse_position
from app.engine.evidence import gather
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers.base import Matcher, Verification
from app.engine.matchers.fusion import FUSION_FLOOR, fused_score
from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.pipeline import Codes, Features, Pipeline
from app.engine.stored_features import StoredFeatures, StoredFeaturesError, decode
from app.engine.stored_verification import verify_stored
from app.storage.feature_files import FeatureFiles
from app.storage.store import ReferenceStore

log = logging.getLogger("geoloc.locate")

#: How many candidates the fused estimate is made of (after region filter and verification).
ESTIMATE_CANDIDATES = 10
#: The most references a search inside a circular region asks an index that filters by position for (its
#: bounding box's corners are dropped after the search; Milvus caps a search's limit at 16,384).
MAX_REGION_SEARCH = 4096
#: How many of the best candidates verification looks at.
VERIFIED_CANDIDATES = 10
#: Fewer local features than this (a plain sky, a blank wall, a black frame) and the photo has nothing to
#: recognise a place by: no candidates, no probabilities, reason ``no_features``. Only for configurations
#: with local features (a global-only one always has its one descriptor).
MIN_LOCAL_FEATURES = 8


class Searchable(Protocol):
    """An index to search (``ReferenceIndex``, a collection's, or one with references left out).
    ``holds_positions``: a region is searched as a ``box`` of positions the index filters by; otherwise as
    the ids the store finds in it (``allowed``)."""

    @property
    def holds_positions(self) -> bool: ...

    def check_mode(self, mode: str | None) -> str: ...

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed=None, box=None): ...


class ReferenceSource(Protocol):
    """What locate needs to know about references besides their codes."""

    def info(self, ids: Sequence[int]) -> dict[int, RefInfo]: ...

    def in_region(self, region: Region) -> np.ndarray: ...

    def image_bytes(self, ref_id: int) -> bytes | None: ...


class StoreReferences:
    """The data dir as a ``ReferenceSource``: every read is one batched query."""

    def __init__(self, store: ReferenceStore):
        self.store = store

    def info(self, ids: Sequence[int]) -> dict[int, RefInfo]:
        return {
            i: RefInfo(r.lat, r.lon, r.label, r.captured_at, r.heading) for i, r in self.store.get_many(ids).items()
        }

    def in_region(self, region: Region) -> np.ndarray:
        ids, lats, lons = self.store.in_bbox(region.bounding_box())
        return ids[region.contains(lats, lons)] if len(ids) else ids

    def image_bytes(self, ref_id: int) -> bytes | None:
        path = self.store.image_path(ref_id)
        try:
            return path.read_bytes() if path is not None else None
        except OSError:
            return None


class StoredFeaturesSource(Protocol):
    """Where the candidates' stored local features come from (``PipelineConfig.stored_features``)."""

    def stored_features(self, ids: Sequence[int]) -> dict[int, StoredFeatures]: ...


class StoredReferenceFeatures:
    """The data dir's stored features: the candidates' image names in one batched read, then one small file
    read each (never all in memory: ``app.storage.feature_files``)."""

    def __init__(self, store: ReferenceStore, files: FeatureFiles):
        self.store = store
        self.files = files

    def stored_features(self, ids: Sequence[int]) -> dict[int, StoredFeatures]:
        """Those of ``ids`` with a readable file; a missing one (not back-filled yet) or a corrupt one is left
        out, so its candidate is unverified rather than the request failed."""
        out = {}
        for i, ref in self.store.get_many(ids).items():
            data = self.files.read(ref.sha256)
            if data is None:
                continue
            try:
                out[i] = decode(data)
            except StoredFeaturesError as e:
                log.warning("reference %d: its stored features are unreadable (%s); left unverified", i, e)
        return out


class Excluding:
    """A ``Searchable`` that never returns ``excluded`` ids: a reference's own capture left out, or every
    reference near a place removed (calibration and the evaluation's simulated absent places). It asks the
    index for ``k`` more than it leaves out, so it costs what the excluded set costs, never a scan."""

    def __init__(self, index: Searchable, excluded):
        self.index = index
        self.excluded = np.asarray(sorted({int(i) for i in excluded}), np.int64)

    @property
    def holds_positions(self) -> bool:
        return self.index.holds_positions

    def check_mode(self, mode: str | None) -> str:
        return self.index.check_mode(mode)

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed=None, box=None):
        s, i = self.index.search(float_code, binary_code, k + len(self.excluded), mode, allowed, box)
        keep = ~np.isin(i, self.excluded)
        return s[keep][:k], i[keep][:k]


def search_positions(
    index: Searchable, refs: ReferenceSource, codes, n: int, mode: str, region: Region
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The best ``n`` references inside ``region`` on an index that holds positions: the index keeps to the
    region's bounding box, and a circle's corners are dropped here (the positions from ``refs``), asking for
    more while too few are left. Returns (scores, ids, whether the region holds no reference at all). A
    circle asks for twice ``n`` at first (its box is 4/pi of its area): one search, where asking for ``n``
    often came short and searched again."""
    box = region.bounding_box()
    k = n if region.bbox is not None else min(2 * n, MAX_REGION_SEARCH)
    while True:
        scores, ids = index.search(codes.float_, codes.binary, k, mode, box=box)
        exhausted = len(ids) < k
        if region.bbox is not None:  # the box is the region
            return scores, ids, exhausted and not len(ids)
        info = refs.info(ids)  # a reference deleted since is no position: left out, as the answer leaves it out
        at = np.array([(info[i].lat, info[i].lon) if i in info else (np.nan, np.nan) for i in ids.tolist()])
        inside = region.contains(at[:, 0], at[:, 1]) if len(at) else np.zeros(0, bool)
        if inside.sum() >= n or exhausted or k >= MAX_REGION_SEARCH:
            kept = np.flatnonzero(inside)[:n]
            return scores[kept], ids[kept], exhausted and not len(kept)
        k = min(4 * k, MAX_REGION_SEARCH)


# -- the one locate path --------------------------------------------------------------------------------
def verify_candidates(
    query_rgb: np.ndarray,
    ids: Sequence[int],
    refs: ReferenceSource,
    limits: ImageLimits,
    matcher: Matcher,
) -> dict[int, int | None]:
    """Inliers of the chosen geometry per candidate (0: too few matches, or no geometry); None where the
    pair could not be verified (image gone or undecodable, OpenCV refused the matches)."""
    return {
        i: None if v is None else v.inliers
        for i, v in verify_candidate_pairs(query_rgb, ids, refs, limits, matcher).items()
    }


def verify_candidate_pairs(
    query_rgb: np.ndarray,
    ids: Sequence[int],
    refs: ReferenceSource,
    limits: ImageLimits,
    matcher: Matcher,
    features_cache: dict[int, object] | None = None,
) -> dict[int, Verification | None]:
    """``verify_candidates`` with the whole outcome per pair (matches, both models' inliers), for the
    evaluation's analysis; None where the pair could not be verified.

    The query's features are computed once; each candidate's are recomputed from its stored image (most
    of what verification costs). Storing the strongest 480 keypoints at ingest (62 KB per
    reference; all 1,500 would take 193 KB) verified as well on penn and is the measured next step; this
    is the one place that would read them (docs/results.md, "Verification that works").

    ``features_cache`` (reference id -> its matcher features) keeps each candidate's features across calls:
    the calibration verifies hundreds of answers whose candidates recur, /locate never passes one."""
    q = matcher.features(query_rgb)
    out: dict[int, Verification | None] = {}
    feats: dict[int, object] = {}
    for i in ids:
        out[int(i)] = None
        if features_cache is not None and int(i) in features_cache:
            feats[int(i)] = features_cache[int(i)]
            continue
        data = refs.image_bytes(int(i))
        if data is None:
            continue
        try:
            feats[int(i)] = matcher.features(load_image(data, limits.stored()).rgb)
        except (cv2.error, GeolocError) as e:
            log.debug("verification of reference %s skipped: %s", i, e)
            continue
        if features_cache is not None:
            features_cache[int(i)] = feats[int(i)]
    # The candidates together: a matcher may batch them (``Matcher.match_many``); one that fails as a whole
    # leaves them all unverified, never the request failed.
    outcomes: dict[int, Verification] = {}
    try:
        outcomes = dict(zip(feats, matcher.match_many(q, list(feats.values())), strict=True))
    except (cv2.error, GeolocError) as e:
        log.debug("verification of references %s skipped: %s", list(feats), e)
    for i, v in outcomes.items():
        if v.error is not None:  # the pair could not be verified (USAC refused it): unverified, never an error
            log.debug("verification of reference %s skipped: %s", i, v.error)
        out[i] = None if v.error is not None else v
    return out


def verify_from_stored(
    query_rgb: np.ndarray | None,
    head: Sequence[tuple[int, float]],
    pipeline: Pipeline,
    stored: StoredFeaturesSource,
    query: PixelFeatures | None = None,
) -> dict[int, Verification | None]:
    """Verify the ``head`` candidates ((id, global score), retrieval order) against their stored features:
    the query's extracted once by the configuration's profile (or ``query``, extracted so already: the
    calibration and the evaluation locate one photo several times), the candidates' read from their files,
    all matched in one batch (``verify_stored``, with the profile's adaptive stop). None where a candidate
    was not verified: no stored file, another extractor's record, left out by the stop, or OpenCV refused it."""
    extractor = pipeline.stored_extractor
    if extractor is None:
        raise ValueError(f"configuration {pipeline.config.name} stores no local features")
    profile = extractor.profile
    ids = [i for i, _ in head]
    records = stored.stored_features(ids)
    given = [r if r is not None and r.kind == profile.kind else None for r in (records.get(i) for i in ids)]
    out: dict[int, Verification | None] = dict.fromkeys(ids)
    if not any(r is not None for r in given):
        return out
    try:
        q = query if query is not None else extractor.query(query_rgb)
        outcome = verify_stored(
            q, given, [s for _, s in head], profile.settings, profile.stop_margin, profile.fusion_floor
        )
    except (cv2.error, GeolocError) as e:
        log.debug("verification of references %s skipped: %s", ids, e)
        return out
    for i, v in zip(ids, outcome.verifications, strict=True):
        if v is not None and v.error is not None:
            log.debug("verification of reference %s skipped: %s", i, v.error)
        out[i] = None if v is None or v.error is not None else v
    return out


def order_by_verification(
    ranked: Sequence[tuple[int, float]], inliers: dict[int, int | None], floor: int = FUSION_FLOOR
) -> list[tuple[int, float]]:
    """(id, global score) pairs re-ordered by ``fused_score``; ties keep the retrieval order.

    Unverified candidates (None, 0 inliers, or not in ``inliers``) keep their global score, so verification
    only ever lifts a candidate and never reorders the unverified among themselves. The scores returned
    stay the global ones: calibration and the estimate are fitted on them."""
    by_fused = [(fused_score(s, inliers.get(i) or 0, floor=floor), n) for n, (i, s) in enumerate(ranked)]
    return [ranked[n] for _, n in sorted(by_fused, key=lambda p: (-p[0], p[1]))]


def locate_features(
    pipeline: Pipeline,
    index: Searchable,
    refs: ReferenceSource,
    features: Features,
    options: LocateOptions,
    query_rgb: np.ndarray | None = None,
    limits: ImageLimits | None = None,
    cluster_radius_m: float = 25.0,
    codes: Codes | None = None,
    features_cache: dict[int, object] | None = None,
    calibration: Calibration | None = None,
    stored: StoredFeaturesSource | None = None,
    stored_query: PixelFeatures | None = None,
) -> LocateAnswer:
    """Search, verify, fuse, shape. ``query_rgb`` is needed only for verification (``options.rerank``, the public
    option's name; None: verified when the configuration stores local features).
    ``stored``: the candidates' stored local features; with a configuration that stores them, verification
    reads them (``verify_from_stored``) instead of re-extracting each candidate with the matcher.
    ``calibration``: the rule that judges this collection (``Collection.calibration``), else the pipeline's.
    ``codes``: the features already encoded by ``pipeline`` (calibration and the evaluation locate one photo
    twice, its place present and absent: the second search reuses the first's codes). ``features_cache``:
    the references' matcher features kept across calls (``verify_candidate_pairs``). ``stored_query``: the
    query's features by the configuration's stored profile, extracted already (``verify_from_stored``)."""
    mode = index.check_mode(options.mode)
    profile = pipeline.config.stored_features
    verify = options.rerank if options.rerank is not None else profile is not None
    t: dict[str, float] = {}
    allowed = None
    if options.region is not None and not index.holds_positions:
        t0 = time.perf_counter()
        allowed = refs.in_region(options.region)
        t["region"] = (time.perf_counter() - t0) * 1000
    if pipeline.config.local is not None and features.n_local < MIN_LOCAL_FEATURES:
        return _featureless(pipeline, features, mode, t)
    if codes is None:
        codes = pipeline.encode_features(features, pipeline.select(features))
    t.update(codes.timings_ms)
    n = max(options.top_k, ESTIMATE_CANDIDATES)
    t0 = time.perf_counter()
    region_empty = allowed is not None and len(allowed) == 0
    if region_empty:
        scores, ids = np.zeros(0, np.float32), np.zeros(0, np.int64)
    elif options.region is not None and allowed is None:
        scores, ids, region_empty = search_positions(index, refs, codes, n, mode, options.region)
    else:
        scores, ids = index.search(codes.float_, codes.binary, n, mode, allowed)
    t["search"] = (time.perf_counter() - t0) * 1000
    t0 = time.perf_counter()
    info = refs.info(ids)
    t["metadata"] = (time.perf_counter() - t0) * 1000
    ranked = [(int(i), float(s)) for i, s in zip(ids, scores, strict=True) if int(i) in info]
    inliers: dict[int, int | None] = {}
    verification: dict[int, Verification | None] = {}
    if verify and ranked:
        from_stored = profile is not None and stored is not None
        if query_rgb is None and not (from_stored and stored_query is not None):
            raise ValueError("verification needs the query image")
        t0 = time.perf_counter()
        floor = FUSION_FLOOR
        if from_stored:
            verification = verify_from_stored(query_rgb, ranked[:VERIFIED_CANDIDATES], pipeline, stored, stored_query)
            floor = pipeline.stored_extractor.profile.fusion_floor
        else:
            head = [i for i, _ in ranked[:VERIFIED_CANDIDATES]]
            verification = verify_candidate_pairs(
                query_rgb, head, refs, limits or ImageLimits(), pipeline.matcher, features_cache
            )
        inliers = {i: None if v is None else v.inliers for i, v in verification.items()}
        ranked = order_by_verification(ranked, inliers, floor)
        t["rerank"] = (time.perf_counter() - t0) * 1000  # the public timing's name: verification
    t0 = time.perf_counter()
    fused = ranked[:ESTIMATE_CANDIDATES]
    estimate = fuse_position(
        np.array([info[i].lat for i, _ in fused]),
        np.array([info[i].lon for i, _ in fused]),
        np.array([s for _, s in fused]),
        cluster_radius_m,
    )
    fused_ids = [i for i, _ in fused]
    evidence = gather(
        np.array([info[i].lat for i in fused_ids]),
        np.array([info[i].lon for i in fused_ids]),
        np.array([s for _, s in fused]),
        verification if verify else None,
        fused_ids,
    )
    # A verified answer is judged by the rule fitted on verified answers, when the collection has one.
    calibration = (calibration or pipeline.calibration).for_answer(verify)
    if mode != index.check_mode(None) and calibration.calibrated:
        # The calibration located its sample in the default mode: another mode's scores (Hamming similarities
        # in binary mode) are on another scale, and reading them through it would invent probabilities.
        calibration = Calibration.conservative(f"this collection is calibrated for {index.check_mode(None)} search")
    decision = calibration.decide(evidence, estimate)
    if options.region is not None and decision.code == NO_MATCH:  # the references searched: the region's only
        decision = replace(
            decision, reason=decision.reason.replace("no reference looks", "no reference in the requested region looks")
        )
    probability = {} if decision.p_within is None else dict(zip(fused_ids, decision.p_within, strict=True))
    t["estimate"] = (time.perf_counter() - t0) * 1000
    if region_empty:
        decision = Decision(False, NO_REFERENCES, "no references in the requested region", None, None)
    if decision.confident and decision.radius_m is not None:  # the collection's disc, and its rate
        estimate = replace(estimate, radius_m=decision.radius_m, radius_rate=decision.radius_rate)
    reason = decision.reason if not decision.confident else None
    confident = estimate if decision.confident else None
    shown = [(i, s) for i, s in ranked if s >= options.min_score][: options.top_k]
    candidates = [
        Candidate(
            reference_id=i,
            lat=info[i].lat,
            lon=info[i].lon,
            score=s,
            label=info[i].label,
            captured_at=info[i].captured_at,
            heading=info[i].heading,
            inliers=inliers.get(i) if verify else None,
            p_within_25m=round(float(probability[i]), 4) if i in probability else None,
            distance_m=float(haversine_m(confident.lat, confident.lon, info[i].lat, info[i].lon))
            if confident
            else None,
        )
        for i, s in shown
    ]
    return LocateAnswer(
        candidates=candidates,
        estimate=estimate,
        reason=reason,
        reason_code=None if decision.confident else decision.code,
        mode=mode,
        config=pipeline.config.name,
        features_extracted=codes.features_extracted,
        features_kept=codes.features_kept,
        timings_ms=t,
        verification=verification,
        evidence=evidence,
        answer_p=decision.answer_p,
    )


def _featureless(pipeline: Pipeline, features: Features, mode: str, t: dict[str, float]) -> LocateAnswer:
    """The answer for a photo without usable features: nothing is searched, so nothing is claimed."""
    n = features.n_local
    return LocateAnswer(
        candidates=[],
        estimate=Estimate(None, None, None, 0.0, "no features"),
        reason=f"no usable features: {n} distinctive points found in the photo ({MIN_LOCAL_FEATURES} needed); it "
        "may be blank, dark or blurred",
        reason_code=NO_FEATURES,
        mode=mode,
        config=pipeline.config.name,
        features_extracted=n,
        features_kept=n,
        timings_ms={**features.timings_ms, **t},
    )
