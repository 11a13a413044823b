"""One library photo's suggestion: the visual answer (``GeolocService.locate``) fused with the time prior.

Why a separate step: the visual answer is /locate's, unchanged (its calibration decides what is confident);
this module only says what the time prior adds (``app.library.timeprior``) and what the answer rests on
(``basis``: pixels, time, or pixels+time), in the shape the journal, the exports and the page share."""

from __future__ import annotations

import numpy as np

from app.domain import LocateAnswer
from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m
from app.library.photos import PhotoMeta
from app.library.timeprior import MIN_SUPPORT, Prior, inside, time_only_radius

#: Candidates a suggestion carries (the page shows them beside the photo).
SHOWN_CANDIDATES = 5
#: A prior wider than this (a gap over about 90 s) rescues nothing: on a campus it covers every candidate.
MAX_RESCUE_RADIUS_M = 150.0


def suggestion(meta: PhotoMeta, answer: LocateAnswer, prior: Prior | None) -> dict:
    """The journal's record of a located photo (JSON-ready)."""
    est = answer.estimate
    out: dict = {
        "file": str(meta.path),
        "taken": meta.taken_iso,
        "camera": meta.camera,
        "note": meta.note,
        "placed": False,
        "confident": False,
        "lat": None,
        "lon": None,
        "radius_m": None,
        # The calibrated probability of the visual answer's place; a position the time prior chose instead
        # (a rescue, or time alone) has no calibrated rate, so "p" is then None and "visual_p" says the
        # pixels' own.
        "p": None if answer.answer_p is None else round(float(answer.answer_p), 4),
        "visual_p": None if answer.answer_p is None else round(float(answer.answer_p), 4),
        "basis": None,
        "reason_code": answer.reason_code,
        "reason": answer.reason,
        "prior": prior.as_dict() if prior else None,
        "candidates": [
            {"reference_id": c.reference_id, "lat": c.lat, "lon": c.lon, "score": round(c.score, 4), "label": c.label}
            for c in answer.candidates[:SHOWN_CANDIDATES]
        ],
        # What the joint location of the photo's run reads (``app.library.joint``): every candidate the
        # calibration gives a probability, as (lat, lon, p_within_25m).
        "calibrated_candidates": [
            [c.lat, c.lon, round(float(c.p_within_25m), 4)] for c in answer.candidates if c.p_within_25m is not None
        ],
    }
    if answer.reason is None and est.lat is not None:
        basis = "pixels+time" if prior is not None and inside(prior, est.lat, est.lon) else "pixels"
        return _placed(out, est.lat, est.lon, est.radius_m, True, basis)
    if prior is None:
        return out
    if prior.radius_m <= MAX_RESCUE_RADIUS_M:
        agreeing = [c for c in answer.candidates if inside(prior, c.lat, c.lon)]
        if len(agreeing) >= MIN_SUPPORT:
            fused = fuse_position(
                np.array([c.lat for c in agreeing]),
                np.array([c.lon for c in agreeing]),
                np.array([c.score for c in agreeing]),
            )
            if fused.lat is not None and fused.support >= MIN_SUPPORT:
                radius = rescue_radius(prior, fused.lat, fused.lon, fused.radius_m)
                return _placed({**out, "p": None}, fused.lat, fused.lon, radius, True, "pixels+time")
    radius = time_only_radius(prior)
    if radius is not None:
        return _placed({**out, "p": None}, prior.lat, prior.lon, radius, False, "time")
    return out


def rescue_radius(prior: Prior, lat: float, lon: float, fused_radius_m: float) -> float:
    """A rescue is confident because of the time prior, not a calibrated rate, so its radius must hold wherever
    the prior's disc says the photo was taken: it reaches the far edge of that disc from the placed point
    (never less than the fused candidates' own radius). The fused radius alone fell short on the
    README's library (img_00037: placed 57 m from the truth, radius 41 m, truth inside the disc)."""
    to_far_edge = float(haversine_m(prior.lat, prior.lon, lat, lon)) + prior.radius_m
    return max(float(fused_radius_m), to_far_edge)


def _placed(out: dict, lat: float, lon: float, radius_m: float | None, confident: bool, basis: str) -> dict:
    out.update(
        placed=True,
        confident=confident,
        lat=round(float(lat), 7),
        lon=round(float(lon), 7),
        radius_m=None if radius_m is None else round(float(radius_m), 1),
        basis=basis,
        reason_code=None if confident else out["reason_code"] or "time_only",
        reason=None if confident else "a position from the capture time alone (a same-camera photo minutes away)",
    )
    return out
