"""FAISS snapshots of a collection's index: files named by the index version, a manifest with checksums.

Why checksums: a snapshot is a cache of what SQLite holds, and a cache that is silently wrong is worse than
none (a flipped byte in the middle of a float index still loads, and ranks garbage). So every file's
sha256 is in the manifest and is verified on load; anything that does not verify (a missing, truncated,
corrupt or foreign file, a manifest that is not JSON) raises ``SnapshotInvalid`` and the caller rebuilds
from SQLite. Files are written first and the manifest last, each atomically: a crash in between leaves the
previous manifest naming the previous, intact files.

Why a binding to the database: a snapshot that verifies is still wrong if it describes another database,
or this one at a state it no longer has (a data dir copied without its ``-wal``: the snapshot indexes rows
the copy lost, and their ids would be handed out again to new uploads, so an old photo would be answered
with a new reference's position). The manifest names the database (its random id), the change-log version
and that version's entry, and the highest reference id handed out; a snapshot that does not match is
refused (``SnapshotMismatch``) and the store raises its id counters past it, so it can never match later.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from app.engine.artifacts import atomic_write_bytes
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline

if TYPE_CHECKING:
    from app.store import ReferenceStore

MANIFEST = "index.json"
FORMAT = 2


class SnapshotInvalid(Exception):
    """No usable snapshot: the caller rebuilds the index from the codes in SQLite."""


class SnapshotUnverifiable(SnapshotInvalid):
    """A snapshot written by an older version, which named no database: rebuilt once, then replaced."""


class SnapshotMismatch(SnapshotInvalid):
    """A snapshot of another database, or of this one at a state it no longer has."""

    def __init__(self, message: str, manifest: dict):
        super().__init__(message)
        self.manifest = manifest


def _same_change(ours: list | None, theirs: list | None) -> bool:
    """Same reference id and operation, and the same image where both still know it (a reference deleted
    since has no sha256 left: that is no divergence)."""
    if ours is None or theirs is None or len(theirs) < 2:
        return False
    same_sha = ours[2] is None or len(theirs) < 3 or theirs[2] is None or ours[2] == theirs[2]
    return ours[:2] == theirs[:2] and same_sha


def check_binding(manifest: dict, store: ReferenceStore) -> None:
    """Raise unless the snapshot was made from this database at a version it still holds. The manifest is
    read before the database: a snapshot another process writes meanwhile is never ahead of what we read."""
    if not manifest.get("database_id"):
        raise SnapshotUnverifiable("the snapshot names no database (written by an older version): rebuilding it")
    version = int(manifest.get("version", 0))
    database_id, head, change = store.binding_state(version)
    why = None
    if manifest["database_id"] != database_id:
        why = f"it was made from database {manifest['database_id']}, this one is {database_id}"
    elif version > head:
        why = (
            f"its change-log version {version} is ahead of the database's {head}: the database lost rows it "
            "indexes (a copy without its -wal file?)"
        )
    elif version and not _same_change(change, manifest.get("last_change")):
        why = f"the change log at version {version} is not the one it was made from (the database diverged)"
    if why:
        raise SnapshotMismatch(f"the snapshot does not belong to this database: {why}", manifest)


def write_snapshot(
    data_dir: Path,
    index: ReferenceIndex,
    pipeline: Pipeline,
    version: int,
    generation: int = 0,
    binding: dict | None = None,
) -> dict:
    """Files named by generation and version (two generations at one version never share a file name); the
    manifest carries the pipeline's fingerprint, so one generation's snapshot is never loaded for another,
    and ``binding`` (``ReferenceStore.binding``), so it is never loaded for another database."""
    files: dict[str, dict] = {}
    for kind, idx in (("float", index.float), ("binary", index.binary)):
        if idx is not None:
            name = f"{kind}-g{generation}-v{version}.faiss"
            data = idx.to_bytes()
            atomic_write_bytes(data_dir / name, data)
            files[kind] = {
                "file": name,
                "bytes": len(data),
                "sha256": hashlib.sha256(data).hexdigest(),
                "tombstones": sorted(idx.tombstones),
            }
    manifest = {
        "format": FORMAT,
        "version": version,
        "generation": generation,
        "size": index.size,
        "config": pipeline.config.name,
        "fingerprint": pipeline.fingerprint,
        "float_dim": pipeline.float_dim,
        "bits": pipeline.bits,
        "files": files,
        "written_at": time.time(),
        **(binding or {}),
    }
    atomic_write_bytes(data_dir / MANIFEST, json.dumps(manifest, indent=1).encode())
    keep = {f["file"] for f in files.values()}
    for old in data_dir.glob("*-v*.faiss"):
        if old.name not in keep:
            old.unlink(missing_ok=True)
    return manifest


def read_manifest(data_dir: Path) -> dict:
    path = data_dir / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise SnapshotInvalid("no snapshot yet") from None
    except (OSError, ValueError) as e:
        raise SnapshotInvalid(f"{path} is unreadable or not JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise SnapshotInvalid(f"{path} is not a snapshot manifest of format {FORMAT}")
    return manifest


def load_snapshot(
    data_dir: Path, pipeline: Pipeline, store: ReferenceStore | None = None
) -> tuple[ReferenceIndex, dict]:
    """The snapshot's index and its manifest, every file verified against its checksum and, with ``store``,
    the snapshot checked to be of that database (every caller that serves or checks it passes one)."""
    m = read_manifest(data_dir)
    if m.get("fingerprint") != pipeline.fingerprint:
        raise SnapshotInvalid("the snapshot was made with another fitted pipeline")
    if store is not None:
        check_binding(m, store)
    index = ReferenceIndex(pipeline.config, pipeline.float_dim, pipeline.bits)
    try:
        for kind, idx in (("float", index.float), ("binary", index.binary)):
            if idx is None:
                continue
            entry = m["files"][kind]
            data = (data_dir / entry["file"]).read_bytes()
            if len(data) != entry["bytes"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
                raise SnapshotInvalid(f"{entry['file']} does not match its checksum (corrupt or truncated)")
            idx.load_bytes(data, entry["tombstones"])
        int(m["version"])
    except SnapshotInvalid:
        raise
    except (OSError, KeyError, TypeError, ValueError, RuntimeError) as e:
        raise SnapshotInvalid(f"the snapshot cannot be loaded ({type(e).__name__}: {e})") from None
    return index, m


def snapshot_files(data_dir: Path) -> list[Path]:
    """The manifest and the files it names (what a backup copies)."""
    m = read_manifest(data_dir)
    return [data_dir / MANIFEST] + [data_dir / f["file"] for f in m["files"].values()]
