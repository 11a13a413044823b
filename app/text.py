"""Text that people read back (labels, capture times, file names used as labels): one rule for every way
in (the form, ``metadata``, PATCH, file names, the command line's sources).

Control characters (C0, DEL, C1) and the bidirectional controls are refused, never stored: a NUL or an
escape sequence garbles a terminal or a log line, and U+202E makes ``photo<RLO>gpj.exe`` read as
``photoexe.jpg``. Joiners (U+200C, U+200D) stay allowed: Persian, Indic scripts and emoji need them."""

from __future__ import annotations

import re
import unicodedata
from datetime import date, datetime

LABEL_MAX = 200
CAPTURED_AT_MAX = 64
#: The bidirectional controls (Unicode category Cf): marks, embeddings, overrides and isolates.
BIDI_CONTROLS = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def unsafe_character(text: str) -> str | None:
    """The first character that must not be stored, written as U+XXXX; None when there is none.
    Lone surrogates (Cs) are refused too: SQLite could not encode them."""
    for ch in text:
        if ch in BIDI_CONTROLS or unicodedata.category(ch) in ("Cc", "Cs"):
            return f"U+{ord(ch):04X}"
    return None


def readable(text: str) -> str:
    """``text`` unchanged, or ValueError naming the character (pydantic turns it into a 422)."""
    bad = unsafe_character(text)
    if bad is not None:
        raise ValueError(f"contains the control character {bad}")
    return text


# -- capture times: ISO 8601 ---------------------------------------------------------------------------------
#: ISO 8601 extended form: a date, or a date and time (a space for the T is read too), with an optional zone.
_ISO = re.compile(r"\d{4}-\d{2}-\d{2}(?:[T ]\d{2}:\d{2}(?::\d{2}(?:\.\d{1,6})?)?(?:Z|[+-]\d{2}:\d{2})?)?")
#: EXIF's DateTimeOriginal ("2024:09:23 16:08:20"), with OffsetTimeOriginal appended when the photo has one.
_EXIF = re.compile(r"(\d{4}):(\d{2}):(\d{2}) (\d{2}:\d{2}:\d{2})((?:[+-]\d{2}:\d{2})?)")


def iso_captured_at(text: str) -> str:
    """A capture time as ISO 8601 in its extended form: ``2024-09-23`` or ``2024-09-23T16:08:20``, with a
    zone (``+02:00``; ``Z`` is written ``+00:00``) only when one was given; without one it is the camera's
    local time, as EXIF records it. EXIF's own form is converted, so every answer carries one format.
    ValueError for anything else ("yesterday", a 13th month): a capture time a client cannot parse back is
    worse than none."""
    exif = _EXIF.fullmatch(text)
    if exif:
        text = f"{exif[1]}-{exif[2]}-{exif[3]}T{exif[4]}{exif[5]}"
    if not _ISO.fullmatch(text):
        raise ValueError(
            f"must be an ISO 8601 date or date-time such as 2024-09-23T16:08:20 (a zone, Z or +02:00, is "
            f"optional), not {text[:40]!r}"
        )
    try:
        if len(text) == 10:
            return date.fromisoformat(text).isoformat()
        when = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a real date and time") from None
    return when.isoformat(timespec="microseconds" if when.microsecond else "seconds")


def iso_or_as_stored(text: str | None) -> str | None:
    """A stored capture time for an answer: ISO 8601 when it can be read as one (rows stored before the
    conversion hold EXIF's form), else as stored."""
    if text is None:
        return None
    try:
        return iso_captured_at(text)
    except ValueError:
        return text
