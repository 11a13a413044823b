"""FAISS snapshots of a collection's index: files named by the index version, a manifest with checksums.

Why checksums: a snapshot is a cache of what SQLite holds, and a cache that is silently wrong is worse than
none (a flipped byte in the middle of a float index still loads, and ranks garbage). So every file's
sha256 is in the manifest and is verified on load; anything that does not verify (a missing, truncated,
corrupt or foreign file, a manifest that is not JSON) raises ``SnapshotInvalid`` and the caller rebuilds
from SQLite. Files are written first and the manifest last, each atomically: a crash in between leaves the
previous manifest naming the previous, intact files.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from app.engine.artifacts import atomic_write_bytes
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline

MANIFEST = "index.json"
FORMAT = 2


class SnapshotInvalid(Exception):
    """No usable snapshot: the caller rebuilds the index from the codes in SQLite."""


def write_snapshot(
    data_dir: Path, index: ReferenceIndex, pipeline: Pipeline, version: int, generation: int = 0
) -> dict:
    """Files named by generation and version (two generations at one version never share a file name); the
    manifest carries the pipeline's fingerprint, so one generation's snapshot is never loaded for another."""
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


def load_snapshot(data_dir: Path, pipeline: Pipeline) -> tuple[ReferenceIndex, dict]:
    """The snapshot's index and its manifest, every file verified against its checksum."""
    m = read_manifest(data_dir)
    if m.get("fingerprint") != pipeline.fingerprint:
        raise SnapshotInvalid("the snapshot was made with another fitted pipeline")
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
