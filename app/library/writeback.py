"""Write back only what was accepted (issue 36, point 4), with exiftool, never a hand-rolled writer.

- **Sidecar (default):** ``IMG.jpg.xmp`` beside the photo gets ``XMP-exif:GPSLatitude/GPSLongitude`` (and
  the datum); the photo itself is never opened for writing, so it stays byte for byte what it was. An
  existing sidecar is updated (exiftool keeps its other tags) after a backup copy.
- **In-file (on request):** EXIF ``GPSLatitude/Ref``, ``GPSLongitude/Ref`` written into the photo by
  exiftool, which rewrites metadata segments only; the decoded pixels are hashed before and after, and a
  write that changed them is rolled back at once.
- **Dry run:** the plan (file, target, position), nothing written.
- **Undo:** every write records its backup (or that the target was new) in the journal before exiftool
  runs, and the SHA-256 of the target as the write left it; undo restores them newest first, but only a
  target still in that state: one edited since (by the user, another tool) is skipped and reported, never
  overwritten. One file that cannot be restored is reported and the others are.
- **Withdrawn decisions:** a photo written and then rejected or cleared would keep its GPS in the sidecar
  (or EXIF); ``write_back`` undoes its writes (and says so) before writing the accepted ones.
- **What is never touched:** a symbolic link (exiftool would replace it by a regular file, and it may lead
  anywhere), and, on the server, any file outside ``GEOLOC_LIBRARY_ROOT`` (``root``), resolved paths.

Backups live in ``DATA_DIR/library-backups`` (0700): the user's folder gets nothing but sidecars."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

from PIL import Image

from app.library.photos import sidecar_path
from app.storage.library import LibraryJournal

SIDECAR, IN_FILE = "sidecar", "exif"
#: exiftool's own limit per call is the command line: a handful of tags per photo, one call per photo.
EXIFTOOL_TIMEOUT_S = 60


class WriteBackError(RuntimeError):
    """exiftool is missing or refused a file (the message says which and why)."""


@dataclass(frozen=True)
class PlannedWrite:
    photo_id: int
    file: str
    target: str
    mode: str
    lat: float
    lon: float


def exiftool() -> str:
    path = shutil.which("exiftool")
    if path is None:
        raise WriteBackError(
            "exiftool is not installed: apt-get install libimage-exiftool-perl (the Docker image carries it)"
        )
    return path


def pixel_hash(path: Path) -> str:
    """SHA-256 of the decoded pixels (orientation not applied: the stored pixels are what must not change)."""
    with Image.open(path) as img:
        img.load()
        return hashlib.sha256(img.mode.encode() + repr(img.size).encode() + img.tobytes()).hexdigest()


def file_sha(path: Path) -> str:
    """SHA-256 of the file's bytes (what undo compares to tell our write from a later edit)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_target(target: Path, root: Path | None) -> None:
    """Refuse to write or restore ``target`` when it is a symbolic link, or (``root`` given) when its real
    place lies outside ``root``: a journal row names a path, and the path may have changed since."""
    if target.is_symlink():
        raise WriteBackError(f"{target.name} is a symbolic link: not written through")
    if root is not None:
        real = target.parent.resolve() / target.name
        if real.parent != root and root not in real.parent.parents:
            raise WriteBackError(f"{target.name} lies outside the library root: not touched")


def plan(journal: LibraryJournal, sid: str, in_file: bool = False) -> list[PlannedWrite]:
    """The accepted photos whose accepted position is not yet written."""
    mode = IN_FILE if in_file else SIDECAR
    out = []
    for rec in journal.photos(sid):
        pos = rec.accepted_position
        if pos is None:
            continue
        w = rec.written
        if w is not None and (w["lat"], w["lon"]) == pos and w["mode"] == mode:
            continue
        target = rec.path if in_file else str(sidecar_path(Path(rec.path)))
        out.append(PlannedWrite(rec.id, rec.path, target, mode, pos[0], pos[1]))
    return out


def withdrawn(journal: LibraryJournal, sid: str) -> list[str]:
    """The photos written earlier and no longer accepted (rejected, cleared): their writes are to go."""
    return [r.path for r in journal.photos(sid) if r.written is not None and r.accepted_position is None]


def write_back(
    journal: LibraryJournal,
    sid: str,
    data_dir: Path,
    in_file: bool = False,
    dry_run: bool = False,
    root: Path | None = None,
) -> dict:
    """Carry out (or, with ``dry_run``, only list) ``plan``, after undoing the writes of photos no longer
    accepted. A file exiftool refuses is reported and the others are written. Returns ``{"dry_run",
    "written": [...], "failed": [{"file", "reason"}], "withdrawn": {undo's answer for those photos}}``."""
    planned = plan(journal, sid, in_file)
    if dry_run:
        gone = withdrawn(journal, sid)
        return {"dry_run": True, "written": [asdict(p) for p in planned], "failed": [], "withdrawn": gone}
    taken_back = {"restored": [], "skipped": [], "failed": []}
    for rec in journal.photos(sid):
        if rec.written is not None and rec.accepted_position is None:
            got = undo(journal, sid, root, photo_id=rec.id)
            for k in taken_back:
                taken_back[k] += got[k]
    tool = exiftool() if planned else ""
    backups = Path(data_dir) / "library-backups"
    backups.mkdir(mode=0o700, exist_ok=True)
    written, failed = [], []
    for p in planned:
        try:
            _write_one(journal, sid, tool, backups, p, root)
            written.append(asdict(p))
        except (WriteBackError, OSError) as e:
            failed.append({"file": p.file, "reason": str(e)})
    return {"dry_run": False, "written": written, "failed": failed, "withdrawn": taken_back}


