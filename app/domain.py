"""The application's value types: what a locate asks and answers, what an upload and an edit carry.

A reference's editable fields (lat, lon, heading, captured_at, label) are declared once, here, as
``ReferenceFields``: their names, types and bounds. The API's models (app/api/schemas.py) subclass it,
``ReferenceEdit`` is a PATCH (the update path), and ``Upload`` takes its
field names from it. The stored row is ``app.storage.store.Reference``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, make_dataclass
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from app.engine.errors import InvalidPosition
from app.engine.estimate import Estimate
from app.engine.evidence import Evidence
from app.engine.geo import haversine_m, valid_position
from app.engine.matchers.base import Verification
from app.errors import InvalidRequest
from app.text import CAPTURED_AT_MAX, LABEL_MAX, iso_captured_at, readable


# -- locate: the request and the answer ------------------------------------------------------------------
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
            # One fault, one code: a latitude or longitude out of range is invalid_position wherever it comes.
            if not all(math.isfinite(v) for v in self.bbox) or not (
                valid_position(min_lat, min_lon) and valid_position(max_lat, max_lon)
            ):
                raise InvalidPosition("bbox is out of range (lat -90..90, lon -180..180)")
            if min_lon > max_lon or min_lat > max_lat:
                raise InvalidRequest("bbox is inverted (min must not exceed max)")
            return
        if not all(v is not None for v in (self.lat, self.lon, self.radius_m)):
            raise InvalidRequest("a circular region needs lat, lon and radius_m together")
        if not valid_position(self.lat, self.lon):
            raise InvalidPosition(f"region centre {self.lat},{self.lon} is out of range (lat -90..90, lon -180..180)")
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
    #: Verify the top candidates (the public option keeps its old name). None: the configuration's default,
    #: verified when it stores local features (``PipelineConfig.stored_features``), else not.
    rerank: bool | None = None
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
    """What a locate found, unrounded. Its JSON (/locate, `geoloc locate`) is ``app.api.schemas.LocateOut``."""

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
    #: The verification outcome per verified candidate (with ``rerank`` only): not in the JSON, for the evaluation.
    verification: dict[int, Verification | None] = field(default_factory=dict)
    #: The reason code a client branches on (``app.engine.calibration``: no_match, ambiguous, no_features,
    #: no_references); None when confident.
    reason_code: str | None = None
    #: The fused candidates' evidence and the best p of the estimate's group (calibration, evaluation).
    evidence: Evidence | None = None
    answer_p: float | None = None
    #: The collection's extent (min_lon, min_lat, max_lon, max_lat), set by the service.
    extent: tuple[float, float, float, float] | None = None

    @property
    def confident_estimate(self) -> Estimate | None:
        return self.estimate if self.reason is None else None


# -- a reference's editable fields: declared once ----------------------------------------------------------
Heading = Annotated[float, Field(ge=0, lt=360)]
Label = Annotated[str, Field(max_length=LABEL_MAX), AfterValidator(readable)]
#: ISO 8601, stored in its extended form (``app.text.iso_captured_at``: EXIF's form is converted).
CapturedAt = Annotated[
    str,
    Field(
        max_length=CAPTURED_AT_MAX,
        description="ISO 8601 date or date-time, e.g. 2024-09-23T16:08:20; a zone (+02:00, Z) is optional",
    ),
    AfterValidator(readable),
    AfterValidator(iso_captured_at),
]


class ReferenceFields(BaseModel):
    """A reference's writable fields as a client gives them: the one model for the form fields of
    POST /references, each item of its ``metadata`` and (with ranges on the position) PATCH.

    Strict: a boolean is not a number and an object is not a string (lax mode stores ``true`` as 1.0).
    The range of lat/lon is checked by the core, for an upload and an edit alike (``invalid_position``, as for
    EXIF positions and a region's centre): one fault, one code, on every route."""

    model_config = ConfigDict(extra="forbid", strict=True)

    lat: float | None = Field(None, description="degrees in [-90, 90] (else 422 invalid_position)")
    lon: float | None = Field(None, description="degrees in [-180, 180] (else 422 invalid_position)")
    heading: Heading | None = None
    captured_at: CapturedAt | None = None
    label: Label | None = None


#: The names of a reference's editable fields, in their declared order.
REFERENCE_FIELDS: tuple[str, ...] = tuple(ReferenceFields.model_fields)


class ReferenceEdit(ReferenceFields):
    """An edit of a reference's metadata: every field optional; only those given change (a None heading,
    label or capture time clears it; a position can be changed, never cleared, and its range is checked by
    ``GeolocService.update``, like an upload's)."""

    @property
    def given(self) -> dict[str, Any]:
        """The fields the caller set, with their values."""
        return {name: getattr(self, name) for name in REFERENCE_FIELDS if name in self.model_fields_set}


# -- uploads ---------------------------------------------------------------------------------------------
Upload = make_dataclass(
    "Upload",
    [("data", bytes), ("filename", str | None, None), *((name, Any, None) for name in REFERENCE_FIELDS)],
)
Upload.__module__ = __name__
Upload.__doc__ = """One image to add: its bytes, its file name, and the reference's fields as given
    (``REFERENCE_FIELDS``, in that order; not validated yet: ``app.ingestion.uploads.prepare_upload`` does, naming the
    image). A position of None reads it from the photo's EXIF."""


@dataclass(frozen=True)
class Accepted:
    job_id: str
    reference_ids: list[int]
    duplicates: list[bool]
    #: One line per duplicate whose upload asked for other metadata than the stored reference has.
    notes: list[str] = field(default_factory=list)
