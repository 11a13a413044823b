"""Several photos, one path: the sequence use case, for every face (POST /locate/sequence, `geoloc locate
--sequence` and `--video`, the evaluation's ``--sequence-window``).

Each photo is first located alone by the one locate path (``GeolocService.locate``, or
``locate_features`` in the evaluation), asking for ``SEQUENCE_K`` candidates: the ones the calibration
gives a probability. ``sequence_answers`` then reads those answers as observations of the sequence model
(``app.engine.sequence``) and turns each photo's posterior back into a /locate-shaped answer:

- a photo confident alone keeps its answer: it rests on ``pixels``;
- a photo not confident alone whose sequence posterior for one place gets an estimate by the sequence's
  own disc (``Calibration.sequence_disc``, fitted on the collection's references arranged as held-out
  walks: ``walk_answer``) gets that place as its estimate, with that disc and its rate (never below the
  place's own spread plus the constant rule's margin): it rests on ``sequence``. A collection calibrated
  without walks (no capture times, or before them) reads the single-photo disc there instead
  (``sequence_estimate``), its rate unstated;
- any other photo keeps its single-photo answer (no estimate), its reason saying what the sequence found.

The cost per sequence is N single locates plus arrays of ``SEQUENCE_K`` x ``SEQUENCE_K`` per photo: it does
not grow with the collection."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from app.domain import Candidate, LocateAnswer, LocateOptions
from app.engine.calibration import AMBIGUOUS, NO_MATCH, Calibration, Disc, rate_words
from app.engine.errors import GeolocError
from app.engine.estimate import MARGIN_M, RADIUS_FLOOR_M, Estimate
from app.engine.geo import haversine_m
from app.engine.sequence import ABSENT, BURST_S, PLACE_RADIUS_M, Motion, Observation, Places, solve
from app.errors import InvalidRequest, ServiceError, code_of
from app.usecases.locate import ESTIMATE_CANDIDATES
from app.usecases.sequence_inputs import sequence_times, taken_order

if TYPE_CHECKING:
    from app.usecases.service import GeolocService

#: Candidates per photo the model reads: those the calibration gives a ``p_within_25m``.
SEQUENCE_K = ESTIMATE_CANDIDATES
#: The fewest photos a sequence holds, and the most one request may send (each is one locate).
MIN_PHOTOS = 2
MAX_PHOTOS = 50
PIXELS, SEQUENCE = "pixels", "sequence"
#: The errors that belong to one image (the others, a bad mode or a collection not ready, fail the request).
IMAGE_CODES = ("unreadable_image", "unsupported_image_format", "image_too_small", "image_shape", "too_large")


class BrokenImagesInSequence(ServiceError):
    """Images of a sequence that cannot be located (each named); nothing is answered for any of them."""

    code = "unreadable_image"

    def __init__(self, message: str, code: str = "unreadable_image"):
        super().__init__(message)
        self.code = code


@dataclass
class SequencePhoto:
    """One photo's answer in its sequence: /locate's answer, what it rests on, and the sequence's posterior
    of the state it names (the place of its estimate, else the most probable one; None: not calibrated)."""

    answer: LocateAnswer
    rests_on: str
    sequence_p: float | None = None
    alone: LocateAnswer | None = None  # the photo's single answer (the evaluation compares the two)


@dataclass(frozen=True)
class PathPoint:
    """The most likely path (Viterbi) at one photo: a place, or None where it leaves the collection."""

    lat: float | None
    lon: float | None
    in_collection: bool


@dataclass
class SequenceAnswer:
    photos: list[SequencePhoto]
    path: list[PathPoint]
    times_from: str  # given, exif or order
    note: str | None = None  # why the sequence could not inform the answers (an uncalibrated collection)
    #: Each answer's photo, as its position among the photos given (from 0); empty: the order given.
    images: list[int] = field(default_factory=list)


def observation(answer: LocateAnswer, time_s: float | None) -> Observation:
    """The model's view of one single answer: its candidates that carry a calibrated probability."""
    cands = [c for c in answer.candidates if c.p_within_25m is not None]
    return Observation(
        np.array([c.lat for c in cands], np.float64),
        np.array([c.lon for c in cands], np.float64),
        np.array([c.p_within_25m for c in cands], np.float64),
        time_s,
    )


