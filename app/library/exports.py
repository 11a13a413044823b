"""Exports for GIS: GeoJSON (RFC 7946), CSV and GPX.

``accepted`` (the default of `geoloc library export`): the positions the user accepted or moved, nothing
else. ``suggestions`` (what a scan writes, or ``--all``): every located photo, placed or not, with its radius,
rate, basis and reason. RFC 7946: a FeatureCollection of Features whose coordinates are [lon, lat] in WGS 84;
a photo with no position is a Feature with ``"geometry": null`` and its reason in its properties. GPX has no
way to say "no position", so its file holds the placed photos only (waypoints, by gpxpy). With
``everything``, a file the scan could not read is there too, unplaced, with its reason (reason_code
``unreadable``): "all" means every photo without a position from the library, not only the readable ones.

CSV cells are opened by spreadsheets, which run a cell starting with ``= + - @`` (or a tab or carriage
return before one) as a formula; file names and cameras come from the user's files and EXIF, so such a
text cell gets a leading ``'`` (OWASP's CSV-injection rule). Numbers are written as numbers. Rows end in CRLF
(RFC 4180): Python's writer quotes a cell only for the characters of its line ending, so with a bare ``\n`` a
file name holding a carriage return would split its row.

File names are whatever the file system allows, so any text may hold characters a file cannot: a lone
surrogate (how Python spells bytes that are not UTF-8) has no UTF-8 form, and XML 1.0 forbids most C0
controls (ESC, NUL...) and U+FFFE/U+FFFF even as character references. Each becomes U+FFFD: lone surrogates
in every export, the characters XML forbids in the GPX; JSON and CSV carry the controls as they are."""

from __future__ import annotations

import csv
import io
import json
import os
import re
from pathlib import Path

import gpxpy.gpx

from app.storage.library import LOCATED, PROBLEM, PhotoRecord

FORMATS = ("geojson", "csv", "gpx")
CSV_COLUMNS = (
    "file", "lat", "lon", "radius_m", "placed", "confident", "p", "basis", "decision", "reason_code", "reason",
    "taken", "camera", "note", "candidates",
)  # fmt: skip


#: Characters with no UTF-8 form: the halves of a surrogate pair, which a Python str can hold alone.
LONE_SURROGATE = re.compile("[\ud800-\udfff]")
#: Characters outside XML 1.0's Char production (#x9 | #xA | #xD | [#x20-#xD7FF] | [#xE000-#xFFFD] |
#: [#x10000-#x10FFFF]): no XML file may hold them, escaped or not.
XML_FORBIDDEN = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def encodable(value: object) -> object:
    """``value`` with its lone surrogates as U+FFFD, so that any export can be written as UTF-8."""
    return LONE_SURROGATE.sub("\ufffd", value) if isinstance(value, str) else value


def xml_text(value: str) -> str:
    """``value`` with what XML 1.0 forbids as U+FFFD: one ESC in a file name would make the GPX unreadable."""
    return XML_FORBIDDEN.sub("\ufffd", value)


def rows(records: list[PhotoRecord], everything: bool) -> list[dict]:
    """One flat row per photo: the accepted ones only, or (``everything``) every located photo."""
    out = []
    for rec in records:
        if rec.kind == PROBLEM and everything:
            out.append(_unreadable(rec))
            continue
        if rec.kind != LOCATED:
            continue
        r = rec.result
        accepted = rec.accepted_position
        if not everything and accepted is None:
            continue
        lat, lon = accepted if accepted is not None else (r.get("lat"), r.get("lon"))
        placed = accepted is not None or bool(r.get("placed"))
        moved = accepted is not None and accepted != (r.get("lat"), r.get("lon"))
        out.append(
            {
                "file": rec.path,
                "lat": lat if placed else None,
                "lon": lon if placed else None,
                "radius_m": None if moved or not placed else r.get("radius_m"),
                "placed": placed,
                "confident": bool(r.get("confident")),
                "p": r.get("p"),
                "basis": "user" if moved else r.get("basis"),
                "decision": rec.decision,
                "reason_code": None if placed else r.get("reason_code"),
                "reason": None if placed else r.get("reason"),
                "taken": r.get("taken"),
                "camera": r.get("camera"),
                "note": r.get("note"),
                "candidates": r.get("candidates") or [],
            }
        )
    return out


def _unreadable(rec: PhotoRecord) -> dict:
    """A file the scan could not use, as an unplaced row with its reason."""
    return {
        "file": rec.path, "lat": None, "lon": None, "radius_m": None, "placed": False, "confident": False,
        "p": None, "basis": None, "decision": None, "reason_code": "unreadable",
        "reason": rec.result.get("reason"), "taken": None, "camera": None, "note": None, "candidates": [],
    }  # fmt: skip


FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> object:
    """A value as a CSV cell no spreadsheet runs: text starting like a formula gets a leading ``'``."""
    if value is None:
        return ""
    if isinstance(value, str) and value.startswith(FORMULA_START):
        return "'" + value
    return value


def geojson(table: list[dict]) -> str:
    features = []
    for row in table:
        props = {k: v for k, v in row.items() if k not in ("lat", "lon")}
        geometry = None
        if row["placed"]:
            geometry = {"type": "Point", "coordinates": [round(row["lon"], 7), round(row["lat"], 7)]}
        features.append({"type": "Feature", "geometry": geometry, "properties": props})
    return json.dumps({"type": "FeatureCollection", "features": features}, indent=1)


def csv_text(table: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\r\n")
    w.writeheader()
    for row in table:
        cands = "; ".join(f"{c['lat']:.7f} {c['lon']:.7f} {c['score']}" for c in row["candidates"])
        w.writerow({**{k: csv_cell(v) for k, v in row.items()}, "candidates": cands})
    return buf.getvalue()


def gpx_text(table: list[dict]) -> str:
    doc = gpxpy.gpx.GPX()
    doc.creator = "geoloc library"  # every text below goes through xml_text: gpxpy escapes markup only
    for row in table:
        if not row["placed"]:
            continue
        desc = f"basis {row['basis']}" + (f", radius {row['radius_m']} m" if row["radius_m"] is not None else "")
        doc.waypoints.append(
            gpxpy.gpx.GPXWaypoint(
                latitude=row["lat"],
                longitude=row["lon"],
                name=xml_text(os.path.basename(row["file"])),
                description=xml_text(desc),
            )
        )
    # A parser reads a raw carriage return as a newline (XML's end-of-line rule); as a reference it stays one.
    # gpxpy writes none of its own, so every one left is in a name or a description.
    return doc.to_xml().replace("\r", "&#13;")


RENDER = {"geojson": geojson, "csv": csv_text, "gpx": gpx_text}
MEDIA_TYPES = {"geojson": "application/geo+json", "csv": "text/csv", "gpx": "application/gpx+xml"}


def render(records: list[PhotoRecord], fmt: str, everything: bool) -> str:
    if fmt not in RENDER:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    table = [{k: encodable(v) for k, v in row.items()} for row in rows(records, everything)]
    return RENDER[fmt](table)


def write_export(records: list[PhotoRecord], fmt: str, everything: bool, out: Path) -> int:
    """Write one export atomically (a half-written GeoJSON is worse than none); returns its rows."""
    text = render(records, fmt, everything)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(text, encoding="utf-8")  # never the locale's: a C locale cannot write "é"
    os.replace(tmp, out)
    return len(rows(records, everything))
