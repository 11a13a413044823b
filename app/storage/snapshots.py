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
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from app.engine.artifacts import atomic_write_bytes
from app.engine.index.base import StagedDump, UnknownIndexKind
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


@dataclass
class _StagedFile:
    name: str
    tmp: Path
    dump: StagedDump | None
    tombstones: list[int]
    kind: str


class StagedSnapshot:
    """A snapshot begun from the served index itself, without a copy of it (``VectorIndex.stage_dump``):
    made under the collection's lock, then ``finish`` (without the lock: the rest of each file, fsync,
    rename, the manifest) and ``adopt`` (under the lock again, if the index is still the one served)."""

    def __init__(self, data_dir: Path, index: ReferenceIndex, version: int, generation: int):
        """Files named by generation and version (two generations at one version never share a file name)."""
        self.data_dir, self.version, self.generation, self.size = data_dir, version, generation, index.size
        self.files: dict[str, _StagedFile] = {}
        data_dir.mkdir(parents=True, exist_ok=True)
        try:
            for part, idx in index.parts().items():
                name = f"{part}-g{generation}-v{version}.faiss"
                fd, tmp = tempfile.mkstemp(dir=data_dir, prefix=f".{name}.", suffix=".tmp")
                os.close(fd)
                self.files[part] = _StagedFile(name, Path(tmp), None, idx.removed_ids().tolist(), idx.kind)
                self.files[part].dump = idx.stage_dump(Path(tmp))
        except BaseException:
            self.discard()
            raise

    def discard(self) -> None:
        for f in self.files.values():
            f.tmp.unlink(missing_ok=True)

    def finish(self, pipeline: Pipeline, binding: Binding) -> SnapshotManifest:
        """The manifest carries the pipeline's fingerprint, so one generation's snapshot is never loaded for
        another, and ``binding`` (``ReferenceStore.binding``), so it is never loaded for another database.
        Files first, each fsynced and renamed into place, the manifest last (atomically)."""
        files: dict[str, SnapshotFile] = {}
        try:
            for part, f in self.files.items():
                f.dump.finish()
                with open(f.tmp, "rb+") as fh:
                    os.fsync(fh.fileno())
                os.replace(f.tmp, self.data_dir / f.name)
                size, sha256 = _file_digest(self.data_dir / f.name)
                files[part] = SnapshotFile(f.name, size, sha256, f.tombstones, f.kind)
        except BaseException:
            self.discard()
            raise
        manifest = SnapshotManifest(
            format=FORMAT,
            version=self.version,
            generation=self.generation,
            size=self.size,
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
        atomic_write_bytes(self.data_dir / MANIFEST, manifest.to_json().encode())
        keep = {f.file for f in files.values()}
        for old in self.data_dir.glob("*-v*.faiss"):
            if old.name not in keep:
                old.unlink(missing_ok=True)
        return manifest

    def adopt(self) -> None:
        """Under the lock, with the index still served: each part reads from its new file where it reads
        from one (``StagedDump.adopt``)."""
        for f in self.files.values():
            f.dump.adopt(self.data_dir / f.name)


def write_snapshot(
    data_dir: Path,
    index: ReferenceIndex,
    pipeline: Pipeline,
    version: int,
    generation: int,
    binding: Binding,
) -> SnapshotManifest:
    """One snapshot of ``index`` in one go (nothing else changes it meanwhile: a copy, or a lone process)."""
    staged = StagedSnapshot(data_dir, index, version, generation)
    manifest = staged.finish(pipeline, binding)
    staged.adopt()
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


#: What makes the index a snapshot's files load into (``Pipeline.new_index``): with no kinds, an empty index
#: of the configuration's kinds; with each part's recorded kind, an empty one of those. Given by the caller:
#: which kinds an index is built of is the engine's to say, the snapshot only records them.
IndexFactory = Callable[..., ReferenceIndex]


def load_snapshot(
    data_dir: Path, pipeline: Pipeline, store: Identity | None = None, *, new_index: IndexFactory
) -> tuple[ReferenceIndex, SnapshotManifest]:
    """The snapshot's index and its manifest, every file verified against its checksum and, with ``store``,
    the snapshot checked to be of that database (every caller that serves or checks it passes one).
    ``new_index``: see ``IndexFactory``."""
    m = read_manifest(data_dir)
    if m.fingerprint != pipeline.fingerprint:
        raise SnapshotInvalid("the snapshot was made with another fitted pipeline")
    if store is not None:
        check_binding(m, store)
    index = new_index()
    recorded = {part: f.kind for part, f in m.files.items() if f.kind}
    try:
        if any(index.kinds().get(part, kind) != kind for part, kind in recorded.items()):
            # the collection switched kind by size (``Collection``): each file holds its trained state
            index = new_index(kinds=recorded)
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