def sequence_answers(
    singles: Sequence[LocateAnswer],
    times_s: Sequence[float | None],
    calibration: Calibration,
    motion: Motion,
    options: LocateOptions,
    burst_s: float = BURST_S,
    times_from: str = "order",
) -> SequenceAnswer:
    """The sequence's answers from each photo's single answer (located with ``SEQUENCE_K`` candidates or
    more), in order. ``calibration``: the rule that judged the single answers; ``options``: the caller's,
    whose ``top_k`` and ``min_score`` cut each answer's candidates at the end."""
    if not calibration.calibrated:
        note = f"the sequence could not inform the answers: the collection is not calibrated ({calibration.note})"
        photos = [SequencePhoto(_shown(a, options), PIXELS, None, a) for a in singles]
        return SequenceAnswer(photos, [PathPoint(None, None, False) for _ in singles], times_from, note)
    observations = [observation(a, t) for a, t in zip(singles, times_s, strict=True)]
    result = solve(observations, in_collection(motion, calibration), burst_s)
    walk_disc = Disc(**calibration.sequence_disc) if calibration.sequence_disc else None
    photos, path = [], []
    for n, alone in enumerate(singles):
        s = result.step_of(n)
        places, post = result.places[s], result.posterior[s]
        by_itself = favoured_alone(observations[n])
        single = replace(alone, candidates=by_posterior(alone.candidates, places, post, by_itself))
        k = int(result.path[s])
        path.append(PathPoint(None, None, False) if k == ABSENT else PathPoint(places.lats[k], places.lons[k], True))
        best = int(np.argmax(post))
        best_is_place = best < len(places.lats)
        if single.reason is None:
            photos.append(SequencePhoto(_shown(single, options), PIXELS, _p_near(places, post, single), alone))
            continue
        if walk_disc is not None and len(places.lats):
            photos.append(walk_answer(single, alone, places, post, walk_disc, options))
            continue
        p = float(post[best])
        estimate = sequence_estimate(places, post, calibration)
        if estimate is not None:
            answer = replace(single, estimate=estimate, reason=None, reason_code=None, answer_p=p)
            photos.append(SequencePhoto(_shown(answer, options), SEQUENCE, p, alone))
            continue
        if best_is_place:
            needs = (
                "no disc this collection states holds for evidence that strong"
                if calibration.disc is not None
                else f"below the {calibration.confident_p:.1%} this collection needs"
            )
            why = f"; with the sequence, the most probable place has a {p:.1%} chance: {needs}"
            answer = replace(single, reason=(single.reason or "") + why)
        else:
            answer = not_in_collection(single, p)
        photos.append(SequencePhoto(_shown(answer, options), PIXELS, p, alone))
    return SequenceAnswer(photos, path, times_from)


def walk_answer(
    single: LocateAnswer, alone: LocateAnswer, places: Places, post: np.ndarray, disc: Disc, options: LocateOptions
) -> SequencePhoto:
    """The answer of a photo not confident alone, by the sequence's own disc (``Calibration.sequence_disc``,
    fitted on the collection's references arranged as held-out walks): the place the posterior favours most,
    with the disc that held for ``disc.rate`` of the walks' photos whose posterior was as strong, and that
    rate, where the disc informs (it rests on ``sequence``); else no estimate, saying why. Why not the
    single-photo disc: in a walk the collection holds none of the walk's photos nor, often, the places
    between them, and the single-photo disc, fitted with each reference's neighbours present, held far less
    often there than it stated (docs/sequences.md)."""
    k = int(np.argmax(post[:-1]))
    p = float(post[k])
    radius = disc.estimate_radius(p)
    if radius is not None:
        radius = max(radius, float(places.spread_m[k]) + MARGIN_M, RADIUS_FLOOR_M)
        estimate = Estimate(float(places.lats[k]), float(places.lons[k]), radius, p, None, radius_rate=disc.rate)
        answer = replace(single, estimate=estimate, reason=None, reason_code=None, answer_p=p)
        return SequencePhoto(_shown(answer, options), SEQUENCE, p, alone)
    if post[-1] > p:
        answer = not_in_collection(single, float(post[-1]))
    else:
        reason = f"{single.reason}; with the sequence, the most probable place: {walk_disc_reason(disc, p)}"
        answer = replace(single, reason=reason)
    return SequencePhoto(_shown(answer, options), PIXELS, p, alone)


