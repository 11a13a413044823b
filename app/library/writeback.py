"""Write back only what was accepted, with exiftool, never a hand-rolled writer.

- **Sidecar (default):** ``IMG.jpg.xmp`` beside the photo gets ``XMP-exif:GPSLatitude/GPSLongitude`` (and
  the datum); the photo itself is never opened for writing, so it stays byte for byte what it was. An
  existing sidecar is updated (exiftool keeps its other tags).
- **In-file (on request):** EXIF ``GPSLatitude/Ref``, ``GPSLongitude/Ref`` written into the photo by
  exiftool, which rewrites metadata segments only; the decoded pixels are hashed before and after, and a
  write that changed them is refused.
- **Marked as an estimate:** every write also sets GPSProcessingMethod to ``ESTIMATE_MARK``, so that the
  position is never taken for a measured one again, by any library or ingest (``app.engine.imageio``).
- **How a write is made:** exiftool edits a copy in ``DATA_DIR/library-staging``; the result is read back
  and checked; the journal records the backup of the target (``DATA_DIR/library-backups``, 0700), the
  SHA-256 of the target before and of what the write will leave; only then is the target replaced, by one
  rename in its folder. A failure at any step (a full disk, an immutable file) leaves the user's folder as
  it was, without temporary files; a crash leaves the journal knowing both hashes.
- **A photo changed since it was located** (its size or mtime differ from the journal's) is not written:
  the position was decided for another picture.
- **Dry run:** the plan (file, target, position), nothing written.
- **Undo:** newest first, a target is restored only when it is as our write left it; one as before (the
  process stopped before the rename) needs nothing; one edited since (by the user, another tool) is
  skipped and reported, never overwritten. One file that cannot be restored is reported and the others are.
- **Withdrawn decisions:** a photo written and then rejected or cleared would keep its GPS in the sidecar
  (or EXIF); ``write_back`` undoes its writes (and says so) before writing the accepted ones.
- **What is never touched:** a symbolic link (exiftool would replace it by a regular file, and it may lead
  anywhere), a folder whose path now runs through a link (journalled paths are resolved: every read,
  write and rename goes through a descriptor of the folder, checked once), the data dir, and, on the
  server, any file outside ``GEOLOC_LIBRARY_ROOT`` (``root``)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import stat
import subprocess
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

from PIL import Image

from app.engine.imageio import ESTIMATE_MARK
from app.library.photos import sidecar_path
from app.storage.library import BACKUPS_DIR, STAGING_DIR, LibraryJournal
from app.user_files import is_within, real_path

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
    size: int  # the photo as it was located: a photo changed since is not written
    mtime_ns: int


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
        out.append(PlannedWrite(rec.id, rec.path, target, mode, pos[0], pos[1], rec.size, rec.mtime_ns))
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
    written, failed = [], []
    for p in planned:
        try:
            _write_one(journal, sid, tool, Path(data_dir), p, root)
            written.append(asdict(p))
        except (WriteBackError, OSError) as e:
            failed.append({"file": p.file, "reason": str(e)})
    return {"dry_run": False, "written": written, "failed": failed, "withdrawn": taken_back}


def _write_one(
    journal: LibraryJournal, sid: str, tool: str, data_dir: Path, p: PlannedWrite, root: Path | None
) -> None:
    """Write ``p`` (see the module docstring): staged and checked in the data dir, journalled with the hash
    it is about to leave, then put in place by one rename in the photo's folder."""
    photo, target = Path(p.file), Path(p.target)
    folder = open_folder(photo.parent, root, data_dir)
    try:
        _, st = read_at(folder, photo.name, required=True)
        if (st.st_size, st.st_mtime_ns) != (p.size, p.mtime_ns):
            raise WriteBackError(
                f"{photo.name} changed since it was located (edited, or replaced by another file): not written; "
                "scan again to locate it anew"
            )
        before, before_st = read_at(folder, target.name)
        staged = _staging(data_dir) / f"{uuid.uuid4().hex}{target.suffix}"
        try:
            if before is not None:
                _write_file(staged, before)
            _run_exiftool(tool, staged, p)
            after = staged.read_bytes()
        finally:
            staged.unlink(missing_ok=True)
        backup = None
        if before is not None:
            backup = _backups(data_dir) / f"{uuid.uuid4().hex}{target.suffix}"
            _write_file(backup, before)
        before_sha = None if before is None else _sha(before)
        write_id = journal.add_write(sid, p.photo_id, p.mode, target, backup, before_sha, _sha(after))
        try:
            replace_at(folder, target.name, after, None if before_st is None else before_st.st_mode)
        except BaseException:
            journal.mark_undone(write_id)  # the target was never replaced: nothing for undo to do
            raise
        if p.mode == IN_FILE:
            now = os.stat(target.name, dir_fd=folder, follow_symlinks=False)
            journal.restat(p.photo_id, now.st_size, now.st_mtime_ns)
        journal.set_written(p.photo_id, {"mode": p.mode, "target": str(target), "lat": p.lat, "lon": p.lon})
    finally:
        os.close(folder)


