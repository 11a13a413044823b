"""Operations on a data dir: check that its parts agree, back it up while it is in use, restore it.

Why a check: the FAISS snapshot is a cache of SQLite and the images live beside it; after a disk incident
or a hand edit an operator needs one command that says which part disagrees with which, rather than
rankings that are quietly wrong. Why SQLite's backup API: it copies a consistent state of a database
that other processes keep writing, which a plain file copy of a WAL database does not.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.apikey import KEY_FILE, key_path
from app.engine.configs import DEFAULT_CONFIG
from app.errors import OperationRefused
from app.permissions import private_dir, private_tree
from app.storage.backend import StorageBackend
from app.storage.feature_files import FEATURES, FeatureFiles, damage, profile_root
from app.storage.files import IMAGES
from app.storage.library import BACKUPS_DIR, JOURNAL_FILE, copy_journal, rebase_backups
from app.storage.migrations import SchemaTooNew, refuse_too_new, schema_version
from app.storage.orphans import MIN_AGE_S, retry_removals, sweep
from app.storage.snapshots import (
    MANIFEST,
    SnapshotInvalid,
    SnapshotUnverifiable,
    load_snapshot,
    read_manifest,
    snapshot_files,
)
from app.storage.store import ReferenceStore
from app.usecases.collection import pipeline_source
from app.usecases.models import check_models, named_config

BACKUP_MANIFEST = "backup.json"
KEY_NOTE = f"this backup holds the API key ({KEY_FILE}, mode 0600): keep it as private as the key itself"
PIPELINES = "pipelines"  # the data dir's re-fitted pipelines, one folder per generation
#: The photo library's journal (``app.storage.library``) and the copies its write-back keeps of what it
#: overwrote (``app.library.writeback``): without them a restored data dir cannot undo a write.


@dataclass
class CheckReport:
    lines: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def _sample(ids, n: int = 10) -> str:
    ids = list(ids)
    return ", ".join(str(i) for i in ids[:n]) + (f" (and {len(ids) - n} more)" if len(ids) > n else "")


def check_data_dir(data_dir: Path, models_dir: Path, config: str | None, backend: StorageBackend) -> CheckReport:
    """Whether the rows, image files, codes, index snapshot and stored features of ``backend`` (the process's,
    from its Settings) agree; each disagreement is a line of ``problems``."""
    r = CheckReport()
    if not backend.exists():
        r.problems.append(f"{backend.describe()} does not exist")
        return r
    store = ReferenceStore(data_dir, read_only=True, backend=backend)
    if not store.holds_tables():
        r.problems.append(
            f"{backend.describe()} holds no tables: its content is still in a -wal file that is not here "
            "(a copy without it?); copy the data dir with `geoloc backup`"
        )
        return r
    try:  # a read-only open runs no upgrade, so it never meets the refusal a writable open (the server) does
        refuse_too_new(store.database, schema_version(store.database))
    except SchemaTooNew as e:
        r.problems.append(f"{e} (the server refuses to open it; the rest is not checked)")
        store.close()
        return r
    counts = {s: store.count(s) for s in ("indexed", "pending", "failed")}
    r.lines.append(f"rows: {counts['indexed']} indexed, {counts['pending']} pending, {counts['failed']} failed")
    quarantined = store.quarantined()
    if quarantined:
        r.problems.append(
            f"quarantined references (their encoding never finished, the process stopped each time): "
            f"{_sample([i for i, _ in quarantined])}; delete them (DELETE /references/ID) or upload a fixed image"
        )
    rows = store.stored_rows()
    named = {row.image for row in rows}
    on_disk, foreign = _listing(store.images_dir)
    missing = [row.id for row in rows if row.image not in on_disk]
    orphans = sorted(on_disk - named)
    r.lines.append(f"images: {len(on_disk)} files, {len(missing)} missing, {len(orphans)} not named by any row")
    if missing:
        r.problems.append(f"references whose image file is missing: {_sample(missing)}")
    if orphans:
        r.problems.append(f"image files no row names: {_sample(orphans)} (`geoloc check --repair` removes them)")
    if foreign:
        r.problems.append(
            f"entries of {store.images_dir} that are not image files (folders, links): {_sample(foreign)}; "
            "`geoloc check --repair` leaves them: move them out by hand"
        )
    _check_leftovers(store, data_dir, r)
    name = store.get_meta("config") or config or DEFAULT_CONFIG
    damaged = check_models(models_dir, named_config(name, models_dir))  # an added model's files, by sha256
    if damaged:
        r.problems += [f"{p}: add the model again (`geoloc models add`); the rest is not checked" for p in damaged]
        store.close()
        return r
    pipeline = pipeline_source(data_dir, models_dir, store.get_meta("pipeline"), name).load()
    r.lines.append(f"pipeline: {store.get_meta('pipeline') or 'models:' + name}, generation {store.head()[1]}")
    fsize = 4 * (pipeline.float_dim or 0)
    bsize = (pipeline.bits or 0) // 8
    bad_codes = [
        row.id
        for row in rows
        if row.status == "indexed"
        and (
            (fsize and (row.float_code is None or len(row.float_code) != fsize))
            or (bsize and (row.binary_code is None or len(row.binary_code) != bsize))
        )
    ]
    if bad_codes:
        r.problems.append(f"indexed references without codes of the pipeline's size: {_sample(bad_codes)}")
    _check_stored_features(store, pipeline.config.stored_features, rows, r)
    indexed = np.array(sorted(row.id for row in rows if row.status == "indexed"), np.int64)
    try:
        index, manifest = load_snapshot(store.snapshots_dir, pipeline, store, new_index=pipeline.new_index)
    except SnapshotInvalid as e:
        r.lines.append(f"index: no usable snapshot ({e}); the service rebuilds it from the database")
        if (store.snapshots_dir / MANIFEST).exists() and not isinstance(e, SnapshotUnverifiable):
            r.problems.append(f"the snapshot is not usable: {e}")
        return r
    from app.usecases.collection import apply_changes

    changes = store.changes_since(manifest.version)
    apply_changes(index, changes)
    in_index = np.sort(index.ids())
    r.lines.append(
        f"index: snapshot of version {manifest.version} verified, {len(changes)} later changes in the log, "
        f"{len(in_index)} references after replay"
    )
    not_indexed = np.setdiff1d(indexed, in_index)
    extra = np.setdiff1d(in_index, indexed)
    if len(not_indexed):
        r.problems.append(f"indexed rows missing from the index: {_sample(not_indexed.tolist())}")
    if len(extra):
        r.problems.append(f"index entries without an indexed row: {_sample(extra.tolist())}")
    store.close()
    return r


def _check_stored_features(store: ReferenceStore, profile: str | None, rows, r: CheckReport) -> None:
    """With a configuration that stores local features: the indexed references whose file is missing (they
    are found, but never verified: a data dir ingested before the configuration stored them, or a crash
    between the file and its row) and those whose file is damaged (emptied, truncated, bit-flipped: every
    request that meets one logs a warning and goes unverified). Each indexed reference's file is read and
    its CRC checked, one file at a time, folder by folder (nothing kept but the names): at 10^6 references
    that reads the whole profile's folder, which is this offline command's job, never a request's."""
    if profile is None:
        return
    files = FeatureFiles(profile_root(store.data_dir, profile))
    indexed = {row.image.split(".", 1)[0]: row.id for row in rows if row.status == "indexed"}
    stored: set[str] = set()
    damaged: list[str] = []
    for sha in files.names():
        stored.add(sha)
        if sha not in indexed:
            continue  # no request reads it (a pending row's file is written again when it is encoded)
        data = files.read(sha)
        why = None if data is None else damage(data)  # None: removed meanwhile, with its row
        if why is not None:
            damaged.append(f"{indexed[sha]} ({files.path(sha).relative_to(store.data_dir)}: {why})")
    missing = [ref_id for sha, ref_id in indexed.items() if sha not in stored]
    r.lines.append(
        f"stored features ({profile}): {len(stored)} files, {len(missing)} indexed references without one, "
        f"{len(damaged)} damaged"
    )
    if missing:
        r.problems.append(
            f"references whose stored features file is missing (found, never verified): {_sample(missing)}"
        )
    if damaged:
        r.problems.append(
            f"references whose stored features file is damaged (never verified; `geoloc features backfill` "
            f"remakes them): {_sample(damaged)}"
        )


