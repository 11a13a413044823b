"""Prometheus metrics (prometheus-client): requests, latencies, /locate stages, index, queue, memory."""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, PlatformCollector, ProcessCollector
from starlette.middleware.base import BaseHTTPMiddleware
from starlette.requests import Request

from app.usecases.service import Gauges

#: ``VectorIndex.stats`` keys shown as labels of ``geoloc_index_kind`` (None where a kind has no such one).
KIND_LABELS = ("kind", "nlist", "nprobe", "shortlist", "quantizer", "m")

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)


class Metrics:
    """One registry per app, so tests can build several apps in one process."""

    def __init__(self):
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)  # process memory, CPU, open files
        PlatformCollector(registry=self.registry)
        self.requests = Counter(
            "geoloc_http_requests_total", "HTTP requests", ["route", "method", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "geoloc_http_request_seconds",
            "HTTP request latency",
            ["route", "method", "status"],
            buckets=BUCKETS,
            registry=self.registry,
        )
        self.stage = Histogram(
            "geoloc_locate_stage_seconds",
            "/locate latency by stage",
            ["stage"],
            buckets=BUCKETS,
            registry=self.registry,
        )
        self.index_size = Gauge("geoloc_index_size", "references in the index", ["kind"], registry=self.registry)
        self.index_kind = Gauge(
            "geoloc_index_kind",
            "1 for the index kind serving each part (float, binary) and its parameters",
            ["part", *KIND_LABELS],
            registry=self.registry,
        )
        self.index_switching = Gauge(
            "geoloc_index_switching",
            "1 while the compressed index is built in the background (the collection reached "
            "GEOLOC_INDEX_SWITCH_AT references; the exact one serves meanwhile)",
            registry=self.registry,
        )
        self.index_kind_switches = Gauge(
            "geoloc_index_kind_switches", "exact -> compressed switches by size since start", registry=self.registry
        )
        self.queue_depth = Gauge(
            "geoloc_queue_depth", "references accepted and waiting to be encoded", registry=self.registry
        )
        self.index_version = Gauge(
            "geoloc_index_version", "index version (change log position)", registry=self.registry
        )
        self.snapshot_age = Gauge(
            "geoloc_snapshot_age_seconds", "age of the newest index snapshot (-1: none yet)", registry=self.registry
        )
        self.snapshot_writes = Gauge(
            "geoloc_snapshot_writes", "index snapshots this process wrote since it started", registry=self.registry
        )
        self.replayed_at_start = Gauge(
            "geoloc_index_replayed_at_start", "changes replayed over the snapshot when loading", registry=self.registry
        )
        self.full_rebuilds = Gauge(
            "geoloc_index_full_rebuilds", "full index rebuilds from SQLite since start", registry=self.registry
        )
        self.tombstones = Gauge(
            "geoloc_index_tombstones", "deleted references not compacted yet", registry=self.registry
        )
        self.ingested = Counter(
            "geoloc_ingested_images_total",
            "references encoded by this process's worker",
            ["result"],
            registry=self.registry,
        )

    def observe(self, g: Gauges) -> None:
        """The gauges read from the live collection at scrape time (``GeolocService.gauges``)."""
        self.index_kind.clear()  # a new generation may serve another kind
        for part, stats in g.index.items():
            self.index_size.labels(part).set(stats["size"])
            self.index_kind.labels(part, *(str(stats.get(p)) for p in KIND_LABELS)).set(1)
        self.queue_depth.set(g.pending)
        st = g.upkeep
        self.index_version.set(g.version)
        self.snapshot_age.set(time.time() - st.snapshot_written_at if st.snapshot_written_at else -1)
        self.snapshot_writes.set(st.snapshot_writes)
        self.replayed_at_start.set(st.replayed_at_start)
        self.full_rebuilds.set(st.full_rebuilds)
        self.tombstones.set(g.tombstones)
        self.index_switching.set(int(g.switching))
        self.index_kind_switches.set(st.kind_switches)


class MetricsMiddleware(BaseHTTPMiddleware):
    def __init__(self, app, metrics: Metrics):
        super().__init__(app)
        self.metrics = metrics

    async def dispatch(self, request: Request, call_next):
        start = time.perf_counter()
        status = 500
        try:
            response = await call_next(request)
            status = response.status_code
            return response
        finally:
            route = request.scope.get("route")
            path = getattr(route, "path", "unmatched")
            labels = (path, request.method, str(status))
            self.metrics.requests.labels(*labels).inc()
            self.metrics.latency.labels(*labels).observe(time.perf_counter() - start)