def _staging(data_dir: Path) -> Path:
    path = Path(data_dir) / STAGING_DIR
    path.mkdir(mode=0o700, exist_ok=True)
    return path


def _backups(data_dir: Path) -> Path:
    path = Path(data_dir) / BACKUPS_DIR
    path.mkdir(mode=0o700, exist_ok=True)
    return path


def _write_file(path: Path, data: bytes) -> None:
    """``data`` into a new file of the data dir, on disk before the journal names it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def open_folder(folder: Path, root: Path | None, data_dir: Path) -> int:
    """A descriptor of the photo's folder, through which every later read, write and rename goes, so that
    nothing changed in its path afterwards can redirect them. Refused (``WriteBackError``) when the folder
    is no longer the one scanned (a link put in its path: journalled paths are resolved), lies outside
    ``root``, or inside the data dir (the service's own files)."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise WriteBackError(f"{folder} cannot be opened: {e.strerror or e}") from None
    real = real_path(fd, folder)
    reason = None
    if real != Path(folder):
        reason = f"{folder} now leads to {real} (a symbolic link in its path): not written through"
    elif root is not None and not is_within(real, root):
        reason = f"{folder.name} lies outside the library root: not touched"
    elif is_within(real, Path(data_dir).resolve()):
        reason = f"{folder} lies inside the data dir: the service's own files are never written"
    if reason is not None:
        os.close(fd)
        raise WriteBackError(reason)
    return fd


def read_at(folder: int, name: str, required: bool = False) -> tuple[bytes | None, os.stat_result | None]:
    """The bytes and ``fstat`` of ``name`` in ``folder``, (None, None) when there is no such file (unless
    ``required``); a link, pipe or folder there is refused."""
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0), dir_fd=folder)
    except FileNotFoundError:
        if required:
            raise WriteBackError(f"{name} is gone since the scan: not written") from None
        return None, None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise WriteBackError(f"{name} is a symbolic link: not written through") from None
        raise
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise WriteBackError(f"{name} is not a regular file: not touched")
        return f.read(), st


def replace_at(folder: int, name: str, data: bytes, mode: int | None) -> None:
    """``name`` in ``folder`` replaced by ``data`` at once (a hidden file beside it, renamed over it), with
    the permissions it had (``mode``; None: a new file). A failure (a full disk, an immutable file) leaves
    nothing behind in the user's folder: the hidden file is removed."""
    tmp = _hidden(name)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp, dir_fd=folder)  # left by a process killed mid-write: ours, by its name
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o666, dir_fd=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                os.fchmod(f.fileno(), stat.S_IMODE(mode))
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, name, src_dir_fd=folder, dst_dir_fd=folder)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=folder)
        raise
    os.fsync(folder)


def _hidden(name: str) -> str:
    """The temporary name a write of ``name`` uses beside it (hidden: a scan passes over it)."""
    return f".{name}.geoloc-write"


def unlink_at(folder: int, name: str) -> None:
    os.unlink(name, dir_fd=folder)
    os.fsync(folder)


