"""Load: N concurrent clients mixing /locate and /references for T seconds, on loopback only.

    .venv/bin/python -m bench.load --clients 4 --seconds 60            # starts its own server
    .venv/bin/python -m bench.load --url http://127.0.0.1:8000 --api-key KEY   # an existing one

Without --url it starts ``geoloc serve`` (the fitted default configuration in models/) on a fresh data dir
seeded with penn-campus-gps db photos, so the run never touches a collection users care about. With
--url, the references it adds stay in that collection. Bounded three ways: --seconds, --max-requests and
a per-request timeout. Prints requests per second, p50/p95/p99 latency per operation, errors, and the
server's resident memory (from its /metrics) before and after.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from app.engine.configs import DEFAULT_CONFIG
from app.engine.imageio import load_image
from bench.common import (
    REPO,
    is_photo,
    penn_rows,
    percentiles,
    post_references,
    require_loopback,
    resident_bytes,
    synthetic_reference,
)
from tools.server_process import ServerProcess

MAX_SECONDS = 900
MAX_CLIENTS = 64


@dataclass
class Sample:
    op: str
    status: int  # 0: transport error or timeout
    ms: float


@dataclass
class LoadReport:
    clients: int
    seconds: float
    locate_share: float
    samples: list[Sample] = field(default_factory=list)
    rss_before: float | None = None
    rss_after: float | None = None
    references_indexed_after: int | None = None

    def summary(self) -> dict:
        ok = [s for s in self.samples if 200 <= s.status < 300]
        out = {
            "clients": self.clients,
            "seconds": round(self.seconds, 1),
            "locate_share": self.locate_share,
            "requests": len(self.samples),
            "requests_per_s": len(self.samples) / self.seconds if self.seconds else 0.0,
            "ok": len(ok),
            "errors": dict(Counter(str(s.status) for s in self.samples if not 200 <= s.status < 300)),
            "rss_before_mb": None if self.rss_before is None else self.rss_before / 2**20,
            "rss_after_mb": None if self.rss_after is None else self.rss_after / 2**20,
            "references_indexed_after": self.references_indexed_after,
            "ops": {},
        }
        for op in sorted({s.op for s in self.samples}):
            ms = [s.ms for s in ok if s.op == op]
            out["ops"][op] = {"n": sum(1 for s in self.samples if s.op == op), "ok": len(ms), **percentiles(ms)}
        return out


def format_report(summary: dict) -> str:
    lines = [
        f"{summary['clients']} clients, {summary['seconds']} s, {summary['locate_share']:.0%} /locate: "
        f"{summary['requests']} requests, {summary['requests_per_s']:.2f} req/s, errors {summary['errors'] or 'none'}",
    ]
    for op, s in summary["ops"].items():
        lines.append(f"  {op:<12} n={s['n']:<5} p50 {s['p50']:.0f} ms  p95 {s['p95']:.0f} ms  p99 {s['p99']:.0f} ms")
    if summary["rss_before_mb"] is not None:
        before, after = summary["rss_before_mb"], summary["rss_after_mb"]
        lines.append(f"  server resident memory: {before:.0f} MB before, {after:.0f} MB after")
    lines.append(f"  references in the index right after the run: {summary['references_indexed_after']}")
    return "\n".join(lines)


class Workload:
    """Query images (real penn photos and crops, kept for /locate) and a pool of distinct reference JPEGs."""

    def __init__(self, rows, n_references: int, seed: int = 0):
        rng = np.random.default_rng(seed)
        queries = [r for r in rows if r.split == "query"]
        self.queries = [r.image.read_bytes() for r in queries]
        photos = [r for r in rows if is_photo(r) and r.split != "query"]
        decoded = {r.image: load_image(r.image.read_bytes(), decode_long_side=960).rgb for r in photos}
        self.references = []
        for n in range(n_references):
            r = photos[n % len(photos)]
            self.references.append((f"load-{n}.jpg", synthetic_reference(decoded[r.image], rng), r.lat, r.lon))
        self._q = self._r = 0

    def next_query(self) -> bytes:
        self._q += 1
        return self.queries[self._q % len(self.queries)]

    def next_reference(self) -> tuple[str, bytes, float, float]:
        self._r += 1
        return self.references[self._r % len(self.references)]


async def _client(
    url: str,
    work: Workload,
    report: LoadReport,
    deadline: float,
    budget: list[int],
    rng: np.random.Generator,
    api_key: str | None,
    timeout: float,
) -> None:
    headers = {"X-API-Key": api_key} if api_key else {}
    async with httpx.AsyncClient(base_url=url, timeout=timeout, headers=headers) as client:
        while time.perf_counter() < deadline and budget[0] > 0:
            budget[0] -= 1
            if rng.random() < report.locate_share:
                op, kwargs = "/locate", {"files": [("image", ("q.jpg", work.next_query(), "image/jpeg"))]}
            else:
                name, data, lat, lon = work.next_reference()
                op = "/references"
                kwargs = {"files": [("image", (name, data, "image/jpeg"))], "data": {"lat": lat, "lon": lon}}
            t0 = time.perf_counter()
            try:
                r = await client.post(op, **kwargs)
                status = r.status_code
            except httpx.HTTPError:
                status = 0
            report.samples.append(Sample(op, status, (time.perf_counter() - t0) * 1000))


async def _run_clients(urls, work, report, max_requests, api_key, timeout, seed) -> None:
    """Client ``c`` talks to ``urls[c % len(urls)]``: the clients spread round-robin over the servers."""
    deadline = time.perf_counter() + report.seconds
    budget = [max_requests]
    rngs = [np.random.default_rng([seed, c]) for c in range(report.clients)]
    await asyncio.gather(
        *(
            _client(urls[c % len(urls)], work, report, deadline, budget, rngs[c], api_key, timeout)
            for c in range(report.clients)
        )
    )


def run_load(
    url: str | Sequence[str],
    clients: int,
    seconds: float,
    locate_share: float = 0.8,
    max_requests: int = 5000,
    api_key: str | None = None,
    timeout: float = 60.0,
    seed: int = 0,
    rows=None,
) -> LoadReport:
    """``url``: one server, or several (replicas of one collection) that the clients spread over; the
    resident memory reported is then the sum of theirs, the index size the first one's."""
    urls = [url] if isinstance(url, str) else list(url)
    for u in urls:
        require_loopback(u)
    if not 1 <= clients <= MAX_CLIENTS:
        raise SystemExit(f"--clients must be 1..{MAX_CLIENTS}")
    if not 0 < seconds <= MAX_SECONDS:
        raise SystemExit(f"--seconds must be in (0, {MAX_SECONDS}]")
    rows = rows or penn_rows()
    n_refs = min(int(max_requests * (1 - locate_share)) + clients, 1000)
    work = Workload(rows, max(n_refs, 1), seed)
    report = LoadReport(clients, seconds, locate_share)
    servers = [httpx.Client(base_url=u, timeout=30) for u in urls]
    try:
        report.rss_before = _total([resident_bytes(c) for c in servers])
        t0 = time.perf_counter()
        asyncio.run(_run_clients(urls, work, report, max_requests, api_key, timeout, seed))
        report.seconds = time.perf_counter() - t0
        report.rss_after = _total([resident_bytes(c) for c in servers])
        report.references_indexed_after = servers[0].get("/ready").json().get("index_size")
    finally:
        for c in servers:
            c.close()
    return report


