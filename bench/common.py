"""What the benchmark scripts share: the penn rows they use, summary statistics, talking to a server.

Benchmarks print medians (and tail percentiles where a distribution matters) and compare against a
baseline measured in the same process, never against a number from another day or machine."""

from __future__ import annotations

import json
import platform
import statistics
from collections.abc import Iterable
from pathlib import Path
from urllib.parse import urlparse

import cv2
import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

from app.manifests import Row, read_manifest
from app.runtime import configure_allocator
from app.settings import Settings
from tools.server_process import wait_job

# The bench process measures the floor: the same allocator settings as `geoloc serve`.
configure_allocator(Settings().malloc_tuning, Settings().malloc_trim)

REPO = Path(__file__).resolve().parents[1]
MANIFEST = REPO / "data" / "manifests" / "penn-campus-gps.csv"
LOOPBACK = {"127.0.0.1", "localhost", "::1"}


def median_ms(values: Iterable[float]) -> float:
    return float(statistics.median(list(values)))


def percentiles(values: Iterable[float], ps=(50, 95, 99)) -> dict[str, float]:
    arr = np.asarray(list(values), float)
    if not len(arr):
        return {f"p{p}": float("nan") for p in ps}
    return {f"p{p}": float(np.percentile(arr, p)) for p in ps}


def machine() -> str:
    import os

    return f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.platform()}"


def penn_rows(manifest: Path = MANIFEST) -> list[Row]:
    if not manifest.exists():
        raise SystemExit(f"{manifest} is missing: run `make manifests` first")
    return read_manifest(manifest)


def is_photo(row: Row) -> bool:
    """1600 px phone photos, as opposed to the 224 px crops of the same captures."""
    return row.image.parent.name == "photos"


def require_loopback(url: str) -> None:
    host = urlparse(url).hostname
    if host not in LOOPBACK:
        raise SystemExit(f"refusing {url}: load and benchmarks run against a loopback server only")


def resident_bytes(client: httpx.Client) -> float | None:
    """The server's resident memory from its own /metrics (prometheus-client's process collector)."""
    r = client.get("/metrics")
    if r.status_code != 200:
        return None
    for family in text_string_to_metric_families(r.text):
        if family.name == "process_resident_memory_bytes":
            return family.samples[0].value
    return None


def post_references(
    client: httpx.Client,
    images: list[tuple[str, bytes, float, float]],
    batch: int = 8,
    api_key: str | None = None,
    timeout: float = 1800,
) -> list[dict]:
    """POST (name, bytes, lat, lon) in batches and wait for every job; returns the finished jobs."""
    headers = {"X-API-Key": api_key} if api_key else {}
    jobs = []
    for start in range(0, len(images), batch):
        chunk = images[start : start + batch]
        files = [("image", (name, data, "image/jpeg")) for name, data, _, _ in chunk]
        meta = json.dumps([{"lat": lat, "lon": lon} for _, _, lat, lon in chunk])
        r = client.post("/references", files=files, data={"metadata": meta}, headers=headers)
        if r.status_code != 202:
            raise RuntimeError(f"POST /references -> {r.status_code}: {r.text[:300]}")
        jobs.append(r.json()["job_id"])
    return [wait_job(client, j, timeout) for j in jobs]


def synthetic_reference(photo: np.ndarray, rng: np.random.Generator, long_side: int = 480) -> bytes:
    """A distinct JPEG cut from a real photo (a random 50-90 % window, resized), so the service's
    de-duplication by content hash does not turn a load test into a no-op."""
    h, w = photo.shape[:2]
    f = rng.uniform(0.5, 0.9)
    ch, cw = int(h * f), int(w * f)
    y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    crop = photo[y : y + ch, x : x + cw]
    scale = long_side / max(ch, cw)
    crop = cv2.resize(crop, (max(1, int(cw * scale)), max(1, int(ch * scale))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", crop, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(80, 95))])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


BENCHMARKS_DOC = REPO / "docs" / "benchmarks.md"


def _markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def write_section(name: str, body: str, doc: Path = BENCHMARKS_DOC) -> None:
    """Replace (or append) one marked section of a results document, leaving the others as they are.

    Why markers: several benchmarks write into docs/benchmarks.md on their own schedules (`make bench`,
    bench/scale.py, bench/ingest_speed.py); each owns its section, so no run erases another's figures."""
    begin, end = _markers(name)
    section = f"{begin}\n{body.strip()}\n{end}"
    text = doc.read_text() if doc.exists() else ""
    if begin in text and end in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + section + "\n"
    doc.write_text(text)


def marked_sections(text: str) -> list[str]:
    """Every ``<!-- name:begin -->...<!-- name:end -->`` block of ``text``, in order."""
    import re

    return [m.group(0) for m in re.finditer(r"<!-- ([\w-]+):begin -->.*?<!-- \1:end -->", text, re.S)]
