"""The evaluation's sequences (``geoloc eval --sequence-window N``): each query photo answered with the photos
around it in its walk, beside the same photo answered alone, on the same folds.

The manifest's query rows form sequences: a ``sequence`` column groups them, ordered by a ``time`` column
where every row of the sequence has one, else by row order; a manifest without ``sequence`` is one sequence
in row order. Each photo is answered from a window of ``window`` photos of its sequence: centred on it
(offline), or ending at it (``online``: only the photos before it, as a robot would). The answers come from
``app.usecases.sequence.sequence_answers``, the function /locate/sequence calls, over the single answers
the evaluation already made (``locate_features``), judged by the fold's own calibration."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from app.domain import LocateAnswer, LocateOptions
from app.engine.calibration import Calibration
from app.engine.sequence import Motion
from app.manifests import Row
from app.usecases.sequence import sequence_answers
from app.usecases.sequence_inputs import parse_time, seconds


@dataclass(frozen=True)
class SequenceWindow:
    """How the evaluation forms each photo's sequence."""

    window: int
    online: bool = False
    motion: Motion = Motion()


def sequences(rows: Sequence[Row], idx: Sequence[int]) -> list[tuple[list[int], list[float | None]]]:
    """The query rows ``idx`` grouped into sequences (first appearance order), each in time order where every
    row has a time, with each row's time in seconds (None: order only)."""
    groups: dict[str | None, list[int]] = {}
    for i in idx:
        groups.setdefault(rows[i].sequence, []).append(i)
    out = []
    for members in groups.values():
        if all(rows[i].time for i in members):
            secs = dict(
                zip(members, seconds([parse_time(rows[i].time, n) for n, i in enumerate(members)]), strict=True)
            )
            members = sorted(members, key=lambda i: (secs[i], i))
            out.append((members, [secs[i] - secs[members[0]] for i in members]))
        else:
            out.append((members, [None] * len(members)))
    return out


def window_of(position: int, length: int, window: SequenceWindow) -> tuple[int, int]:
    """[start, end) of the photo at ``position``'s window in a sequence of ``length``."""
    n = max(window.window, 1)
    if window.online:
        return max(0, position - n + 1), position + 1
    start = max(0, position - (n - 1) // 2)
    return start, min(length, start + n)


def answer_in_windows(
    rows: Sequence[Row],
    idx: Sequence[int],
    singles: dict[int, LocateAnswer],
    calibration: Calibration,
    window: SequenceWindow,
    options: LocateOptions,
) -> dict[int, tuple[LocateAnswer, str]]:
    """Each query row's answer with its window of its sequence, and what it rests on."""
    out = {}
    for members, secs in sequences(rows, idx):
        for pos, i in enumerate(members):
            a, b = window_of(pos, len(members), window)
            result = sequence_answers(
                [singles[j] for j in members[a:b]], secs[a:b], calibration, window.motion, options
            )
            photo = result.photos[pos - a]
            out[i] = (photo.answer, photo.rests_on)
    return out
