"""Response models: they are the API's documentation (/openapi.json) as much as its validation."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, Field, field_validator

from app.domain import LocateAnswer, ReferenceEdit
from app.text import iso_or_as_stored

if TYPE_CHECKING:
    from app.usecases.sequence import SequenceAnswer

#: How answers round: metres to 0.1 m, scores, probabilities and shares to 4 digits, an estimate's
#: position to 7 decimals (1 cm). More digits would be noise (``distance_m: 1.2e-09``), fewer would hide a
#: difference between two candidates.
METRES_DIGITS, SCORE_DIGITS, DEGREES_DIGITS = 1, 4, 7
CAPTURED_AT_DOC = "ISO 8601 (2024-09-23T16:08:20), with a zone (+02:00) only when one is known"


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None else round(v, digits)


class CandidateOut(BaseModel):
    # One ``app.domain.Candidate``, read by attribute, rounded (``METRES_DIGITS``...).
    reference_id: int
    lat: float
    lon: float
    score: float = Field(description="similarity in [0, 1], whatever the search mode (4 digits)")
    distance_m: float | None = Field(
        None, description="metres from the fused estimate, to 0.1 m (only when there is a confident estimate)"
    )
    label: str | None = None
    captured_at: str | None = Field(None, description=CAPTURED_AT_DOC)
    heading: float | None = None
    inliers: int | None = Field(
        None,
        description="geometric verification inliers, when verified (rerank=true, or by default with stored "
        "local features); null when this candidate was not verified",
    )
    p_within_25m: float | None = Field(
        None,
        description="probability that this reference lies within 25 m of where the photo was taken, calibrated on "
        "this collection by `geoloc fit` / `geoloc refit` (given for the first 10 candidates; null when the "
        "collection is too small to calibrate)",
    )

    @field_validator("score", "p_within_25m")
    @classmethod
    def _score_digits(cls, v: float | None) -> float | None:
        return _round(v, SCORE_DIGITS)

    @field_validator("distance_m")
    @classmethod
    def _metres(cls, v: float | None) -> float | None:
        return _round(v, METRES_DIGITS)

    @field_validator("captured_at")
    @classmethod
    def _iso(cls, v: str | None) -> str | None:
        return iso_or_as_stored(v)


class EstimateOut(BaseModel):
    lat: float
    lon: float
    radius_m: float = Field(
        description="the disc around lat, lon that holds the truth, to 0.1 m: for radius_rate of such answers "
        "when it is given (the smallest disc that held at that rate for this collection's own answers with evidence "
        "as strong), else for most confident answers"
    )
    radius_rate: float | None = Field(
        None,
        ge=0,
        le=1,
        description="the share of such answers (with evidence this strong) whose truth lies within radius_m, "
        "calibrated on this collection by `geoloc fit` / `geoloc refit` (0.9: 9 in 10; GEOLOC_RADIUS_RATE); null "
        "when the collection is not calibrated and radius_m is the constant rule (farthest fused candidate + 40 m)",
    )
    confidence: float = Field(ge=0, le=1, description="the fused group's share of the candidates' weight")

    @field_validator("lat", "lon")
    @classmethod
    def _degrees(cls, v: float) -> float:
        return round(v, DEGREES_DIGITS)

    @field_validator("radius_m")
    @classmethod
    def _metres(cls, v: float) -> float:
        return round(v, METRES_DIGITS)

    @field_validator("confidence")
    @classmethod
    def _share(cls, v: float) -> float:
        return round(v, SCORE_DIGITS)


class FeaturesOut(BaseModel):
    extracted: int
    kept: int


class ExtentOut(BaseModel):
    min_lat: float
    min_lon: float
    max_lat: float
    max_lon: float


class IndexOut(BaseModel):
    size: int
    version: int
    generation: int = Field(0, description="the index generation answering (a re-fit makes the next one)")
    extent: ExtentOut | None = Field(
        None, description="the bounding box of the collection's references (what it covers); null when empty"
    )


class LocateOut(BaseModel):
    candidates: list[CandidateOut]
    estimate: EstimateOut | None
    reason: str | None = Field(None, description="why there is no estimate, in words that claim only what was measured")
    reason_code: str | None = Field(
        None,
        description="null when there is an estimate; else no_match (no reference looks like this photo: no "
        "candidate has a 10 % chance of lying within 25 m; it does not say the place is absent from the "
        "collection), ambiguous (candidates, but no disc small enough holds at the stated rate: possible places "
        "only), no_features (the photo "
        "has no usable features: no candidates, no probabilities) or no_references (the collection or the "
        "region searched holds none)",
    )
    mode: str
    config: str
    features: FeaturesOut
    timings_ms: dict[str, float]
    index: IndexOut

    @classmethod
    def of(cls, answer: LocateAnswer) -> LocateOut:
        """The answer of /locate and of `geoloc locate`, the one declaration of its JSON: the candidates and
        the estimate read from the domain's, the estimate only when confident, timings to 3 decimals."""
        e = answer.confident_estimate
        return cls(
            candidates=[CandidateOut.model_validate(c, from_attributes=True) for c in answer.candidates],
            estimate=None if e is None else EstimateOut.model_validate(e, from_attributes=True),
            reason=answer.reason,
            reason_code=answer.reason_code,
            mode=answer.mode,
            config=answer.config,
            features=FeaturesOut(extracted=answer.features_extracted, kept=answer.features_kept),
            timings_ms={k: round(v, 3) for k, v in answer.timings_ms.items()},
            index=IndexOut(
                size=answer.index_size,
                version=answer.index_version,
                generation=answer.index_generation,
                extent=None
                if answer.extent is None
                else ExtentOut(
                    min_lon=answer.extent[0],
                    min_lat=answer.extent[1],
                    max_lon=answer.extent[2],
                    max_lat=answer.extent[3],
                ),
            ),
        )