def _run_exiftool(tool: str, staged: Path, p: PlannedWrite) -> None:
    """Write ``p``'s position into ``staged`` (a copy in the data dir, or a new sidecar), and check it."""
    before = pixel_hash(staged) if p.mode == IN_FILE else None
    ns, ew = ("N" if p.lat >= 0 else "S"), ("E" if p.lon >= 0 else "W")
    if p.mode == IN_FILE:
        tags = [
            f"-EXIF:GPSLatitude={abs(p.lat)}",
            f"-EXIF:GPSLatitudeRef={ns}",
            f"-EXIF:GPSLongitude={abs(p.lon)}",
            f"-EXIF:GPSLongitudeRef={ew}",
            "-EXIF:GPSMapDatum=WGS-84",
            f"-EXIF:GPSProcessingMethod={ESTIMATE_MARK}",
        ]
    else:
        tags = [
            f"-XMP-exif:GPSLatitude={p.lat}",
            f"-XMP-exif:GPSLongitude={p.lon}",
            "-XMP-exif:GPSMapDatum=WGS-84",
            f"-XMP-exif:GPSProcessingMethod={ESTIMATE_MARK}",
        ]
    # "--" ends the options: a file named "-something" is a file, never an option.
    cmd = [tool, "-q", "-q", "-m", "-overwrite_original", *tags, "--", str(staged)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=EXIFTOOL_TIMEOUT_S)
    name = Path(p.target).name
    if done.returncode != 0 or not staged.exists():
        raise WriteBackError(f"exiftool refused {name}: {(done.stderr or done.stdout).strip()[:300]}")
    # -m lets exiftool pass over a photo's minor metadata faults, and then it may leave a damaged EXIF block
    # unchanged and still exit 0: what was written is read back before it counts.
    got = read_gps(tool, staged)
    if got is None or abs(got[0] - p.lat) > 1e-6 or abs(got[1] - p.lon) > 1e-6:
        raise WriteBackError(f"exiftool could not write GPS into {name} (its metadata may be damaged)")
    if before is not None and pixel_hash(staged) != before:
        raise WriteBackError(f"{name}: the pixel data would change in the write; nothing was written")


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


def undo(journal: LibraryJournal, sid: str, root: Path | None = None, photo_id: int | None = None) -> dict:
    """Undo every write of this library (or of one photo) not yet undone, newest first; the decisions stay
    (write again to redo). Each target is compared with the hashes its write recorded before it replaced
    the file: as written, it is restored; as before (the process stopped before the rename), there is
    nothing to undo; anything else was changed since (by the user, another tool) and is skipped and
    reported, never overwritten, and so are its older writes (they no longer describe the file). One that
    cannot be restored (an OSError, a link, outside ``root``) is reported and the others go on. Returns
    ``{"restored": [target], "skipped": [{"target", "reason"}], "failed": [{"target", "reason"}]}``."""
    data_dir = journal.path.parent
    restored, skipped, failed = [], [], []
    for w in journal.live_writes(sid, photo_id):
        target = Path(w["target"])
        try:
            changed = _undo_one(w, target, root, data_dir)
        except (WriteBackError, OSError) as e:
            failed.append({"target": str(target), "reason": str(e)})
            continue
        if changed is None:
            restored.append(str(target))
        else:
            skipped.append({"target": str(target), "reason": changed})
        journal.mark_undone(w["id"])
        journal.set_written(w["photo"], None)
        if w["mode"] == IN_FILE:
            with contextlib.suppress(OSError):
                st = target.stat(follow_symlinks=False)
                journal.restat(w["photo"], st.st_size, st.st_mtime_ns)
    return {"restored": restored, "skipped": skipped, "failed": failed}


def _undo_one(w: dict, target: Path, root: Path | None, data_dir: Path) -> str | None:
    """Put one write's target back as it was; None when done (or nothing was left to undo), else why it
    was left as it is."""
    backup = Path(w["backup"]) if w["backup"] else None
    folder = open_folder(target.parent, root, data_dir)
    try:
        with contextlib.suppress(FileNotFoundError):  # a process killed between its write and rename
            os.unlink(_hidden(target.name), dir_fd=folder)
        current, st = read_at(folder, target.name)
        now = None if current is None else _sha(current)
        if w["after_sha"] is None:  # a journal of the earlier layout: a write that never finished
            original = None if backup is None else _sha(backup.read_bytes())
            if now == original:
                return None
            return f"its write did not finish and the file differs from its original (kept at {backup}): left as it is"
        if now == w["after_sha"]:
            if backup is None:
                unlink_at(folder, target.name)
            else:
                replace_at(folder, target.name, backup.read_bytes(), st.st_mode)
            return None
        if current is None:
            return "gone since it was written: nothing to restore"
        if now == w["before_sha"]:
            return None  # the process stopped before the rename: the file is as it was
        return "changed since it was written (by hand or another tool): left as it is"
    finally:
        os.close(folder)
