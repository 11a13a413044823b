"""Text that people read back (labels, capture times, file names used as labels): one rule for every way
in (the form, ``metadata``, PATCH, file names, the command line's sources).

Control characters (C0, DEL, C1) and the bidirectional controls are refused, never stored: a NUL or an
escape sequence garbles a terminal or a log line, and U+202E makes ``photo<RLO>gpj.exe`` read as
``photoexe.jpg``. Joiners (U+200C, U+200D) stay allowed: Persian, Indic scripts and emoji need them."""

from __future__ import annotations

import unicodedata

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