def not_in_collection(single: LocateAnswer, p_absent: float) -> LocateAnswer:
    """A photo's answer when the sequence's most probable state for it is "not in this collection"
    (``p_absent``): said as what was measured, ``no_match`` where the photo alone was ambiguous or no match."""
    return replace(
        single,
        reason=f"no reference looks like this photo: with the sequence, its most probable state is none of the "
        f"candidates' places ({p_absent:.0%})",
        reason_code=NO_MATCH if single.reason_code in (AMBIGUOUS, NO_MATCH) else single.reason_code,
    )


def walk_disc_reason(disc: Disc, p: float) -> str:
    """Why a sequence's answer this strong has no estimate, in words that claim only what the walks
    measured."""
    share = f"{rate_words(disc.rate)} such answers"
    r = disc.radius(p)
    if r is None:
        return (
            f"no disc holds {share} (posterior {p:.0%}): of this collection's own held-out walks, more than "
            f"{rate_words(1 - disc.rate)} photos this weak were off their place or walked where it holds none"
        )
    return (
        f"{share} (posterior {p:.0%}) lie within {r:.0f} m, wider than the {disc.limit_m:.0f} m an estimate may state"
    )


def in_collection(motion: Motion, calibration: Calibration) -> Motion:
    """``motion`` weighed against the calibrated collection's extent (``Motion.continuity_gain``), where the
    calibration knows it (a collection calibrated before discs does not: the full gain)."""
    extent = (calibration.disc or {}).get("extent_m")
    return motion if motion.extent_m is not None or not extent else replace(motion, extent_m=float(extent))


def sequence_estimate(places: Places, post: np.ndarray, calibration: Calibration) -> Estimate | None:
    """The estimate a step's posterior gives: its most probable state when that is a place whose posterior
    gets an estimate by the single-photo rule (``Calibration.estimate_disc``), with that rule's disc, never
    below the place's own spread plus the constant rule's margin.

    Its rate is left unstated (``radius_rate`` None): the disc's rate was measured on single answers, and
    how often a sequence's posterior of that strength holds has not been measured on the collection (the
    words then say the rate is not calibrated rather than claim the single photos' figure)."""
    best = int(np.argmax(post))
    if best >= len(places.lats):
        return None
    p = float(post[best])
    constant = max(float(places.spread_m[best]) + MARGIN_M, RADIUS_FLOOR_M)
    disc = calibration.estimate_disc(p, constant)
    if disc is None:
        return None
    radius = constant if disc[0] is None else max(disc[0], constant)
    return Estimate(float(places.lats[best]), float(places.lons[best]), radius, p, None, radius_rate=None)


def by_posterior(
    candidates: Sequence[Candidate], places: Places, post: np.ndarray, alone: tuple[float, float] | None = None
) -> list[Candidate]:
    """The candidates with the sequence's choice first: the best-ranked candidate of the place the posterior
    favours most (a candidate without a calibrated probability, or farther than ``PLACE_RADIUS_M`` from every
    place, counts 0); the others keep the photo's own order. ``alone``: the place the model favours for the
    photo by itself; when the sequence favours the same one, nothing moves.

    Why only one moves: every candidate of a place shares its posterior, and ranking them all by it filled
    the first five with one place's candidates, pushing out the other places the photo alone had ranked
    there. Why nothing moves when the sequence agrees with the photo alone: the model ranks by calibrated
    probability, the photo's own order by verified score; only what the sequence adds should reorder."""
    if not len(places.lats) or not candidates or int(np.argmax(post)) == len(places.lats):
        return list(candidates)
    best = int(np.argmax(post[:-1]))
    if alone is not None and haversine_m(places.lats[best], places.lons[best], *alone) <= PLACE_RADIUS_M:
        return list(candidates)
    lats = np.array([c.lat for c in candidates])
    lons = np.array([c.lon for c in candidates])
    d = haversine_m(lats, lons, places.lats[best], places.lons[best])
    near = [n for n, c in enumerate(candidates) if c.p_within_25m is not None and d[n] <= PLACE_RADIUS_M]
    if not near:
        return list(candidates)
    lead = near[0]
    return [candidates[lead], *(c for n, c in enumerate(candidates) if n != lead)]


