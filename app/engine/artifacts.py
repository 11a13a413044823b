"""Save and load fitted things (codebooks, PCA, binarisers) with a manifest, atomically.

Why: a service restart must reload exactly what was fitted, and a file from another version or another
kind must be refused rather than silently misused. Every artifact is an ``.npz`` of arrays plus a JSON
manifest (kind, format version, parameters, library versions, a hash of the training data).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.errors import IncompatibleArtifact, ModelNotReady


def atomic_write_file(path: Path, write: Callable[[Path], None]) -> None:
    """``write`` a temporary file in the same folder (by path: a FAISS index streams itself to disk), fsync,
    then rename over ``path``, as ``atomic_write_bytes`` does."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(Path(tmp))
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a temporary file in the same folder, fsync, then rename over ``path``: readers see the
    old file or the new one, never half of one, even if the process dies mid-write."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def library_versions() -> dict[str, str]:
    import cv2
    import faiss
    import sklearn

    return {
        "numpy": np.__version__,
        "scikit-learn": sklearn.__version__,
        "faiss": faiss.__version__,
        "opencv": cv2.__version__,
    }


def data_hash(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def save_artifact(
    directory: Path,
    name: str,
    kind: str,
    version: int,
    params: dict[str, Any],
    arrays: dict[str, np.ndarray],
    extra: dict[str, Any] | None = None,
) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(directory / f"{name}.npz", buf.getvalue())
    manifest = {
        "kind": kind,
        "format_version": version,
        "params": params,
        "libraries": library_versions(),
        **(extra or {}),
    }
    atomic_write_bytes(directory / f"{name}.json", json.dumps(manifest, indent=1).encode())


def load_artifact(directory: Path, name: str, kind: str, version: int) -> tuple[dict, dict[str, np.ndarray]]:
    mpath = directory / f"{name}.json"
    if not mpath.exists():
        raise ModelNotReady(f"{mpath} is missing: fit the pipeline first (`geoloc fit`)")
    manifest = json.loads(mpath.read_text())
    if manifest.get("kind") != kind or manifest.get("format_version") != version:
        raise IncompatibleArtifact(
            f"{mpath} is a {manifest.get('kind')} v{manifest.get('format_version')}, expected {kind} v{version}"
        )
    with np.load(directory / f"{name}.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return manifest, arrays
