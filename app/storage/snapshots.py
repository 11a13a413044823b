"""Snapshots of a collection's index: files named by the index version, a manifest with checksums.

Each part of the index (float, binary) is one file its kind writes (``VectorIndex.dump``), the ids it
removed but still stores beside it in the manifest. Format 2 is the one the service wrote before the index
seam (the same FAISS files and manifest), so a data dir written by an older version loads unchanged.

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
from dataclasses import asdict, dataclass
from pathlib import Path

from app.engine.artifacts import atomic_write_bytes, atomic_write_file
from app.engine.index.base import UnknownIndexKind
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline
from app.storage.identity import Binding, Identity

MANIFEST = "index.json"
FORMAT = 2


@dataclass(frozen=True)
class SnapshotFile:
    """One index file of a snapshot: its name in the data dir, size, checksum, deleted ids, and the kind that
    wrote it (None in a snapshot written before the kind could switch by size: the configuration's kind)."""

    file: str
    bytes: int
    sha256: str
    tombstones: list[int]
    kind: str | None = None


@dataclass(frozen=True)
class SnapshotManifest:
    """``index.json``: what a snapshot holds and what it was made from (its keys, in this order, on disk)."""

    format: int
    version: int  # the change-log version the snapshot holds
    generation: int
    size: int
    config: str | None
    fingerprint: str | None  # the fitted pipeline's
    float_dim: int | None
    bits: int | None
    files: dict[str, SnapshotFile]  # by kind: float, binary
    written_at: float | None
    # The binding (``Identity.binding``); None in a snapshot written by an older version.
    database_id: str | None = None
    ref_high_water: int | None = None
    last_change: list | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_dict(cls, m: dict) -> SnapshotManifest:
        """Raises ``SnapshotInvalid`` for a manifest whose fields are missing or of the wrong type."""
        try:
            return cls(
                format=m["format"],
                version=int(m["version"]),
                generation=int(m.get("generation", -1)),
                size=int(m.get("size") or 0),
                config=m.get("config"),
                fingerprint=m.get("fingerprint"),
                float_dim=m.get("float_dim"),
                bits=m.get("bits"),
                files={kind: SnapshotFile(**entry) for kind, entry in m["files"].items()},
                written_at=m.get("written_at"),
                database_id=m.get("database_id"),
                ref_high_water=m.get("ref_high_water"),
                last_change=m.get("last_change"),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise SnapshotInvalid(f"the snapshot cannot be loaded ({type(e).__name__}: {e})") from None


class SnapshotInvalid(Exception):
    """No usable snapshot: the caller rebuilds the index from the codes in SQLite."""


class SnapshotUnverifiable(SnapshotInvalid):
    """A snapshot written by an older version, which named no database: rebuilt once, then replaced."""


class SnapshotMismatch(SnapshotInvalid):
    """A snapshot of another database, or of this one at a state it no longer has."""

    def __init__(self, message: str, manifest: SnapshotManifest):
        super().__init__(message)
        self.manifest = manifest


def _same_change(ours: list | None, theirs: list | None) -> bool:
    """Same reference id and operation, and the same image where both still know it (a reference deleted
    since has no sha256 left: that is no divergence)."""
    if ours is None or theirs is None or len(theirs) < 2:
        return False
    same_sha = ours[2] is None or len(theirs) < 3 or theirs[2] is None or ours[2] == theirs[2]
    return ours[:2] == theirs[:2] and same_sha


def check_binding(manifest: SnapshotManifest, store: Identity) -> None:
    """Raise unless the snapshot was made from this database at a version it still holds. The manifest is
    read before the database: a snapshot another process writes meanwhile is never ahead of what we read."""
    if not manifest.database_id:
        raise SnapshotUnverifiable("the snapshot names no database (written by an older version): rebuilding it")
    version = manifest.version
    database_id, head, change = store.binding_state(version)
    why = None
    if manifest.database_id != database_id:
        why = f"it was made from database {manifest.database_id}, this one is {database_id}"
    elif version > head:
        why = (
            f"its change-log version {version} is ahead of the database's {head}: the database lost rows it "
            "indexes (a copy without its -wal file?)"
        )
    elif version and not _same_change(change, manifest.last_change):
        why = f"the change log at version {version} is not the one it was made from (the database diverged)"
    if why:
        raise SnapshotMismatch(f"the snapshot does not belong to this database: {why}", manifest)


def write_snapshot(
    data_dir: Path,
    index: ReferenceIndex,
    pipeline: Pipeline,
    version: int,
    generation: int,
    binding: Binding,
) -> SnapshotManifest:
    """Files named by generation and version (two generations at one version never share a file name); the
    manifest carries the pipeline's fingerprint, so one generation's snapshot is never loaded for another,
    and ``binding`` (``ReferenceStore.binding``), so it is never loaded for another database."""
    files: dict[str, SnapshotFile] = {}
    for part, idx in index.parts().items():
        name = f"{part}-g{generation}-v{version}.faiss"
        path = data_dir / name
        atomic_write_file(path, idx.dump)
        size, sha256 = _file_digest(path)
        files[part] = SnapshotFile(name, size, sha256, idx.removed_ids().tolist(), idx.kind)
    manifest = SnapshotManifest(
        format=FORMAT,
        version=version,
        generation=generation,
        size=index.size,
        config=pipeline.config.name,
        fingerprint=pipeline.fingerprint,
        float_dim=pipeline.float_dim,
        bits=pipeline.bits,
        files=files,
        written_at=time.time(),
        database_id=binding.database_id,
        ref_high_water=binding.ref_high_water,
        last_change=binding.last_change,
    )
    atomic_write_bytes(data_dir / MANIFEST, manifest.to_json().encode())
    keep = {f.file for f in files.values()}
    for old in data_dir.glob("*-v*.faiss"):
        if old.name not in keep:
            old.unlink(missing_ok=True)
    return manifest


def _file_digest(path: Path) -> tuple[int, str]:
    """Size and sha256 of a file, read in chunks (an index of 10^7 references is never a second time in RAM)."""
    with open(path, "rb") as f:
        digest = hashlib.file_digest(f, "sha256")
        return f.tell(), digest.hexdigest()


def read_manifest(data_dir: Path) -> SnapshotManifest:
    path = data_dir / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise SnapshotInvalid("no snapshot yet") from None
    except (OSError, ValueError) as e:
        raise SnapshotInvalid(f"{path} is unreadable or not JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise SnapshotInvalid(f"{path} is not a snapshot manifest of format {FORMAT}")
    return SnapshotManifest.from_dict(manifest)


def load_snapshot(
    data_dir: Path, pipeline: Pipeline, store: Identity | None = None
) -> tuple[ReferenceIndex, SnapshotManifest]:
    """The snapshot's index and its manifest, every file verified against its checksum and, with ``store``,
    the snapshot checked to be of that database (every caller that serves or checks it passes one)."""
    m = read_manifest(data_dir)
    if m.fingerprint != pipeline.fingerprint:
        raise SnapshotInvalid("the snapshot was made with another fitted pipeline")
    if store is not None:
        check_binding(m, store)
    index = pipeline.new_index()
    recorded = {part: f.kind for part, f in m.files.items() if f.kind}
    try:
        if any(index.kinds().get(part, kind) != kind for part, kind in recorded.items()):
            # the collection switched kind by size (``Collection``): each file holds its trained state
            index = ReferenceIndex(pipeline.config, pipeline.float_dim, pipeline.bits, kinds=recorded)
        for part, idx in index.parts().items():
            entry = m.files[part]
            path = data_dir / entry.file
            if _file_digest(path) != (entry.bytes, entry.sha256):
                raise SnapshotInvalid(f"{entry.file} does not match its checksum (corrupt or truncated)")
            idx.load(path)
            idx.remove(entry.tombstones)
    except SnapshotInvalid:
        raise
    except (OSError, KeyError, TypeError, ValueError, RuntimeError, UnknownIndexKind) as e:
        raise SnapshotInvalid(f"the snapshot cannot be loaded ({type(e).__name__}: {e})") from None
    return index, m


def snapshot_files(data_dir: Path) -> list[Path]:
    """The manifest and the files it names (what a backup copies)."""
    m = read_manifest(data_dir)
    return [data_dir / MANIFEST] + [data_dir / f.file for f in m.files.values()]