class ReferenceOut(BaseModel):
    id: int
    lat: float
    lon: float
    heading: float | None
    captured_at: str | None = Field(description=CAPTURED_AT_DOC)
    label: str | None
    source: str | None
    created_at: str
    status: str = Field(description="pending (accepted, being encoded), indexed, or failed")
    error: str | None = None
    sha256: str

    @field_validator("captured_at")
    @classmethod
    def _iso(cls, v: str | None) -> str | None:
        return iso_or_as_stored(v)  # rows stored before the conversion hold EXIF's form


class ReferenceList(BaseModel):
    """A page of references. Paging by ``offset`` counts and skips rows (O(rows): fine for a few thousand);
    paging by id (``after`` / ``before``, the ids in ``next_after`` / ``prev_before``) costs the same on any
    page of 10^6 references (without a bbox; a bbox that holds few rows walks past the others). A page
    emptied by deletes carries its neighbours' cursors."""

    items: list[ReferenceOut]
    total: int | None = Field(description="matching rows of any status; null on id pages unless total=true")
    offset: int | None = Field(description="the position of the first item; null on id pages")
    limit: int
    next_after: int | None = Field(None, description="pass as after= for the next page; null: this is the last")
    prev_before: int | None = Field(None, description="pass as before= for the previous page; null: the first")


class AcceptedOut(BaseModel):
    job_id: str
    reference_ids: list[int]
    duplicates: list[bool] = Field(description="true where identical bytes were already stored")
    notes: list[str] = Field(
        default_factory=list,
        description="for a duplicate uploaded with other metadata: the stored metadata was kept (PATCH changes it)",
    )


class ReferencePatch(ReferenceEdit):
    """PATCH /references/{id}: every field optional; only those given change."""


class JobItem(BaseModel):
    reference_id: int
    duplicate: bool
    status: str
    error: str | None
    quarantined: bool = Field(
        description="failed because its encoding never finished GEOLOC_ENCODE_ATTEMPTS times (the process "
        "encoding it stopped each time); `geoloc check` lists these too"
    )