def _listing(images_dir: Path) -> tuple[set[str], list[str]]:
    """The images folder's regular files (what rows name and what ``--repair`` may remove: the sweep
    unlinks regular files only) and, apart, its other entries (folders, links, ...), which no row names and
    the sweep never touches. Names starting with a dot (thumbnails, temporary files) are neither."""
    files: set[str] = set()
    foreign: list[str] = []
    with os.scandir(images_dir) as it:
        for e in it:
            if e.name.startswith("."):
                continue
            if e.is_file(follow_symlinks=False):
                files.add(e.name)
            else:
                foreign.append(e.name)
    return files, sorted(foreign)


def _check_leftovers(store: ReferenceStore, data_dir: Path, r: CheckReport) -> None:
    """Files that no longer belong to anything: removals queued by deletes, temporary files of killed
    writers older than ``MIN_AGE_S`` (younger ones may be uploads being written)."""
    queued = store.queued_removals()
    if queued:
        r.problems.append(
            f"{len(queued)} image files of deleted references still to remove: {_sample(queued)} "
            "(the worker retries; `geoloc check --repair` too)"
        )
    now = time.time()
    stale = [p.name for p in store.images_dir.glob(".*.tmp") if p.is_file() and now - p.stat().st_mtime > MIN_AGE_S]
    if stale:
        r.problems.append(f"stale temporary files: {_sample(stale)} (`geoloc check --repair` removes them)")


