"""A library's photos located jointly: each camera's run of photos close in time read as one walk.

Why: the time prior (``app.library.timeprior``) needs a geotagged photo minutes away, so a run of photos
with no GPS at all got nothing from time. Here each camera's photos, in time order, the located ones and
the geotagged ones alike, are cut into runs wherever two consecutive photos are more than ``RUN_GAP_S``
apart, and each run is read by the sequence model (``app.engine.sequence``, the one ``POST
/locate/sequence`` reads) as one walk:

- a located photo is observed through its calibrated candidates, as its suggestion journalled them;
- a geotagged photo of the run is observed as one place, its GPS position, with ``ANCHOR_P``: the time
  prior is one more term of the same model.

A photo its own suggestion leaves unconfident (no position, time alone, or an estimate not confident)
whose posterior for one place gets an estimate by the collection's rule (``Calibration.estimate_disc``,
read by ``sequence_estimate`` as for a sequence's answers) is placed there with that disc: it rests on
``sequence``, and what it had before is kept under ``alone``. Confident suggestions are never changed.

Which photos form a run: only photos that name their camera (EXIF Make + Model; a photo without one could
be anyone's), each camera read as one clock as a sequence's photos are (``sequence_inputs.seconds``: a
phone writes the zone offset on some photos only, so a time without one takes the camera's zone).

The runs are read from the journal (every photo the scan located, also those an earlier run of it
located), so a scan resumed after a crash ends as an uninterrupted one does; a collection that cannot be
read so (not calibrated), or a scan without the runs, takes earlier runs' placements back."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from app.engine.calibration import Calibration
from app.engine.sequence import Motion, Observation, solve
from app.library.timeprior import WINDOW_S, Anchor
from app.usecases.sequence import SEQUENCE, in_collection, sequence_estimate
from app.usecases.sequence_inputs import seconds

#: Consecutive photos of one camera at most this far apart belong to one run (the time prior's window).
RUN_GAP_S = WINDOW_S
#: A geotagged photo's probability of lying within 25 m of where it was taken: a phone's GPS fix is
#: usually within 10 m, but not always (under trees, beside tall buildings).
ANCHOR_P = 0.95
#: What a suggestion the sequence replaces kept as it was.
ALONE_FIELDS = ("placed", "confident", "lat", "lon", "radius_m", "p", "basis", "reason_code", "reason")


@dataclass(frozen=True)
class Member:
    """One photo of a run: a located photo (``result``: its journalled suggestion) or an anchor."""

    taken: datetime
    observation: Observation
    result: dict | None = None


def observed(result: dict) -> Observation:
    """A located photo as the model reads it: its calibrated candidates (none in an older journal)."""
    rows = np.asarray(result.get("calibrated_candidates") or [], np.float64).reshape(-1, 3)
    return Observation(rows[:, 0], rows[:, 1], rows[:, 2])


def anchored(anchor: Anchor) -> Observation:
    return Observation(np.array([anchor.lat]), np.array([anchor.lon]), np.array([ANCHOR_P]))


def runs(members: Sequence[Member]) -> list[list[Member]]:
    """One camera's photos in time order, cut wherever two consecutive ones are more than ``RUN_GAP_S``
    apart; each member's observation timed on the camera's one clock."""
    if not members:
        return []
    secs = seconds([m.taken for m in members])
    ordered = sorted(zip(secs, range(len(members)), members, strict=True), key=lambda x: (x[0], x[1]))
    out: list[list[Member]] = []
    last = None
    for t, _, m in ordered:
        timed = Member(m.taken, Observation(m.observation.lats, m.observation.lons, m.observation.p, t), m.result)
        if last is None or t - last > RUN_GAP_S:
            out.append([])
        out[-1].append(timed)
        last = t
    return out


def joint_suggestions(
    results: Sequence[dict],
    anchors: Sequence[Anchor],
    calibration: Calibration,
    motion: Motion | None = None,
    enabled: bool = True,
) -> dict[str, dict]:
    """The suggestions the runs change, by file: photos the sequence now places confidently, and photos
    an earlier joint reading placed that the runs no longer support (their own suggestion back).
    ``enabled`` False, or a collection not calibrated: every earlier placement taken back, nothing placed."""
    changed: dict[str, dict] = {}
    if not enabled or not calibration.calibrated:
        for r in results:
            if r.get("basis") == SEQUENCE:
                changed[r["file"]] = rested(r, None)
        return changed
    by_camera: dict[str, list[Member]] = {}
    for r in results:
        if r.get("taken") and r.get("camera"):
            member = Member(datetime.fromisoformat(r["taken"]), observed(r), r)
            by_camera.setdefault(r["camera"], []).append(member)
        elif r.get("basis") == SEQUENCE:  # no run can hold it
            changed[r["file"]] = rested(r, None)
    for a in anchors:
        if a.camera in by_camera:
            by_camera[a.camera].append(Member(a.taken, anchored(a)))
    motion = in_collection(motion or Motion(), calibration)
    for members in by_camera.values():
        for run in runs(members):
            path = solve([m.observation for m in run], motion) if len(run) > 1 else None
            for n, m in enumerate(run):
                if m.result is None:
                    continue
                estimate = None
                if path is not None:
                    s = path.step_of(n)
                    estimate = sequence_estimate(path.places[s], path.posterior[s], calibration)
                new = rested(m.result, estimate)
                if new != m.result:
                    changed[m.result["file"]] = new
    return changed


def rested(result: dict, estimate) -> dict:
    """``result`` as the run leaves it: placed by the sequence where its own suggestion is not confident and
    the sequence gives an estimate; its own suggestion where it is confident, or the sequence gives none."""
    own = {**result, **result["alone"]} if result.get("basis") == SEQUENCE else result
    own = {k: v for k, v in own.items() if k != "alone"}
    if own["confident"] or estimate is None:
        return own
    return {
        **own,
        "placed": True,
        "confident": True,
        "lat": round(float(estimate.lat), 7),
        "lon": round(float(estimate.lon), 7),
        "radius_m": round(float(estimate.radius_m), 1),
        "p": round(float(estimate.confidence), 4),
        "basis": SEQUENCE,
        "reason_code": None,
        "reason": None,
        "alone": {k: own.get(k) for k in ALONE_FIELDS},
    }
