"""The application core: the use cases every face of the product calls (HTTP routes, the CLI, the
evaluation, the benchmarks), so that what the evaluation measures is what /locate serves.

- ``locate_features`` is the one locate path: search (restricted to a region when asked), optional
  geometric verification, the fused estimate, then the candidates' metadata in one batched read. It works
  on anything that searches (a live ``Collection`` or an in-memory ``ReferenceIndex``) and anything that
  knows the references (the store, or the evaluation's rows), so the evaluation calls it unchanged.
- ``GeolocService`` binds it to a data dir and adds the other use cases: accept uploads (validated, then
  stored in bulk as pending rows with their job), encode, complete, delete, list, get.

The estimate rule, one for every face: fuse the first ``ESTIMATE_CANDIDATES`` candidates after the region
filter and verification, before ``min_score`` and before cutting to ``top_k``, so the estimate never
depends on how many candidates the caller asked for.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Protocol

import cv2
import numpy as np

from app.collection import Collection, SnapshotPolicy
from app.encoding.items import Encoded, EncodeItem, encode_item
from app.engine import rerank as rerank_mod
from app.engine.calibration import candidate_probabilities
from app.engine.errors import GeolocError, InvalidPosition, NoGpsInImage
from app.engine.estimate import Estimate, fuse_position
from app.engine.geo import haversine_m, valid_position
from app.engine.imageio import ImageLimits, LoadedImage, load_image
from app.engine.models.base import Matcher
from app.engine.models.registry import build_matcher
from app.engine.pipeline import Features, Pipeline
from app.errors import InvalidRequest, StorageUnavailable
from app.runtime import release_free_memory
from app.store import NewReference, Reference, ReferenceStore, is_storage_error
from app.text import CAPTURED_AT_MAX, LABEL_MAX, unsafe_character

log = logging.getLogger("geoloc.core")

#: The matcher of callers that verify without a pipeline (tests, the evaluation's analysis).
DEFAULT_MATCHER = "sift-mnn"

#: How many candidates the fused estimate is made of (after region filter and verification).
ESTIMATE_CANDIDATES = 10
#: How many of the best candidates geometric verification looks at.
RERANK_CANDIDATES = 10


# -- requests and answers -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Region:
    """A circle (lat, lon, radius_m) or a bbox (min_lon, min_lat, max_lon, max_lat)."""

    lat: float | None = None
    lon: float | None = None
    radius_m: float | None = None
    bbox: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        if self.bbox is not None:
            if any(v is not None for v in (self.lat, self.lon, self.radius_m)):
                raise InvalidRequest("give either bbox or lat+lon+radius_m, not both")
            min_lon, min_lat, max_lon, max_lat = self.bbox
            if (
                not all(math.isfinite(v) for v in self.bbox)
                or not (valid_position(min_lat, min_lon) and valid_position(max_lat, max_lon))
                or min_lon > max_lon
                or min_lat > max_lat
            ):
                raise InvalidRequest("bbox is out of range or inverted (min must not exceed max)")
            return
        if not all(v is not None for v in (self.lat, self.lon, self.radius_m)):
            raise InvalidRequest("a circular region needs lat, lon and radius_m together")
        if not valid_position(self.lat, self.lon):
            raise InvalidRequest(f"region centre {self.lat},{self.lon} is out of range")
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise InvalidRequest("radius_m must be a positive number of metres")

    def bounding_box(self) -> tuple[float, float, float, float]:
        if self.bbox is not None:
            return self.bbox
        dlat = self.radius_m / 111_320
        dlon = self.radius_m / (111_320 * max(math.cos(math.radians(self.lat)), 1e-6))
        return self.lon - dlon, self.lat - dlat, self.lon + dlon, self.lat + dlat

    def contains(self, lats: np.ndarray, lons: np.ndarray) -> np.ndarray:
        if self.bbox is not None:
            min_lon, min_lat, max_lon, max_lat = self.bbox
            return (lats >= min_lat) & (lats <= max_lat) & (lons >= min_lon) & (lons <= max_lon)
        return haversine_m(self.lat, self.lon, lats, lons) <= self.radius_m


@dataclass(frozen=True)
class LocateOptions:
    top_k: int = 10
    mode: str | None = None
    rerank: bool = False
    region: Region | None = None
    min_score: float = 0.0


@dataclass(frozen=True)
class RefInfo:
    """What a candidate carries besides its score."""

    lat: float
    lon: float
    label: str | None = None
    captured_at: str | None = None
    heading: float | None = None


@dataclass(frozen=True)
class Candidate:
    reference_id: int
    lat: float
    lon: float
    score: float
    label: str | None = None
    captured_at: str | None = None
    heading: float | None = None
    inliers: int | None = None  # geometric verification, when asked (None: not verified)
    p_within_25m: float | None = None  # calibrated probability that it lies within 25 m of the photo
    distance_m: float | None = None  # from the confident estimate


@dataclass
class LocateAnswer:
    candidates: list[Candidate]
    estimate: Estimate  # the fused position, confident or not (the evaluation measures both)
    reason: str | None  # why there is no confident estimate; None when there is one
    mode: str
    config: str
    features_extracted: int
    features_kept: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    index_size: int = 0
    index_version: int = 0
    index_generation: int = 0
    #: The verification outcome per verified candidate (rerank only): not in the JSON, for the evaluation.
    verification: dict[int, rerank_mod.Verification | None] = field(default_factory=dict)

    @property
    def confident_estimate(self) -> Estimate | None:
        return self.estimate if self.reason is None else None

    def as_dict(self) -> dict:
        """The JSON shape shared by /locate and `geoloc locate`."""
        e = self.confident_estimate
        return {
            "candidates": [
                {
                    "reference_id": c.reference_id,
                    "lat": c.lat,
                    "lon": c.lon,
                    "score": round(c.score, 6),
                    "distance_m": c.distance_m,
                    "label": c.label,
                    "captured_at": c.captured_at,
                    "heading": c.heading,
                    "inliers": c.inliers,
                    "p_within_25m": c.p_within_25m,
                }
                for c in self.candidates
            ],
            "estimate": None
            if e is None
            else {"lat": e.lat, "lon": e.lon, "radius_m": e.radius_m, "confidence": e.confidence},
            "reason": self.reason,
            "mode": self.mode,
            "config": self.config,
            "features": {"extracted": self.features_extracted, "kept": self.features_kept},
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
            "index": {"size": self.index_size, "version": self.index_version, "generation": self.index_generation},
        }


class Searchable(Protocol):
    def check_mode(self, mode: str | None) -> str: ...

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed=None): ...


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


# -- the one locate path --------------------------------------------------------------------------------
def verify_candidates(
    query_rgb: np.ndarray,
    ids: Sequence[int],
    refs: ReferenceSource,
    limits: ImageLimits,
    matcher: Matcher | None = None,
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
    matcher: Matcher | None = None,
) -> dict[int, rerank_mod.Verification | None]:
    """``verify_candidates`` with the whole outcome per pair (matches, both models' inliers), for the
    evaluation's analysis; None where the pair could not be verified.

    The query's RootSIFT is computed once; each candidate's is recomputed from its stored image (about
    0.1 s each, most of what rerank costs). Storing the strongest 480 keypoints at ingest (62 KB per
    reference; all 1,500 would take 193 KB) verified as well on penn and is the measured next step; this
    is the one place that would read them (docs/RESULTS.md, "Verification that works")."""
    matcher = matcher or build_matcher(DEFAULT_MATCHER)
    q = matcher.features(query_rgb)
    out: dict[int, rerank_mod.Verification | None] = {}
    for i in ids:
        data = refs.image_bytes(int(i))
        if data is None:
            out[int(i)] = None
            continue
        try:
            v = matcher.match(q, matcher.features(load_image(data, limits).rgb))
        except (cv2.error, GeolocError) as e:
            log.debug("verification of reference %s skipped: %s", i, e)
            out[int(i)] = None
            continue
        if v.error is not None:  # both fits refused by USAC: unverified, never an error
            log.debug("verification of reference %s skipped: %s", i, v.error)
        out[int(i)] = None if v.error is not None else v
    return out


def order_by_verification(
    ranked: Sequence[tuple[int, float]], inliers: dict[int, int | None]
) -> list[tuple[int, float]]:
    """(id, global score) pairs re-ordered by ``rerank.fused_score``; ties keep the retrieval order.

    Unverified candidates (None, 0 inliers, or not in ``inliers``) keep their global score, so verification
    only ever lifts a candidate and never reorders the unverified among themselves. The scores returned
    stay the global ones: calibration and the estimate are fitted on them."""
    by_fused = [(rerank_mod.fused_score(s, inliers.get(i) or 0), n) for n, (i, s) in enumerate(ranked)]
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
) -> LocateAnswer:
    """Search, verify, fuse, shape. ``query_rgb`` is needed only for verification (``options.rerank``)."""
    mode = index.check_mode(options.mode)
    t: dict[str, float] = {}
    allowed = None
    if options.region is not None:
        t0 = time.perf_counter()
        allowed = refs.in_region(options.region)
        t["region"] = (time.perf_counter() - t0) * 1000
    keep = pipeline.select(features)
    codes = pipeline.encode_features(features, keep)
    t.update(codes.timings_ms)
    n = max(options.top_k, ESTIMATE_CANDIDATES)
    t0 = time.perf_counter()
    if allowed is not None and len(allowed) == 0:
        scores, ids = np.zeros(0, np.float32), np.zeros(0, np.int64)
    else:
        scores, ids = index.search(codes.float_, codes.binary, n, mode, allowed)
    t["search"] = (time.perf_counter() - t0) * 1000
    t0 = time.perf_counter()
    info = refs.info(ids)
    t["metadata"] = (time.perf_counter() - t0) * 1000
    ranked = [(int(i), float(s)) for i, s in zip(ids, scores, strict=True) if int(i) in info]
    inliers: dict[int, int | None] = {}
    verification: dict[int, rerank_mod.Verification | None] = {}
    if options.rerank and ranked:
        if query_rgb is None:
            raise ValueError("verification needs the query image")
        t0 = time.perf_counter()
        head = [i for i, _ in ranked[:RERANK_CANDIDATES]]
        verification = verify_candidate_pairs(query_rgb, head, refs, limits or ImageLimits(), pipeline.matcher)
        inliers = {i: None if v is None else v.inliers for i, v in verification.items()}
        ranked = order_by_verification(ranked, inliers)
        t["rerank"] = (time.perf_counter() - t0) * 1000
    t0 = time.perf_counter()
    fused = ranked[:ESTIMATE_CANDIDATES]
    estimate = fuse_position(
        np.array([info[i].lat for i, _ in fused]),
        np.array([info[i].lon for i, _ in fused]),
        np.array([s for _, s in fused]),
        cluster_radius_m,
    )
    probability = dict(
        zip(
            [i for i, _ in fused],
            candidate_probabilities(
                [info[i].lat for i, _ in fused], [info[i].lon for i, _ in fused], [s for _, s in fused], estimate
            ),
            strict=True,
        )
    )
    t["estimate"] = (time.perf_counter() - t0) * 1000
    region_empty = allowed is not None and len(allowed) == 0
    reason = "no references in the requested region" if region_empty else estimate.reason
    confident = estimate if reason is None else None
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
            inliers=inliers.get(i) if options.rerank else None,
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
        mode=mode,
        config=pipeline.config.name,
        features_extracted=codes.features_extracted,
        features_kept=codes.features_kept,
        timings_ms=t,
        verification=verification,
    )


# -- uploads ----------------------------------------------------------------------------------------------
@dataclass
class Upload:
    """One image to add, with the position from fields (or None, to read it from the photo's EXIF)."""

    data: bytes
    filename: str | None = None
    lat: float | None = None
    lon: float | None = None
    heading: float | None = None
    captured_at: str | None = None
    label: str | None = None


@dataclass(frozen=True)
class Accepted:
    job_id: str
    reference_ids: list[int]
    duplicates: list[bool]
    #: One line per duplicate whose upload asked for other metadata than the stored reference has.
    notes: list[str] = field(default_factory=list)


def _differences(new: NewReference, old: Reference, asked: Upload | None) -> list[str]:
    """What the upload asked for (explicitly: not a label made from the file name) that differs."""
    out = []
    if abs(new.lat - old.lat) > 1e-7 or abs(new.lon - old.lon) > 1e-7:
        out.append(f"position {old.lat:.6f},{old.lon:.6f} (not {new.lat:.6f},{new.lon:.6f})")
    for name in ("heading", "label", "captured_at"):
        value = getattr(asked, name) if asked is not None else getattr(new, name)
        if value is not None and value != getattr(old, name):
            out.append(f"{name} {getattr(old, name)!r} (not {value!r})")
    return out


@dataclass(frozen=True)
class ReferenceEdit:
    """A PATCH: only the fields given change."""

    lat: float | None = None
    lon: float | None = None
    heading: float | None = None
    label: str | None = None
    captured_at: str | None = None
    given: frozenset[str] = frozenset()  # which fields the caller set (a None heading clears it)


def _position(u: Upload, img: LoadedImage, n: int) -> tuple[float, float]:
    if u.lat is None and u.lon is None:
        if img.gps is None:
            raise NoGpsInImage(f"image {n}: no lat/lon given and no GPS position in its EXIF")
        return img.gps
    if u.lat is None or u.lon is None:
        raise InvalidPosition(f"image {n}: give both lat and lon, or neither (to use the EXIF GPS)")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in (u.lat, u.lon)):
        raise InvalidPosition(f"image {n}: lat and lon must be numbers")  # True is not 1.0
    try:
        lat, lon = float(u.lat), float(u.lon)
    except OverflowError:  # an int of 400 digits
        raise InvalidPosition(f"image {n}: position {u.lat},{u.lon} is out of range") from None
    if not valid_position(lat, lon):
        raise InvalidPosition(f"image {n}: position {lat},{lon} is out of range (lat -90..90, lon -180..180)")
    return lat, lon


def label_from(filename: str | None) -> str | None:
    """The default label: the file's name, never a path ("../../x.jpg" -> "x.jpg"), cut to the label's length
    (a name is not something the caller typed as a label)."""
    if not filename:
        return None
    name = PurePosixPath(filename.replace("\\", "/")).name
    return name[:LABEL_MAX] or None


def _text(value, name: str, limit: int, n: int) -> str | None:
    """A text field as given (None stays None): a string, within its length, with no control character
    (``app.text``). Refused, never cut or converted: what is stored is what was asked for."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise InvalidRequest(f"image {n}: {name} must be a string")
    if len(value) > limit:
        raise InvalidRequest(f"image {n}: {name} has {len(value)} characters; the limit is {limit}")
    bad = unsafe_character(value)
    if bad is not None:
        raise InvalidRequest(f"image {n}: {name} contains the control character {bad}")
    return value


def _exif_text(value: str | None, limit: int) -> str | None:
    """A text the photo's EXIF gave: kept when it would pass as a field, else left out (the photo is fine)."""
    return value if value and len(value) <= limit and unsafe_character(value) is None else None


def prepare_upload(
    u: Upload, limits: ImageLimits, n: int = 0, source: str = "api", exif_heading: bool = False
) -> NewReference:
    """Validate one upload completely (decodable, within limits, with a position) before anything is stored.
    ``exif_heading``: with no heading given, take the photo's EXIF GPSImgDirection (bulk ingestion of a
    folder of photos, where EXIF is the only metadata there is)."""
    label = _text(u.label, "label", LABEL_MAX, n) or None
    captured_at = _text(u.captured_at, "captured_at", CAPTURED_AT_MAX, n) or None
    if label is None:
        label = _text(label_from(u.filename), "file name", LABEL_MAX, n)
    img = load_image(u.data, limits)
    lat, lon = _position(u, img, n)
    hd = u.heading if u.heading is not None or not exif_heading else img.heading
    if hd is not None and (
        isinstance(hd, bool) or not (isinstance(hd, int | float) and math.isfinite(hd) and 0 <= hd < 360)
    ):
        raise InvalidRequest(f"image {n}: heading must be a number in [0, 360)")
    return NewReference(
        image=u.data,
        ext=img.format.lower(),
        lat=lat,
        lon=lon,
        heading=hd,
        captured_at=captured_at or _exif_text(img.captured_at, CAPTURED_AT_MAX),
        label=label,
        source=source,
    )


# -- the service ------------------------------------------------------------------------------------------
class GeolocService:
    """The use cases over one data dir. Thread-safe: the HTTP layer calls it from a thread pool."""

    def __init__(self, collection: Collection, limits: ImageLimits | None = None, keep_queries: bool = False):
        self.collection = collection
        self.limits = limits or ImageLimits()
        self.keep_queries = keep_queries
        self.refs = StoreReferences(collection.store)

    @classmethod
    def open(
        cls,
        data_dir: Path,
        models_dir: Path,
        config: str | None,
        limits: ImageLimits | None = None,
        policy: SnapshotPolicy | None = None,
        keep_queries: bool = False,
    ) -> GeolocService:
        return cls(Collection.open(data_dir, models_dir, config, policy), limits, keep_queries)

    @property
    def store(self) -> ReferenceStore:
        return self.collection.store

    @property
    def pipeline(self) -> Pipeline:
        return self.collection.pipeline

    # -- locate ---------------------------------------------------------------------------------------
    def decode(self, data: bytes) -> LoadedImage:
        return load_image(data, self.limits)

    def extract(self, data: bytes) -> tuple[LoadedImage, Features, float]:
        """Decode and extract (the expensive, parallel part of a request); returns the decode time too."""
        t0 = time.perf_counter()
        img = self.decode(data)
        decode_ms = (time.perf_counter() - t0) * 1000
        features = self.pipeline.extract(img.rgb)
        self.release_memory(img)  # the decode and extraction buffers, before the next request in this slot
        return img, features, decode_ms

    def release_memory(self, img: LoadedImage) -> None:
        """After a large upload (decoded at reduced scale, a PNG at full size first), hand the buffers it
        freed back to the kernel: glibc keeps them in per-thread arenas, and with the server's thread pool
        8 concurrent 49 MP uploads left RSS 1.5 GB above idle for good (bench/locate_memory.py)."""
        if max(img.original_size) > 2 * self.limits.decode_long_side:
            release_free_memory()

    def locate_extracted(self, img: LoadedImage, features: Features, options: LocateOptions) -> LocateAnswer:
        """Search with one generation's pipeline and index taken together (a re-fit may swap them at any
        moment); features extracted under another configuration are extracted again."""
        col = self.collection
        col.catch_up()
        view = col.view()
        view.check_mode(options.mode)
        if features.config is not None and features.config != view.pipeline.config.name:
            features = view.pipeline.extract(img.rgb)
        answer = locate_features(view.pipeline, view, self.refs, features, options, img.rgb, self.limits)
        answer.index_size, answer.index_generation = view.index.size, view.generation
        answer.index_version = col.version if col.generation == view.generation else 0
        return answer

    def locate(self, data: bytes, options: LocateOptions) -> LocateAnswer:
        t0 = time.perf_counter()
        self.collection.check_mode(options.mode)  # a bad mode is refused before the expensive part
        img, features, decode_ms = self.extract(data)
        answer = self.locate_extracted(img, features, options)
        answer.timings_ms = {"decode": decode_ms, **answer.timings_ms, "total": (time.perf_counter() - t0) * 1000}
        self.keep_query(data, img)
        self.release_memory(img)
        return answer

    def keep_query(self, data: bytes, img: LoadedImage) -> None:
        if not self.keep_queries:
            return
        from app.permissions import private_dir
        from app.store import sha256_of, write_image_file

        try:
            folder = self.store.data_dir / "queries"
            private_dir(folder)
            write_image_file(folder / f"{sha256_of(data)}.{img.format.lower()}", data, sync=False)  # 0600
        except OSError as e:  # keeping queries is a courtesy; a full disk must not fail the answer
            log.warning("query not kept: %s", e)

    # -- accept, encode, complete -----------------------------------------------------------------------
    def accept(self, uploads: Sequence[Upload], source: str = "api") -> Accepted:
        """Validate every upload, then store them all (images durable, rows and job in one transaction) as
        pending rows. The index is not touched: the worker encodes them."""
        prepared = [prepare_upload(u, self.limits, n, source) for n, u in enumerate(uploads)]
        return self.accept_prepared(prepared, uploads)

    def accept_prepared(self, prepared: Sequence[NewReference], asked: Sequence[Upload] | None = None) -> Accepted:
        """Store; for identical images already stored, say when the upload's metadata was not applied."""
        items, job_id = self.store.add_many(prepared, job=True)
        dups = [(n, i) for n, (i, created) in enumerate(items) if not created]
        stored = self.store.get_many([i for _, i in dups]) if dups else {}
        notes = []
        for n, ref_id in dups:
            upload = asked[n] if asked is not None else None
            diff = _differences(prepared[n], stored[ref_id], upload) if ref_id in stored else []
            if diff:
                notes.append(
                    f"image {n} is already stored as reference {ref_id}; its stored metadata was kept: "
                    + "; ".join(diff)
                    + f". To change it: PATCH /references/{ref_id}"
                )
        return Accepted(job_id, [i for i, _ in items], [not created for _, created in items], notes)

    def update(self, ref_id: int, edit: ReferenceEdit) -> Reference | None:
        """Edit a reference's metadata (validated here; codes and image unchanged)."""
        fields = {k: getattr(edit, k) for k in edit.given}
        if not fields:
            raise InvalidRequest("give at least one of lat, lon, heading, label, captured_at")
        current = self.store.get(ref_id)
        if current is None:
            return None
        lat, lon = fields.get("lat", current.lat), fields.get("lon", current.lon)
        if lat is None or lon is None or not valid_position(lat, lon):
            raise InvalidPosition(f"position {lat},{lon} is out of range (lat -90..90, lon -180..180)")
        hd = fields.get("heading")
        if hd is not None and not (math.isfinite(hd) and 0 <= hd < 360):
            raise InvalidRequest("heading must be a number in [0, 360)")
        return self.store.update(ref_id, fields)

    def encode(self, batch: Sequence[tuple[int, Path]], workers: int = 1) -> list[Encoded]:
        if workers <= 1 or len(batch) <= 1:
            return [encode_item(self.pipeline, self.limits, EncodeItem(i, p)) for i, p in batch]
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(lambda b: encode_item(self.pipeline, self.limits, EncodeItem(*b)), batch))

    def complete(self, results: Sequence[Encoded]) -> list[int]:
        """Record a batch in one transaction (storage failures stay pending) and bring the index up to date.
        Results made by a pipeline the data dir no longer uses (a re-fit switched while they were encoded)
        are not recorded: their rows stay pending, and this process loads the new generation before
        returning, so the next batch is encoded by it."""
        by_pipeline: dict[str | None, list] = {}
        for r in results:
            if not r.retry:
                by_pipeline.setdefault(r.fingerprint, []).append((r.ref_id, r.float_code, r.binary_code, r.error))
        done: list[int] = []
        stale = False
        for fingerprint, final in by_pipeline.items():
            recorded = self.store.complete(final, fingerprint)
            stale |= fingerprint is not None and not recorded and any(e is None for *_, e in final)
            done += recorded
        if stale and self.store.get_meta("fingerprint") != self.pipeline.fingerprint:
            self.collection.refresh_generation(wait=True)
        self.collection.catch_up()
        return done

    # -- the rest ---------------------------------------------------------------------------------------
    def delete(self, ref_id: int) -> str | None:
        """None: no such reference; else whether its image file is ``"removed"`` or its removal ``"queued"``
        (the reference is gone either way: see ``ReferenceStore.delete``)."""
        outcome = self.store.delete(ref_id)
        if outcome is not None:
            self.collection.catch_up()  # gone from this process's searches at once
        return outcome

    def get(self, ref_id: int) -> Reference | None:
        return self.store.get(ref_id)

    def list(self, offset: int, limit: int, bbox=None) -> tuple[list[Reference], int]:
        return self.store.list(offset, limit, bbox)

    def job(self, job_id: str) -> dict | None:
        return self.store.job(job_id)

    def image_path(self, ref_id: int) -> Path | None:
        return self.store.image_path(ref_id)


__all__ = [
    "Accepted",
    "Candidate",
    "Encoded",
    "GeolocService",
    "InvalidRequest",
    "LocateAnswer",
    "LocateOptions",
    "RefInfo",
    "ReferenceEdit",
    "Region",
    "StorageUnavailable",
    "Upload",
    "is_storage_error",
    "locate_features",
]
