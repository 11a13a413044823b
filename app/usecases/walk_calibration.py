"""The sequence's own disc, fitted on the collection's references arranged as held-out walks.

Why: a photo in a sequence is answered from the sequence's posterior (``app.usecases.sequence``), and how
often a posterior of that strength holds is not what the single-photo disc measured. The single-photo
calibration locates each reference with its own capture left out, its neighbours along the walk still in
the collection; a walk a user sends is new: none of its photos, and none of the places between them, are
references. Read through the single-photo disc, the sequence's answers on held-out penn walks held far
less often than the rate they stated (docs/sequences.md).

So ``calibrate_collection`` also arranges the references it holds out into walks: those with a capture
time (EXIF, a manifest's ``time``, a stored ``captured_at``), one per capture, chained in time order where
the motion model allows each step (``walk_windows``), cut into windows of ``WALK_WINDOW``. Each window is
located as a user's walk would be: every photo of it, with the captures of the whole window left out (its
places present where other captures show them), and once more with every reference within the absent
radius of any of its photos removed (a walk elsewhere). Once the single-photo rule is fitted, each window's
answers go through the sequence model as /locate/sequence's do (``fit_walk_disc``), and the disc is fitted
on the posteriors and errors of the photos not confident alone (those /locate/sequence places by it) as the
single disc is (``fit_disc``: split-conformal per bin of strength, counted in captures, the absent walks
held by no disc). /locate/sequence then states that disc and its rate for each photo of a sequence not
confident alone (``Calibration.sequence_disc``).

What it does not measure: a window holds the captures one auxiliary fit holds out (a quarter of the
collection, dealt at random), so the captures taken between its photos stay references, and a walk whose
every place is new is harder than these; the photos of a window share one path, yet count as captures
apart. Verified answers (``rerank``, a configuration with stored features) have their own disc, fitted on
the windows whose every photo the calibration verifies (``Calibration.verified``).

Cost: one more pair of searches per held-out reference with a time, within the auxiliary fits the
single-photo calibration makes already, plus the sequence model over windows of ``WALK_WINDOW``: bounded by
the calibration's sample, whatever the collection's size.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime

import numpy as np

from app.domain import LocateAnswer
from app.engine.calibration import MAX_RADIUS_M, RADIUS_RATE, Calibration, fit_disc
from app.engine.geo import haversine_m
from app.engine.sequence import SLACK_M, Motion, Observation, solve
from app.engine.training.svm_training import Geotagged
from app.text import iso_captured_at

#: Photos per calibration walk: what the evaluation's windows hold (``--sequence-window 5``).
WALK_WINDOW = 5
#: A walk holds at least this many photos (a sequence does: ``app.usecases.sequence.MIN_PHOTOS``).
MIN_WALK = 2


@dataclass
class WalkAnswers:
    """One calibration walk located: its references in time order, each one's answer (with the whole
    window's captures left out, and with ``absent`` every reference near any of them removed too)."""

    ids: list[int]
    answers: list[LocateAnswer]
    absent: bool


@dataclass
class WalkSample:
    """What the sequence model said of each photo of the located walks not confident alone: the strength of
    the place it favours most (its posterior), that place's error from the truth (inf: none, or a walk
    elsewhere) and the capture it belongs to; and how many photos were confident alone (left out: their own
    answer stands in a sequence)."""

    strength: list[float] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    groups: list[tuple[str, bool]] = field(default_factory=list)
    confident_alone: int = 0


def capture_seconds(taken: Mapping[int, str]) -> dict[int, float]:
    """Each reference's capture time in seconds on one clock (a time without a zone takes the zone of the
    first, in the order given, that has one, as a sequence's times do: right for one camera's clock, off by
    the difference where cameras in several zones wrote local times without one); times that cannot be read
    are left out (that reference belongs to no walk)."""
    parsed: dict[int, datetime] = {}
    for i, text in taken.items():
        try:
            iso = iso_captured_at(str(text).strip())
            if len(iso) > 10:  # a date alone places no photo in a walk
                parsed[i] = datetime.fromisoformat(iso)
        except ValueError:
            continue
    zone = next((t.tzinfo for t in parsed.values() if t.tzinfo is not None), None)
    if zone is not None:
        parsed = {i: t if t.tzinfo is not None else t.replace(tzinfo=zone) for i, t in parsed.items()}
    if not parsed:
        return {}
    first = min(parsed.values())
    return {i: (t - first).total_seconds() for i, t in parsed.items()}


