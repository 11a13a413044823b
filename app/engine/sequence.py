"""Several photos, one path: a hidden Markov model over each photo's candidate places.

Why: one photo is often ambiguous (two facades alike, a candidate that is right but not confident enough),
but people rarely have only one photo. A walk, a drive or a video passes places in order, and a place is
only plausible next to the places before and after it. Sequence matching is how visual place recognition
copes with views one frame cannot settle (SeqSLAM and its successors); here it is a small HMM on top of the
single-photo answer, so it costs a few K x K arrays per photo whatever the collection's size.

- **States** per step: the step's candidate places (its candidates grouped within ``PLACE_RADIUS_M``), plus
  one state "not in this collection" (``ABSENT``).
- **Emissions**: the calibrated probability each place lies within 25 m of the truth, as the single-photo
  answer states it (``p_within_25m``), read as odds against "elsewhere" (the absent state emits 1). Why
  odds: a photo's candidates' probabilities are each a marginal, not exclusive (several wrong places may
  each hold 0.3), and as odds a photo with one place gets exactly its probability back as its posterior,
  while a photo with several places shares it among them.
- **Transitions** (a motion model): two consecutive places are compatible when their distance is within
  what the time gap times a speed bound allows (or a step bound where there are no times), plus both
  places' own uncertainty; beyond it the compatibility falls off exponentially. Entering or leaving the
  absent state has a fixed weight (``ABSENT_LINK``): a walk may leave the collection's area; staying out
  of it weighs 1, and two compatible places up to ``CONTINUITY_GAIN``: the full gain where the reach is
  small against the collection, none where it spans the collection (``continuity_gain``).
- **Bursts**: photos of one place close in time are one step; its emissions are the product of its
  photos' (each photo's evidence about the same place counts once per photo).
- **Viterbi** gives the most likely path; **forward-backward** gives each step's own posterior, what a
  photo's answer reads.

numpy in, numpy out: the application layer turns answers into ``Observation``s and posteriors back into
answers (``app.usecases.sequence``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.geo import haversine_m

#: Candidates within this distance of each other are one place (the single-photo estimate's cluster radius).
PLACE_RADIUS_M = 25.0
#: Walking pace with margin: the default speed bound when the photos have times.
DEFAULT_SPEED_MPS = 2.0
#: The default step bound between consecutive photos without times: a walk's photos a minute or so apart.
DEFAULT_STEP_M = 150.0
#: Consecutive photos at most this many seconds apart whose best places agree are one burst (one step).
BURST_S = 10.0
#: Each place's own uncertainty added to the allowed distance (both places' radius: a candidate is "right"
#: within 25 m of the truth).
SLACK_M = 2 * PLACE_RADIUS_M
#: Beyond the allowed distance, the compatibility falls by e for every this many metres.
FALLOFF_M = 50.0
#: The weight of a transition between two compatible places, against 1 for staying absent: what continuity is
#: worth. Why above 1: next to a known place, the next photo lies in a small reachable disc, not anywhere in
#: the collection's extent; a run of places that line up along a feasible path is unlikely by chance, so
#: photos each too weak alone (p below 0.5, odds below 1) may together outweigh "elsewhere throughout".
CONTINUITY_GAIN = 3.0
#: The weight of a transition into or out of the absent state, against 1 for two compatible places (and for
#: staying absent).
ABSENT_LINK = 0.5
#: A photo of a burst whose candidates hold no place near a step's state: its probability that the state is
#: right anyway (its candidates can all miss a place another photo of the burst shows).
MISSING_P = 0.02
#: No probability is read as exactly 0 or 1 (logs stay finite; one photo never vetoes a path outright).
P_FLOOR = 1e-4
ABSENT = -1


@dataclass(frozen=True)
class Observation:
    """One photo's single-photo answer, as the model reads it: its candidates' positions and their
    calibrated probabilities of lying within 25 m of the truth (best first), and its capture time in
    seconds (None: unknown)."""

    lats: np.ndarray
    lons: np.ndarray
    p: np.ndarray
    time_s: float | None = None


@dataclass(frozen=True)
class Motion:
    """The motion bound between consecutive steps: ``speed_mps`` applies where both have times, ``step_m``
    where either has none."""

    speed_mps: float = DEFAULT_SPEED_MPS
    step_m: float = DEFAULT_STEP_M
    #: The collection's extent (the diagonal of the box its references lie in; None: unknown), against
    #: which a step's reach is weighed (``continuity_gain``).
    extent_m: float | None = None

    def allowed_m(self, gap_s: float | None) -> float:
        return self.step_m if gap_s is None else self.speed_mps * abs(gap_s)

    def continuity_gain(self, gap_s: float | None) -> float:
        """What two compatible places are worth against staying absent, for one step.

        Why it shrinks with the reach: continuity is evidence only because the next photo must lie in a
        small reachable disc rather than anywhere in the collection. Where the step's reach (the allowed
        distance plus both places' slack, as a disc) covers the collection's extent (as a disc of that
        diameter), every place is compatible with every other and a run of places lining up is no longer
        unlikely by chance; the full gain there was a prior, never measured, that the sequence lies in the
        collection, and it lifted sequences of photos from elsewhere, each too weak alone, above the
        disc's threshold together. The gain falls linearly with the share of the collection in reach, to
        1 (no favour) where the reach covers it all. Without a known extent, the full gain."""
        if not self.extent_m or self.extent_m <= 0:
            return CONTINUITY_GAIN
        share = min(1.0, (2.0 * (self.allowed_m(gap_s) + SLACK_M) / self.extent_m) ** 2)
        return 1.0 + (CONTINUITY_GAIN - 1.0) * (1.0 - share)


@dataclass(frozen=True)
class Places:
    """One step's states: place positions, each place's members (indices into its photo's candidates, per
    photo of the step) and each place's emission (the product over the step's photos)."""

    lats: np.ndarray
    lons: np.ndarray
    log_emission: np.ndarray  # one per place, then the absent state last
    spread_m: np.ndarray  # per place: the farthest member candidate from its centre


@dataclass(frozen=True)
class PathResult:
    """Per photo (in the input's order): the state on the most likely path (an index into its step's places,
    or ``ABSENT``), the posterior of every state of its step (places, then absent), and its step."""

    steps: list[list[int]]  # the photos of each step
    places: list[Places]
    path: np.ndarray  # per step: the Viterbi state (place index, or ABSENT)
    posterior: list[np.ndarray]  # per step: places' posteriors, then absent's

    def step_of(self, photo: int) -> int:
        for s, members in enumerate(self.steps):
            if photo in members:
                return s
        raise IndexError(photo)


# -- places ---------------------------------------------------------------------------------------------
def group_places(lats: np.ndarray, lons: np.ndarray, p: np.ndarray, radius_m: float = PLACE_RADIUS_M) -> np.ndarray:
    """A place label per candidate: greedily, the most probable unassigned candidate and every unassigned
    candidate within ``radius_m`` of it form one place."""
    n = len(p)
    label = np.full(n, -1)
    if n == 0:
        return label
    d = haversine_m(lats[:, None], lons[:, None], lats[None, :], lons[None, :])
    k = 0
    for i in np.argsort(-p, kind="stable"):
        if label[i] >= 0:
            continue
        label[(label < 0) & (d[i] <= radius_m)] = k
        k += 1
    return label


def _photo_places(obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One photo's places: centres (weighted by p) and each place's probability (its best candidate's)."""
    p = np.clip(np.asarray(obs.p, np.float64), P_FLOOR, 1 - P_FLOOR)
    label = group_places(np.asarray(obs.lats, np.float64), np.asarray(obs.lons, np.float64), p)
    k = label.max() + 1 if len(label) else 0
    lats, lons, pp = np.zeros(k), np.zeros(k), np.zeros(k)
    for j in range(k):
        m = label == j
        lats[j] = np.sum(obs.lats[m] * p[m]) / p[m].sum()
        lons[j] = np.sum(obs.lons[m] * p[m]) / p[m].sum()
        pp[j] = p[m].max()
    return lats, lons, pp