def _total(values: list[float | None]) -> float | None:
    return None if any(v is None for v in values) else sum(values)


def seeded_server(data_dir: Path, config: str, rows, n_seed: int = 40) -> ServerProcess:
    """A server on a fresh data dir with ``n_seed`` db photos already indexed."""
    server = ServerProcess(data_dir, REPO / "models", config)
    try:
        server.wait_ready()
        seed = [r for r in rows if r.split == "db" and is_photo(r)][:n_seed]
        post_references(server.client, [(r.image.name, r.image.read_bytes(), r.lat, r.lon) for r in seed])
    except BaseException:
        server.stop()
        raise
    return server


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", help="a loopback server to load; default: start one on a temporary data dir")
    ap.add_argument("--api-key")
    ap.add_argument("--config", default=DEFAULT_CONFIG, help="configuration of the server this script starts")
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=60)
    ap.add_argument("--locate-share", type=float, default=0.8, help="fraction of requests that are /locate")
    ap.add_argument("--max-requests", type=int, default=5000)
    ap.add_argument("--timeout", type=float, default=60, help="per request, seconds")
    ap.add_argument("--json", type=Path, help="also write the summary here")
    args = ap.parse_args()
    rows = penn_rows()
    server = None
    with tempfile.TemporaryDirectory(prefix="geoloc-load-") as tmp:
        try:
            if args.url is None:
                print("starting a server on a temporary data dir and seeding it ...")
                server = seeded_server(Path(tmp) / "data", args.config, rows)
                url = server.url
            else:
                url = args.url
            report = run_load(
                url,
                args.clients,
                args.seconds,
                args.locate_share,
                args.max_requests,
                args.api_key or (server.api_key if server else None),
                args.timeout,
                rows=rows,
            )
        finally:
            if server is not None:
                server.stop()
    summary = report.summary()
    print(format_report(summary))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