def _write_one(journal: LibraryJournal, sid: str, tool: str, backups: Path, p: PlannedWrite, root: Path | None) -> None:
    target = Path(p.target)
    check_target(target, root)
    check_target(Path(p.file), root)  # a sidecar beside a linked photo: the link may not be ours either
    backup = None
    if target.exists():
        backup = backups / f"{uuid.uuid4().hex}{target.suffix}"
        shutil.copy2(target, backup)
    write_id = journal.add_write(sid, p.photo_id, p.mode, target, backup)
    try:
        _run_exiftool(tool, target, backup, p)
    except BaseException:
        journal.mark_undone(write_id)  # put back already: nothing for undo to do
        raise
    journal.wrote(write_id, file_sha(target))
    if p.mode == IN_FILE:
        st = target.stat()
        journal.restat(p.photo_id, st.st_size, st.st_mtime_ns)
    journal.set_written(p.photo_id, {"mode": p.mode, "target": str(target), "lat": p.lat, "lon": p.lon})


def _run_exiftool(tool: str, target: Path, backup: Path | None, p: PlannedWrite) -> None:
    """Write ``p``'s position into ``target``, checked; on any failure ``target`` is put back first."""
    before = pixel_hash(target) if p.mode == IN_FILE else None
    ns, ew = ("N" if p.lat >= 0 else "S"), ("E" if p.lon >= 0 else "W")
    if p.mode == IN_FILE:
        tags = [
            f"-EXIF:GPSLatitude={abs(p.lat)}",
            f"-EXIF:GPSLatitudeRef={ns}",
            f"-EXIF:GPSLongitude={abs(p.lon)}",
            f"-EXIF:GPSLongitudeRef={ew}",
            "-EXIF:GPSMapDatum=WGS-84",
        ]
    else:
        tags = [f"-XMP-exif:GPSLatitude={p.lat}", f"-XMP-exif:GPSLongitude={p.lon}", "-XMP-exif:GPSMapDatum=WGS-84"]
    # "--" ends the options: a file named "-something" is a file, never an option.
    cmd = [tool, "-q", "-q", "-m", "-overwrite_original", *tags, "--", str(target)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=EXIFTOOL_TIMEOUT_S)
    if done.returncode != 0 or not target.exists():
        _restore(target, backup)
        raise WriteBackError(f"exiftool refused {target.name}: {(done.stderr or done.stdout).strip()[:300]}")
    # -m lets exiftool pass over a photo's minor metadata faults, and then it may leave a damaged EXIF block
    # unchanged and still exit 0: what was written is read back before it counts.
    got = read_gps(tool, target)
    if got is None or abs(got[0] - p.lat) > 1e-6 or abs(got[1] - p.lon) > 1e-6:
        _restore(target, backup)
        raise WriteBackError(f"exiftool could not write GPS into {target.name} (its metadata may be damaged)")
    if before is not None and pixel_hash(target) != before:
        _restore(target, backup)
        raise WriteBackError(f"{target.name}: the pixel data changed in the write; the original was put back")


def read_gps(tool: str, path: Path) -> tuple[float, float] | None:
    """The GPS position exiftool reads in ``path`` (a photo or a sidecar), signed degrees; None if none."""
    done = subprocess.run(
        [tool, "-n", "-j", "-GPSLatitude", "-GPSLongitude", "--", str(path)],
        capture_output=True,
        text=True,
        timeout=EXIFTOOL_TIMEOUT_S,
    )
    try:
        got = json.loads(done.stdout)[0]
        return float(got["GPSLatitude"]), float(got["GPSLongitude"])
    except (ValueError, KeyError, IndexError, TypeError):
        return None


def _restore(target: Path, backup: Path | None) -> None:
    """Put ``target`` back as it was: its backup copied over it atomically, or removed if it was new."""
    if backup is None:
        target.unlink(missing_ok=True)
        return
    tmp = target.with_name(f".{target.name}.geoloc-undo")
    shutil.copy2(backup, tmp)
    os.replace(tmp, target)


def undo(journal: LibraryJournal, sid: str, root: Path | None = None, photo_id: int | None = None) -> dict:
    """Undo every write of this library (or of one photo) not yet undone, newest first; the decisions stay
    (write again to redo). A target changed since our write (its SHA-256 differs, or it is gone) is
    skipped and reported, and its older writes with it (they no longer describe the file); one that cannot
    be restored (an OSError, a link, outside ``root``) is reported and the others go on. Returns
    ``{"restored": [target], "skipped": [{"target", "reason"}], "failed": [{"target", "reason"}]}``."""
    restored, skipped, failed = [], [], []
    for w in journal.live_writes(sid, photo_id):
        target = Path(w["target"])
        backup = Path(w["backup"]) if w["backup"] else None
        try:
            check_target(target, root)
            changed = _changed_since(target, w["after_sha"])
            if changed is not None:
                skipped.append({"target": str(target), "reason": changed})
            else:
                _restore(target, backup)
                restored.append(str(target))
        except (WriteBackError, OSError) as e:
            failed.append({"target": str(target), "reason": str(e)})
            continue
        journal.mark_undone(w["id"])
        journal.set_written(w["photo"], None)
        if w["mode"] == IN_FILE and target.exists():
            st = target.stat()
            journal.restat(w["photo"], st.st_size, st.st_mtime_ns)
    return {"restored": restored, "skipped": skipped, "failed": failed}


def _changed_since(target: Path, after_sha: str | None) -> str | None:
    """Why ``target`` is no longer as our write left it, or None. A write with no recorded hash never
    finished (the process died in exiftool): its backup is what the file was, and it is put back."""
    if after_sha is None:
        return None
    if not target.exists():
        return "gone since it was written: nothing to restore"
    if file_sha(target) != after_sha:
        return "changed since it was written (by hand or another tool): left as it is"
    return None
