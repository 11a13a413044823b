"""What a library scan needs to know about one file before any pixels are decoded: its GPS, when it was
taken (EXIF DateTimeOriginal with OffsetTimeOriginal) and by which camera (Make + Model).

Why only the header: a library holds 10^4-10^5 photos, and this pass decides which are references and which
are to be located; Pillow reads the EXIF block without decoding the image. A file that cannot be read, or
whose EXIF is broken, is described (``problem``) instead of raising, so one bad file stops nothing else."""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from app.engine.imageio import gps_is_estimate, read_exif_gps
from app.user_files import opened

MAKE, MODEL = 0x010F, 0x0110
ESTIMATED_NOTE = "its GPS is this service's estimate (written back earlier), not a measurement: located again"


@dataclass(frozen=True)
class PhotoMeta:
    """One file of the library, as its header describes it."""

    path: Path
    size: int
    mtime_ns: int
    gps: tuple[float, float] | None = None
    taken: datetime | None = None  # aware when the photo states its offset, naive (local time) otherwise
    camera: str | None = None  # "Make Model", e.g. "Apple iPhone 13"
    problem: str | None = None  # why the file cannot be used (unreadable, not an image)
    note: str | None = None  # a usable photo whose metadata is broken: located from its pixels alone

    @property
    def taken_iso(self) -> str | None:
        return self.taken.isoformat() if self.taken else None


def parse_exif_time(text: str | None) -> datetime | None:
    """``2024:09:23 16:08:20`` (+ ``-04:00`` when EXIF gives the offset) as a datetime; None when absent or
    malformed (cameras without a clock write zeros)."""
    if not text:
        return None
    stamp, zone = text[:19], text[19:]
    try:
        taken = datetime.strptime(stamp, "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    if len(zone) == 6 and zone[0] in "+-":
        try:
            hours, minutes = int(zone[1:3]), int(zone[4:6])
        except ValueError:
            return taken
        sign = 1 if zone[0] == "+" else -1
        taken = taken.replace(tzinfo=timezone(sign * timedelta(hours=hours, minutes=minutes)))
    return taken


def read_meta(path: Path, within: Path | None = None) -> PhotoMeta:
    """The header of ``path``; never raises (a problem is reported in ``problem``). With ``within`` (the
    scanned folder, resolved) the file is read only if it is a regular file there, not a link
    (``app.user_files``): the folder may have changed since it was listed. A pipe or device is a problem,
    never waited on. GPS that this service wrote as its own estimate is no GPS: the photo is located again.

    A file name that is not UTF-8 (bytes from an old camera or another system's encoding) cannot be kept in
    the journal, nor in a GeoJSON or CSV: the file is a problem under a printable form of its name (the
    undecodable bytes shown as U+FFFD), and the scan goes on."""
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        shown = name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
        return PhotoMeta(Path(shown), 0, 0, problem="the file name is not UTF-8: rename the file to scan it")
    try:
        with opened(path, within) as (f, st):
            return _header(path, f, st)
    except OSError as e:
        return PhotoMeta(path, 0, 0, problem=f"cannot read the file: {e.strerror or e}")


def _header(path: Path, f, st: os.stat_result) -> PhotoMeta:
    try:
        with Image.open(f) as img:
            broken = _broken_exif(img)
            if broken is not None:
                note = f"EXIF unreadable ({broken}): located from its pixels alone, without the time prior"
                return PhotoMeta(path, st.st_size, st.st_mtime_ns, note=note)
            gps, taken = read_exif_gps(img)
            camera = _camera(img)
            note = ESTIMATED_NOTE if gps is None and gps_is_estimate(img) else None
    except UnidentifiedImageError:
        return PhotoMeta(path, st.st_size, st.st_mtime_ns, problem="not an image (no format Pillow reads)")
    except (OSError, ValueError, SyntaxError) as e:
        return PhotoMeta(path, st.st_size, st.st_mtime_ns, problem=f"unreadable: {e}")
    return PhotoMeta(path, st.st_size, st.st_mtime_ns, gps, parse_exif_time(taken), camera, note=note)


def _broken_exif(img: Image.Image) -> str | None:
    """Why the photo's EXIF block cannot be parsed, or None (no block, or a sound one). Pillow raises many
    kinds of exception on a damaged block; the pixels are still there."""
    try:
        exif = img.getexif()
        exif.get_ifd(0x8769)
        exif.get_ifd(0x8825)
    except Exception as e:
        return f"{type(e).__name__}: {e}"
    if img.info.get("exif") and len(exif) == 0:
        return "an EXIF block with no readable entry"
    return None


def _camera(img: Image.Image) -> str | None:
    try:
        exif = img.getexif()
        parts = [str(exif.get(tag) or "").strip("\x00 ") for tag in (MAKE, MODEL)]
    except Exception:  # broken EXIF: the camera is unknown, the photo still usable
        return None
    name = " ".join(p for p in parts if p)
    return name or None


def same_stat(meta: PhotoMeta, size: int, mtime_ns: int) -> bool:
    """Whether a journalled file is unchanged (the ingest journal's rule: path, size and mtime)."""
    return meta.size == size and meta.mtime_ns == mtime_ns


def sidecar_path(photo: Path) -> Path:
    """Where the XMP sidecar of ``photo`` lives: ``IMG_1.jpg.xmp`` (darktable's, digiKam's and immich's
    naming: two photos differing only in extension keep separate sidecars)."""
    return photo.with_name(photo.name + ".xmp")


def walk_photos(root: Path, skip: Path | None = None) -> list[Path]:
    """The library's photos (the ingest folder rule: recursive, sorted, hidden files skipped). ``skip``:
    a folder never entered (the data dir, when it lies inside the library: its stored images and undo
    backups are the service's own files, not photos to journal or write into).

    Symbolic links are skipped, files and folders alike: a link may lead out of the folder (or out of the
    server's library root), and reading, thumbnailing or writing through it would touch a file the user
    did not put in the library (exiftool would even replace the link with a regular file)."""
    from app.ingestion.sources import IMAGE_SUFFIXES

    out = []
    for folder, dirs, files in os.walk(root):  # followlinks=False: a linked folder is listed, never entered
        dirs[:] = sorted(
            d
            for d in dirs
            if not d.startswith(".")
            and not os.path.islink(os.path.join(folder, d))
            and not (skip is not None and Path(folder, d).resolve() == skip)
        )
        out += [
            Path(folder) / n
            for n in sorted(files)
            if not n.startswith(".")
            and os.path.splitext(n)[1].lower() in IMAGE_SUFFIXES
            and not os.path.islink(os.path.join(folder, n))
        ]
    return out