def repair_data_dir(data_dir: Path, backend: StorageBackend, min_age_s: float = MIN_AGE_S) -> list[str]:
    """Remove what no longer belongs to anything: queued removals retried, image files no row names and
    temporary files, both older than ``min_age_s`` (younger ones may be uploads in flight). Safe while the
    services run: every unlink is re-checked under the database's write lock. Returns what it did."""
    if not backend.exists():
        raise OperationRefused(f"{backend.describe()} does not exist: nothing to repair")
    store = ReferenceStore(data_dir, backend=backend)
    try:
        removed, failed = retry_removals(store)
        lines = [f"removed {len(removed)} queued image files of deleted references"]
        if failed:
            lines.append(f"could not remove {len(failed)} queued files yet: {_sample(failed)}")
        return lines + sweep(store, min_age_s).lines(min_age_s)
    finally:
        store.close()


def backup_data_dir(data_dir: Path, dest: Path, backend: StorageBackend) -> dict:
    """The storage backend's dump (SQLite's backup API, PostgreSQL's ``pg_dump``: one state while others
    keep writing). Then the images the copied rows name (from the shared images folder on PostgreSQL), their
    stored local features, the data dir's re-fitted pipelines, the photo library's journal and write-back
    copies, its newest snapshot and its API key file."""
    if dest.exists() and any(dest.iterdir()):
        raise OperationRefused(f"{dest} is not empty: back up into a new or empty folder")
    private_dir(dest, parents=True)
    os.chmod(dest, 0o700)  # from the start (an existing empty folder too): nothing under it is reachable meanwhile
    (dest / IMAGES).mkdir(parents=True, exist_ok=True)
    names = backend.dump(dest)  # one state, while others keep writing
    images, snapshots = backend.images_dir, backend.snapshots_dir
    copied = missing = 0
    for name in names:
        try:
            shutil.copy2(images / name, dest / IMAGES / name)
            copied += 1
        except FileNotFoundError:  # deleted since the database copy was taken
            missing += 1
    stored_features = _copy_stored_features(data_dir, dest, names)
    if (data_dir / PIPELINES).is_dir():  # re-fitted pipelines (`geoloc refit`): the codes need theirs
        shutil.copytree(data_dir / PIPELINES, dest / PIPELINES, ignore=shutil.ignore_patterns(".*"))
    library = _copy_library(data_dir, dest)
    version = None
    try:
        for path in snapshot_files(snapshots):
            shutil.copy2(path, dest / path.name)
        version = read_manifest(dest).version
    except (SnapshotInvalid, FileNotFoundError):
        pass  # no snapshot (or replaced meanwhile): a restore rebuilds the index from SQLite
    holds_key = _copy_key(data_dir, dest)
    summary = {
        "references": len(names),
        "images": copied,
        "missing_images": missing,
        "stored_features": stored_features,
        "library": library,
        "snapshot_version": version,
        "api_key": holds_key,
        **({"note": KEY_NOTE} if holds_key else {}),
        "source": str(data_dir.resolve()),
        "database": backend.name,
        "written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    (dest / BACKUP_MANIFEST).write_text(json.dumps(summary, indent=1))
    private_tree(dest)
    return summary


def restore_data_dir(source: Path, data_dir: Path, backend: StorageBackend) -> dict:
    """Into an empty data dir (and, on PostgreSQL, an empty database: ``pg_restore``, the images into the
    shared images folder). A backup restores on the engine it was made on."""
    if not (source / BACKUP_MANIFEST).exists() or not (source / backend.backup_name).exists():
        raise OperationRefused(
            f"{source} is not a backup written by `geoloc backup` on this storage backend ({backend.name}: "
            "GEOLOC_DATABASE_URL set for PostgreSQL, unset for SQLite)"
            if (source / BACKUP_MANIFEST).exists()
            else f"{source} is not a backup written by `geoloc backup`"
        )
    if data_dir.exists() and any(p for p in data_dir.iterdir() if p.name != "README.md"):
        raise OperationRefused(f"{data_dir} is not empty: restore into a new or empty data dir")
    private_dir(data_dir, parents=True)
    backend.restore(source)
    images, snapshots = _store_dirs(data_dir, backend)  # makes the folders; the restored tables open
    shutil.copytree(source / IMAGES, images, dirs_exist_ok=True)
    if (source / FEATURES).is_dir():  # the stored local features: verified at once, no back-fill
        shutil.copytree(source / FEATURES, data_dir / FEATURES, dirs_exist_ok=True)
    if (source / PIPELINES).is_dir():
        shutil.copytree(source / PIPELINES, data_dir / PIPELINES, dirs_exist_ok=True)
    for path in source.glob("*-v*.faiss"):
        shutil.copy2(path, snapshots / path.name)
    if (source / MANIFEST).exists():
        shutil.copy2(source / MANIFEST, snapshots / MANIFEST)
    library = _restore_library(source, data_dir)
    _copy_key(source, data_dir)
    private_tree(data_dir)  # PostgreSQL's shared images folder keeps the mode its operator gave it
    return {**json.loads((source / BACKUP_MANIFEST).read_text()), "restored_library": library}


def _copy_stored_features(data_dir: Path, dest: Path, names: list[str]) -> dict[str, int]:
    """The stored local features of the images the copied rows name, under each profile the data dir holds
    (``features/<profile>/<sha[:3]>/<sha>.lf``, the same layout): a restored data dir verifies its answers at
    once rather than back-filling every reference from its image. Files of rows deleted since the database
    copy are left out, as their images are; one whose reference is older than the stored features has none
    (the restored server back-fills it). Returns the files copied per profile."""
    copied: dict[str, int] = {}
    folder = data_dir / FEATURES
    if not folder.is_dir():
        return copied
    for root in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        files, into = FeatureFiles(root), FeatureFiles(dest / FEATURES / root.name)
        copied[root.name] = 0
        for sha in {name.split(".", 1)[0] for name in names}:
            try:
                data = files.path(sha).read_bytes()
            except (FileNotFoundError, ValueError):  # none stored yet, or a name that is no sha256
                continue
            into.write(sha, data)
            copied[root.name] += 1
    return copied


def _copy_library(data_dir: Path, dest: Path) -> dict[str, int]:
    """The photo library's journal, through SQLite's backup API (it is in WAL mode and a scan or a review
    may be writing it: a file copy could miss the -wal's pages or tear), then every write-back copy.
    In that order: a write copies its backup before it records the row naming it, so every backup a
    copied row names is copied too. Returns the files copied (``journal``: 0 or 1, ``backups``)."""
    copied = {"journal": 0, "backups": 0}
    journal = data_dir / JOURNAL_FILE
    if journal.is_file():  # connecting to a missing file would create it
        copy_journal(journal, dest / JOURNAL_FILE)
        copied["journal"] = 1
    backups = data_dir / BACKUPS_DIR
    if backups.is_dir():
        private_dir(dest / BACKUPS_DIR)
        for path in sorted(backups.iterdir()):
            if path.is_file() and not path.is_symlink():
                shutil.copy2(path, dest / BACKUPS_DIR / path.name)
                copied["backups"] += 1
    return copied


def _restore_library(source: Path, data_dir: Path) -> dict[str, int]:
    """Put the library's journal and write-back copies back. The journal names each copy by its absolute
    path in the data dir it was made in; restored elsewhere those paths lead to the old data dir (gone, or
    another collection's), so they are rewritten to the same file names in this data dir's copies: undo
    then puts back the photos' original bytes. Returns the files restored and the paths rewritten."""
    done = {"journal": 0, "backups": 0, "paths_rewritten": 0}
    if (source / BACKUPS_DIR).is_dir():
        private_dir(data_dir / BACKUPS_DIR)
        for path in sorted((source / BACKUPS_DIR).iterdir()):
            if path.is_file() and not path.is_symlink():
                shutil.copy2(path, data_dir / BACKUPS_DIR / path.name)
                done["backups"] += 1
    if not (source / JOURNAL_FILE).is_file():
        return done
    shutil.copy2(source / JOURNAL_FILE, data_dir / JOURNAL_FILE)
    done["journal"] = 1
    done["paths_rewritten"] = rebase_backups(data_dir / JOURNAL_FILE, (data_dir / BACKUPS_DIR).resolve())
    return done


def _store_dirs(data_dir: Path, backend: StorageBackend) -> tuple[Path, Path]:
    """Where the store keeps its images and its snapshots (shared folders on PostgreSQL, when set), made by
    a writable open of the restored database (which also migrates it to this version's schema)."""
    store = ReferenceStore(data_dir, backend=backend)
    try:
        return store.images_dir, store.snapshots_dir
    finally:
        store.close()


def _copy_key(src_dir: Path, dest_dir: Path) -> bool:
    """Copy the data dir's API key file (clients hold that key: a restore without it would lock them out),
    created 0600 whatever the source's mode. False when there is none (a key from the environment)."""
    try:
        key = key_path(src_dir).read_bytes()
    except FileNotFoundError:
        return False
    fd = os.open(key_path(dest_dir), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(key)
        f.flush()
        os.fsync(f.fileno())
    return True