def log_odds(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), P_FLOOR, 1 - P_FLOOR)
    return np.log(p) - np.log1p(-p)


def step_places(observations: Sequence[Observation], radius_m: float = PLACE_RADIUS_M) -> Places:
    """The states of one step (one photo, or a burst's photos): their places pooled and grouped again; each
    state's emission is the product over the photos of that photo's probability for it (its nearest place
    within ``radius_m``, else ``MISSING_P``), as odds; the absent state's is 1."""
    per = [_photo_places(o) for o in observations]
    lats = np.concatenate([q[0] for q in per])
    lons = np.concatenate([q[1] for q in per])
    p = np.concatenate([q[2] for q in per])
    label = group_places(lats, lons, p, radius_m)
    k = label.max() + 1 if len(label) else 0
    c_lat, c_lon, spread = np.zeros(k), np.zeros(k), np.zeros(k)
    for j in range(k):
        m = label == j
        c_lat[j] = np.sum(lats[m] * p[m]) / p[m].sum()
        c_lon[j] = np.sum(lons[m] * p[m]) / p[m].sum()
        spread[j] = float(np.max(haversine_m(c_lat[j], c_lon[j], lats[m], lons[m])))
    log_e = np.zeros(k + 1)
    for plat, plon, pp in per:
        if k:
            if len(pp):
                d = haversine_m(c_lat[:, None], c_lon[:, None], plat[None, :], plon[None, :])
                near = np.where(d <= radius_m, pp[None, :], 0.0).max(axis=1)
            else:
                near = np.zeros(k)
            log_e[:k] += log_odds(np.maximum(near, MISSING_P))
    return Places(c_lat, c_lon, log_e, spread)