def favoured_alone(observation: Observation) -> tuple[float, float] | None:
    """The place the model favours for one photo by itself (None: "not in this collection")."""
    result = solve([observation])
    places, post = result.places[0], result.posterior[0]
    k = int(np.argmax(post))
    return None if k == len(places.lats) else (float(places.lats[k]), float(places.lons[k]))


def _p_near(places, post: np.ndarray, answer: LocateAnswer) -> float | None:
    """The posterior of the place holding a confident single answer's estimate (None: no place there)."""
    e = answer.estimate
    if e.lat is None or not len(places.lats):
        return None
    d = haversine_m(places.lats, places.lons, e.lat, e.lon)
    k = int(np.argmin(d))
    return float(post[k]) if d[k] <= max(e.radius_m or 0.0, RADIUS_FLOOR_M) else None


def _shown(answer: LocateAnswer, options: LocateOptions) -> LocateAnswer:
    """The candidates the caller asked for (``top_k``, ``min_score``), each with its distance from the
    answer's estimate when it is confident."""
    e = answer.confident_estimate
    shown = [c for c in answer.candidates if c.score >= options.min_score][: options.top_k]
    return replace(
        answer,
        candidates=[
            replace(c, distance_m=None if e is None else float(haversine_m(e.lat, e.lon, c.lat, c.lon))) for c in shown
        ],
    )


# -- the use case over a data dir ---------------------------------------------------------------------
def single_options(options: LocateOptions) -> LocateOptions:
    """The options each photo is located with alone: every candidate the model reads."""
    return replace(options, top_k=max(options.top_k, SEQUENCE_K), min_score=0.0)


def check_count(n: int, most: int = MAX_PHOTOS) -> None:
    if n < MIN_PHOTOS:
        raise InvalidRequest(f"a sequence needs at least {MIN_PHOTOS} images ({n} given); for one, use /locate")
    if n > most:
        raise InvalidRequest(f"a sequence holds at most {most} images ({n} given): send it in parts")


def locate_sequence(
    service: GeolocService,
    images: Sequence[Callable[[], bytes]],
    options: LocateOptions,
    motion: Motion,
    taken_at: Sequence[str] | None = None,
    max_photos: int = MAX_PHOTOS,
    times_s: Sequence[float] | None = None,
    by_time: bool = False,
) -> SequenceAnswer:
    """The sequence use case, whole: count and times checked before anything is located; each photo read
    and located alone (``GeolocService.locate``: under its limits, holding an extraction slot, so a sequence
    holds one decoded photo at a time); a photo that cannot be located is named, all of them, and nothing is
    answered; then the path. ``images``: functions that read each photo's bytes (read twice when the times
    come from EXIF). ``times_s``: the photos' times in seconds, known already (a video's frames).
    ``by_time``: the photos come in any order (files chosen together, named by several cameras) and are
    located in the order of their times, where they all have one; the answer names each one's position
    among those given (``SequenceAnswer.images``)."""
    check_count(len(images), max_photos)
    service.collection.check_mode(options.mode)
    order = list(range(len(images)))
    if times_s is not None:
        times, times_from = list(times_s), "video"
    else:
        times, times_from = sequence_times(images, taken_at, in_order=not by_time)
        if by_time:
            order, times = taken_order(times)
    singles: list[LocateAnswer] = []
    broken: list[tuple[int, GeolocError]] = []
    wide = single_options(options)
    for n in order:
        try:
            singles.append(service.locate(images[n], wide))
        except GeolocError as e:
            if code_of(e) not in IMAGE_CODES:
                raise
            broken.append((n, e))
    if broken:
        broken.sort(key=lambda item: item[0])  # named in the order given
        words = "; ".join(f"image {n}: {e}" for n, e in broken)
        raise BrokenImagesInSequence(
            f"{len(broken)} of the {len(images)} images cannot be located ({words}); nothing was located",
            code_of(broken[0][1]),
        )
    calibration = service.answer_calibration(options)
    answer = sequence_answers(singles, times, calibration, motion, options, times_from=times_from)
    return replace(answer, images=order)
