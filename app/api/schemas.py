"""Response models: they are the API's documentation (/openapi.json) as much as its validation."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from app.text import CAPTURED_AT_MAX, LABEL_MAX, readable


class CandidateOut(BaseModel):
    reference_id: int
    lat: float
    lon: float
    score: float = Field(description="similarity in [0, 1], whatever the search mode")
    distance_m: float | None = Field(None, description="distance from the fused estimate")
    label: str | None = None
    captured_at: str | None = None
    heading: float | None = None
    inliers: int | None = Field(None, description="geometric verification inliers, when rerank=true")
    p_within_25m: float | None = Field(
        None,
        description="calibrated probability that this reference lies within 25 m of where the photo was taken "
        "(cross-validated on penn-campus-gps; given for the first 10 candidates)",
    )


class EstimateOut(BaseModel):
    lat: float
    lon: float
    radius_m: float
    confidence: float = Field(ge=0, le=1)


class FeaturesOut(BaseModel):
    extracted: int
    kept: int


class IndexOut(BaseModel):
    size: int
    version: int
    generation: int = Field(0, description="the index generation answering (a re-fit makes the next one)")


class LocateOut(BaseModel):
    candidates: list[CandidateOut]
    estimate: EstimateOut | None
    reason: str | None = Field(None, description="why there is no confident estimate")
    mode: str
    config: str
    features: FeaturesOut
    timings_ms: dict[str, float]
    index: IndexOut


class ReferenceOut(BaseModel):
    id: int
    lat: float
    lon: float
    heading: float | None
    captured_at: str | None
    label: str | None
    source: str | None
    created_at: str
    status: str = Field(description="pending (accepted, being encoded), indexed, or failed")
    error: str | None = None
    sha256: str


class ReferenceList(BaseModel):
    items: list[ReferenceOut]
    total: int
    offset: int
    limit: int


class AcceptedOut(BaseModel):
    job_id: str
    reference_ids: list[int]
    duplicates: list[bool] = Field(description="true where identical bytes were already stored")
    notes: list[str] = Field(
        default_factory=list,
        description="for a duplicate uploaded with other metadata: the stored metadata was kept (PATCH changes it)",
    )


Label = Annotated[str, Field(max_length=LABEL_MAX), AfterValidator(readable)]
CapturedAt = Annotated[str, Field(max_length=CAPTURED_AT_MAX), AfterValidator(readable)]


class ReferenceFields(BaseModel):
    """A reference's writable fields as a client gives them: the one model for the form fields of
    POST /references, each item of its ``metadata`` and (with ranges on the position) PATCH.

    Strict: a boolean is not a number and an object is not a string (lax mode stores ``true`` as 1.0).
    The range of an upload's lat/lon is checked by the core (``invalid_position``, as for EXIF positions)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    lat: float | None = None
    lon: float | None = None
    heading: float | None = Field(None, ge=0, lt=360)
    captured_at: CapturedAt | None = None
    label: Label | None = None


class ReferencePatch(ReferenceFields):
    """PATCH /references/{id}: every field optional; only those given change."""

    lat: float | None = Field(None, ge=-90, le=90)
    lon: float | None = Field(None, ge=-180, le=180)


class JobItem(BaseModel):
    reference_id: int
    duplicate: bool
    status: str
    error: str | None


class JobOut(BaseModel):
    id: str
    created_at: str
    status: str = Field(description="queued, running, done or failed")
    total: int
    pending: int
    indexed: int
    failed: int
    deleted: int
    items: list[JobItem]


class HealthOut(BaseModel):
    status: str


class ReadyOut(BaseModel):
    status: str
    config: str | None = None
    index_size: int | None = None
    version: int | None = None
    generation: int | None = None
    worker: str | None = None