class JobOut(BaseModel):
    id: str
    created_at: str
    status: str = Field(description="queued, running, done or failed")
    total: int
    pending: int
    indexed: int
    failed: int
    deleted: int
    quarantined: int = Field(description="of the failed items, those quarantined")
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
    #: Where the rows are: ``sqlite`` (the data dir) or ``postgres`` (GEOLOC_DATABASE_URL, shared by replicas).
    database: str | None = None
    #: How this process loaded its index: from a ``snapshot`` (plus the changes after it), or ``rebuilt`` from
    #: the database's codes (a replica starting cold with no snapshot it can trust), or ``shared``: the index is
    #: on a server every replica uses (GEOLOC_MILVUS_URI), nothing loaded here.
    index_loaded: str | None = None
    #: Which index kind serves each part (``float``, ``binary``) and its parameters (``VectorIndex.stats``).
    index: dict[str, dict[str, Any]] | None = None
    #: How the kind is chosen: exact below ``GEOLOC_INDEX_SWITCH_AT`` references then compressed (and whether
    #: the switch is being built now), or the configuration's kinds at every size.
    index_choice: str | None = None
    #: Which rule judges this collection's answers (its own calibration, or the conservative rule and why),
    #: and what a collection that cannot give a confident answer yet needs.
    calibration: str | None = None
    #: With a configuration that stores local features, when this start found references without their file:
    #: the background back-fill's latest line (``features backfill (xfeat-640-n900): 120/500 indexed
    #: references, 118 written, 2 already there, 0 failed``, ending ``(done)``); answers meanwhile verify
    #: the candidates whose file exists. None when there was nothing to back-fill.
    features_backfill: str | None = None


# -- POST /locate/sequence -----------------------------------------------------------------------------------
class SequencePhotoOut(LocateOut):
    """One photo's answer in its sequence: /locate's answer, and what it rests on."""

    rests_on: str = Field(
        description="pixels: the photo alone was confident at the place its estimate names, or it has no estimate; "
        "sequence: the estimate comes from the path through the photos around it; where the collection was "
        "calibrated on its own walks, its disc and radius_rate are the walks' (docs/sequences.md)"
    )
    sequence_p: float | None = Field(
        None,
        description="the sequence's posterior probability of the place the answer names (its estimate's, else the "
        "most probable place, or with a collection not calibrated on walks the most probable state, which may be "
        "'not in this collection'); null when the collection is not calibrated",
    )

    @field_validator("sequence_p")
    @classmethod
    def _p_digits(cls, v: float | None) -> float | None:
        return _round(v, SCORE_DIGITS)


class PathPointOut(BaseModel):
    lat: float | None = Field(None, description="the most likely path's place at this photo (null: none)")
    lon: float | None = None
    in_collection: bool = Field(description="false where the path says the photo shows no place of this collection")

    @field_validator("lat", "lon")
    @classmethod
    def _degrees(cls, v: float | None) -> float | None:
        return _round(v, DEGREES_DIGITS)


class SequenceOut(BaseModel):
    answers: list[SequencePhotoOut] = Field(
        description="one /locate-shaped answer per image, in the order located: as sent, or with order=taken in "
        "the order the images were taken"
    )
    images: list[int] = Field(description="each answer's image, as its position among the images sent (from 0)")
    path: list[PathPointOut] = Field(description="the most likely path (Viterbi), one point per answer")
    times_from: str = Field(
        description="given (taken_at), exif (the photos' DateTimeOriginal), video (the frames' times) or order "
        "(no times)"
    )
    note: str | None = Field(None, description="why the sequence could not inform the answers, when it could not")

    @classmethod
    def of(cls, result: SequenceAnswer) -> SequenceOut:
        return cls(
            answers=[
                SequencePhotoOut(**LocateOut.of(p.answer).model_dump(), rests_on=p.rests_on, sequence_p=p.sequence_p)
                for p in result.photos
            ],
            images=result.images or list(range(len(result.photos))),
            path=[PathPointOut(lat=q.lat, lon=q.lon, in_collection=q.in_collection) for q in result.path],
            times_from=result.times_from,
            note=result.note,
        )
