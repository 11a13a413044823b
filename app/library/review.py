"""A decision per photo: accept the suggestion, move the pin (accept another position)
or reject. Nothing is written here: ``app.library.writeback`` writes only what was accepted."""

from __future__ import annotations

from app.engine.geo import valid_position
from app.storage.library import ACCEPTED, LOCATED, REJECTED, LibraryJournal, PhotoRecord

ACTIONS = ("accept", "move", "reject", "clear")


class DecisionError(ValueError):
    """A decision that cannot be taken (no such photo, nothing to accept, a position out of range)."""


def decide(
    journal: LibraryJournal, sid: str, photo_id: int, action: str, lat: float | None = None, lon: float | None = None
) -> PhotoRecord:
    """Record the decision and return the photo as it now stands. ``accept`` takes the suggested position
    (a photo with none must be moved instead); ``move`` takes ``lat``/``lon``; ``clear`` forgets the
    decision. A decision changes nothing already written: write again, or undo."""
    rec = journal.photo(sid, photo_id)
    if rec is None or rec.kind != LOCATED:
        raise DecisionError(f"photo {photo_id} is not a located photo of this library")
    if action == "accept":
        r = rec.result
        if not r.get("placed"):
            raise DecisionError(f"{rec.path} has no suggested position to accept: move the pin to place it")
        journal.decide(photo_id, ACCEPTED, r["lat"], r["lon"])
    elif action == "move":
        if lat is None or lon is None or not valid_position(lat, lon):
            raise DecisionError(f"move needs lat and lon in range (lat -90..90, lon -180..180), got {lat},{lon}")
        journal.decide(photo_id, ACCEPTED, float(lat), float(lon))
    elif action == "reject":
        journal.decide(photo_id, REJECTED, None, None)
    elif action == "clear":
        journal.decide(photo_id, None, None, None)
    else:
        raise DecisionError(f"action must be one of {', '.join(ACTIONS)}, got {action!r}")
    got = journal.photo(sid, photo_id)
    assert got is not None
    return got