# -- steps: bursts ----------------------------------------------------------------------------------------
def bursts(observations: Sequence[Observation], burst_s: float = BURST_S) -> list[list[int]]:
    """The photos grouped into steps, in order: consecutive photos with times at most ``burst_s`` apart whose
    best places lie within ``PLACE_RADIUS_M`` of each other are one step; every other photo is a step."""
    steps: list[list[int]] = []
    for i, o in enumerate(observations):
        if steps and _same_burst(observations[steps[-1][-1]], o, burst_s):
            steps[-1].append(i)
        else:
            steps.append([i])
    return steps


def _same_burst(a: Observation, b: Observation, burst_s: float) -> bool:
    if a.time_s is None or b.time_s is None or abs(b.time_s - a.time_s) > burst_s:
        return False
    if not len(a.p) or not len(b.p):
        return False
    ia, ib = int(np.argmax(a.p)), int(np.argmax(b.p))
    return bool(haversine_m(a.lats[ia], a.lons[ia], b.lats[ib], b.lons[ib]) <= PLACE_RADIUS_M)


def _step_time(observations: Sequence[Observation], members: Sequence[int]) -> tuple[float | None, float | None]:
    times = [observations[i].time_s for i in members]
    if any(t is None for t in times):
        return None, None
    return float(times[0]), float(times[-1])


# -- transitions -------------------------------------------------------------------------------------------
def log_transition(a: Places, b: Places, gap_s: float | None, motion: Motion) -> np.ndarray:
    """Log compatibility of each state of ``a`` with each of ``b`` ((ka + 1) x (kb + 1), absent last)."""
    ka, kb = len(a.lats), len(b.lats)
    out = np.full((ka + 1, kb + 1), np.log(ABSENT_LINK))
    out[ka, kb] = 0.0
    if ka and kb:
        d = haversine_m(a.lats[:, None], a.lons[:, None], b.lats[None, :], b.lons[None, :])
        excess = np.maximum(d - motion.allowed_m(gap_s) - SLACK_M, 0.0)
        out[:ka, :kb] = np.log(motion.continuity_gain(gap_s)) - excess / FALLOFF_M
    return out


# -- inference --------------------------------------------------------------------------------------------
def _logsumexp(x: np.ndarray, axis: int) -> np.ndarray:
    m = np.max(x, axis=axis, keepdims=True)
    return np.squeeze(m, axis) + np.log(np.sum(np.exp(x - m), axis=axis))


def viterbi(log_e: Sequence[np.ndarray], log_t: Sequence[np.ndarray]) -> list[int]:
    """The most likely state per step (indices into each step's states)."""
    score = log_e[0].copy()
    back = []
    for t in range(1, len(log_e)):
        cand = score[:, None] + log_t[t - 1]
        back.append(np.argmax(cand, axis=0))
        score = cand.max(axis=0) + log_e[t]
    path = [int(np.argmax(score))]
    for b in reversed(back):
        path.append(int(b[path[-1]]))
    return path[::-1]


def forward_backward(log_e: Sequence[np.ndarray], log_t: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Each step's posterior over its states given every step (normalised to sum 1)."""
    n = len(log_e)
    fwd = [log_e[0]]
    for t in range(1, n):
        fwd.append(_logsumexp(fwd[-1][:, None] + log_t[t - 1], axis=0) + log_e[t])
    bwd = [np.zeros_like(log_e[-1])]
    for t in range(n - 2, -1, -1):
        bwd.append(_logsumexp(log_t[t] + (log_e[t + 1] + bwd[-1])[None, :], axis=1))
    bwd = bwd[::-1]
    out = []
    for f, b in zip(fwd, bwd, strict=True):
        x = f + b
        x = np.exp(x - x.max())
        out.append(x / x.sum())
    return out


def solve(observations: Sequence[Observation], motion: Motion | None = None, burst_s: float = BURST_S) -> PathResult:
    """The path through ``observations`` (in order) and each step's posterior."""
    if not observations:
        raise ValueError("a sequence needs at least one photo")
    motion = motion or Motion()
    steps = bursts(observations, burst_s)
    places = [step_places([observations[i] for i in members]) for members in steps]
    log_e = [p.log_emission for p in places]
    log_t = []
    for s in range(1, len(steps)):
        _, end = _step_time(observations, steps[s - 1])
        start, _ = _step_time(observations, steps[s])
        gap = None if end is None or start is None else start - end
        log_t.append(log_transition(places[s - 1], places[s], gap, motion))
    raw = viterbi(log_e, log_t)
    path = np.array([ABSENT if r == len(p.lats) else r for r, p in zip(raw, places, strict=True)])
    return PathResult(steps, places, path, forward_backward(log_e, log_t))