def walk_windows(
    held: Sequence[int],
    refs: Mapping[int, Geotagged],
    times: Mapping[int, float],
    motion: Motion | None = None,
    window: int = WALK_WINDOW,
) -> list[list[int]]:
    """The held-out references with a time as walks: one per capture, in time order, each joining the walk
    whose last photo it can follow under ``motion`` (its distance within the gap times the speed bound plus
    the slack), the nearest of those, else starting one; each walk cut into windows of ``window`` (a
    shorter last window of at least ``MIN_WALK`` kept). Why chained by motion and not by camera: the store
    does not know which camera took a photo, and several photographers' photos interleave in time."""
    motion = motion or Motion()
    firsts: dict[str, int] = {}
    for i in held:
        if i in times and refs[i].group not in firsts:
            firsts[refs[i].group] = i
    order = sorted(firsts.values(), key=lambda i: (times[i], i))
    walks: list[list[int]] = []
    for i in order:
        best, best_d = None, np.inf
        for w in walks:
            last = w[-1]
            d = float(haversine_m(refs[last].lat, refs[last].lon, refs[i].lat, refs[i].lon))
            if d <= motion.allowed_m(times[i] - times[last]) + SLACK_M and d < best_d:
                best, best_d = w, d
        if best is None:
            walks.append([i])
        else:
            best.append(i)
    out = []
    for w in walks:
        for start in range(0, len(w), window):
            part = w[start : start + window]
            if len(part) >= MIN_WALK:
                out.append(part)
    return out


def observe(cal: Calibration, answer: LocateAnswer, time_s: float | None) -> Observation:
    """One calibration answer as the sequence model reads a served one: its candidates with the fitted
    rule's ``p_within_25m`` (what /locate gives each of the first candidates)."""
    ev = answer.evidence
    p = cal.probabilities(ev) if ev is not None and len(ev.values) else None
    if p is None:
        empty = np.zeros(0)
        return Observation(empty, empty, empty, time_s)
    cands = answer.candidates[: len(p)]
    return Observation(
        np.array([c.lat for c in cands], np.float64), np.array([c.lon for c in cands], np.float64), p, time_s
    )


def walk_sample(
    cal: Calibration,
    walks: Sequence[WalkAnswers],
    refs: Mapping[int, Geotagged],
    times: Mapping[int, float],
    motion: Motion,
) -> WalkSample:
    """Each located walk through the sequence model, as /locate/sequence runs it (``solve``, the motion
    weighed against the collection's extent): per photo not confident alone under ``cal``, the posterior of
    the place it favours most and that place's distance from the truth."""
    out = WalkSample()
    for w in walks:
        t0 = times[w.ids[0]]
        result = solve([observe(cal, a, times[i] - t0) for i, a in zip(w.ids, w.answers, strict=True)], motion)
        for n, i in enumerate(w.ids):
            a = w.answers[n]
            if a.evidence is not None and len(a.evidence.values) and cal.decide(a.evidence, a.estimate).confident:
                out.confident_alone += 1
                continue
            s = result.step_of(n)
            places, post = result.places[s], result.posterior[s]
            r = refs[i]
            if len(places.lats):
                k = int(np.argmax(post[:-1]))
                strength = float(post[k])
                error = float(haversine_m(r.lat, r.lon, places.lats[k], places.lons[k]))
            else:
                strength, error = 0.0, np.inf
            out.strength.append(strength)
            out.errors.append(np.inf if w.absent else error)
            out.groups.append((r.group, w.absent))
    return out


def fit_walk_disc(
    cal: Calibration,
    walks: Sequence[WalkAnswers],
    refs: Mapping[int, Geotagged],
    times: Mapping[int, float],
    motion: Motion | None = None,
    rate: float = RADIUS_RATE,
    max_radius_m: float = MAX_RADIUS_M,
    extent_m: float | None = None,
) -> tuple[dict | None, dict]:
    """The sequence's disc (``Disc``'s fields; None: too few walks, or an uncalibrated rule) and what it
    was fitted on, for the calibration's report."""
    present = [w for w in walks if not w.absent]
    report = {"walks": len(present), "photos": sum(len(w.ids) for w in present), "window": WALK_WINDOW}
    if not cal.calibrated or not present:
        return None, report
    motion = motion or Motion()
    motion = motion if motion.extent_m is not None or not extent_m else replace(motion, extent_m=extent_m)
    sample = walk_sample(cal, walks, refs, times, motion)
    report["confident_alone"] = sample.confident_alone
    disc = fit_disc(np.array(sample.strength), np.array(sample.errors), sample.groups, rate, max_radius_m, extent_m)
    if disc is None:
        report["disc"] = "too few walk photos for a disc"
        return None, report
    report["radius_m"] = disc.radius_m
    return {**asdict(disc), "basis": "sequence_p"}, report


def walk_note(disc: dict | None, report: dict) -> str:
    """What the sequence's disc rests on, in words (`geoloc fit` and `geoloc refit` say it)."""
    fitted = f"{report['walks']} held-out walks ({report['photos']} photos)"
    if disc is None:
        return f"sequences: no disc of their own ({report.get('disc', 'no walk located')}; {fitted})"
    shown = ", ".join("none" if r is None else f"{r:.0f}" for r in disc["radius_m"])
    informs = any(r is not None and r <= disc["limit_m"] for r in disc["radius_m"])
    words = "" if informs else f": none within the {disc['limit_m']:.0f} m an estimate may state"
    return f"sequences: discs of {shown} m by posterior on {fitted}{words}"
