"""/locate on a real server, stage by stage, next to the floor; and ingestion through the API.

The floor is what no pipeline of this kind can avoid: decoding the upload, one SqueezeNet pass and one
local-feature extraction, run here in the bench process with the same code and the same thread settings
as the server, interleaved request by request with the server's /locate so both see the same machine.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from app.engine.configs import PipelineConfig
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits, load_image
from app.engine.registry import Kind, create
from app.manifests import Row
from app.settings import Settings
from bench.common import is_photo, median_ms, percentiles, post_references

FULL_SIZE_DIR = "photos-full"
FLOOR_STAGES = ("decode", "local_features", "cnn")


@dataclass
class IngestFigures:
    kind: str
    images: int
    seconds: float

    @property
    def images_per_s(self) -> float:
        return self.images / self.seconds


def collection_rows(rows: list[Row], exclude_groups: set[str]) -> list[Row]:
    """The db rows minus the captures used as queries here (a query is never its own reference)."""
    return [r for r in rows if r.split == "db" and r.group not in exclude_groups]


def ingest(client: httpx.Client, rows: list[Row], kind: str, batch: int = 8) -> IngestFigures:
    """Time from the first POST to the last finished job: what a user waits for a bulk upload."""
    images = [(r.image.name, r.image.read_bytes(), r.lat, r.lon) for r in rows]
    t0 = time.perf_counter()
    jobs = post_references(client, images, batch=batch)
    seconds = time.perf_counter() - t0
    failed = [j for j in jobs if j["status"] != "done"]
    if failed:
        raise RuntimeError(f"ingestion jobs failed: {failed[:2]}")
    return IngestFigures(kind, len(images), seconds)


class Floor:
    """decode + the global model + local features, as the configuration runs them, and nothing else."""

    def __init__(self, models_dir: Path, config: PipelineConfig):
        self.config = config
        self.global_model = create(Kind.GLOBAL_MODEL, config.global_model, models_dir)
        self.global_model.load()
        self.local = create(
            Kind.LOCAL_EXTRACTOR,
            config.local,
            models_dir,
            max_keypoints=config.max_keypoints,
            long_side=config.local_long_side,
        )
        self.limits: ImageLimits = Settings().image_limits()

    def __call__(self, data: bytes) -> dict[str, float]:
        t = {}
        t0 = time.perf_counter()
        img = load_image(data, self.limits)
        t["decode"] = time.perf_counter()
        self.local(img.rgb)  # the order Pipeline.extract runs them in
        t["local_features"] = time.perf_counter()
        self.global_model.dense(img.rgb, self.config.cnn_short_side)
        t["cnn"] = time.perf_counter()
        out, prev = {}, t0
        for k, v in t.items():
            out[k] = (v - prev) * 1000
            prev = v
        out["total"] = (t["cnn"] - t0) * 1000
        return out


@dataclass
class LocateFigures:
    label: str
    n_images: int
    requests: int
    client_ms: dict[str, float]  # p50/p95/p99 wall time seen by the client (upload included)
    server_stages_ms: dict[str, float]  # median per stage, from the response's timings_ms
    floor_stages_ms: dict[str, float]  # median per floor stage
    top1_within_25m: float
    samples: list[dict]  # per request: client ms, server total ms, floor total ms

    server_floor_ms: float = 0.0  # median of decode + local features + cnn as the server timed them

    @property
    def ratio_to_floor(self) -> float:
        return self.client_ms["p50"] / self.floor_stages_ms["total"]

    @property
    def ratio_to_server_floor(self) -> float:
        return self.client_ms["p50"] / self.server_floor_ms


def measure_locate(client: httpx.Client, floor: Floor, queries: list[Row], label: str, reps: int) -> LocateFigures:
    payloads = [(r, r.image.read_bytes()) for r in queries]
    # Warm both sides on every image first: onnxruntime pays once per new input shape (portrait and
    # landscape photos give different shapes), which a user sees once per server, not per request.
    for _, data in payloads:
        client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))]).raise_for_status()
        floor(data)
    wall, stages, floors, hits = [], [], [], []
    for _ in range(reps):
        for row, data in payloads:
            t0 = time.perf_counter()
            r = client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))])
            wall.append((time.perf_counter() - t0) * 1000)
            r.raise_for_status()
            body = r.json()
            stages.append(body["timings_ms"])
            top = body["candidates"][0] if body["candidates"] else None
            hits.append(top is not None and haversine_m(row.lat, row.lon, top["lat"], top["lon"]) <= 25.0)
            floors.append(floor(data))
    names = list(dict.fromkeys(k for s in stages for k in s))
    return LocateFigures(
        label=label,
        n_images=len(payloads),
        requests=len(wall),
        client_ms=percentiles(wall),
        server_stages_ms={k: median_ms(s.get(k, 0.0) for s in stages) for k in names},
        floor_stages_ms={k: median_ms(f[k] for f in floors) for k in floors[0]},
        top1_within_25m=sum(hits) / len(hits),
        samples=[
            {"client": w, "server": s["total"], "floor": f["total"], "server_floor": _floor_part(s)}
            for w, s, f in zip(wall, stages, floors, strict=True)
        ],
        server_floor_ms=median_ms(_floor_part(s) for s in stages),
    )


def _floor_part(server_timings: dict[str, float]) -> float:
    return sum(server_timings.get(k, 0.0) for k in FLOOR_STAGES)


def full_size_queries(rows: list[Row], shared_photos_full: Path) -> list[Row]:
    """The 12 MP originals, with the positions of their 1600 px versions in the manifest."""
    by_name = {r.image.name: r for r in rows if is_photo(r)}
    out = []
    for path in sorted(shared_photos_full.glob("*.jpg")):
        r = by_name.get(path.name)
        if r is not None:
            out.append(Row(image=path, lat=r.lat, lon=r.lon, split="query", group=r.group))
    return out
