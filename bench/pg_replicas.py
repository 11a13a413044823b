"""/locate throughput with one and with two API replicas on one PostgreSQL database, on this machine.

Run: ``python -m bench.pg_replicas --clients 4 --seconds 30 --rounds 2``. Starts a throw-away PostgreSQL
server (``tools.postgres_server``), then two ``geoloc serve`` processes, each with a local data dir of its
own and the images and snapshots on one shared path, on that one database (what
tests/api/test_postgres_hosts.py runs as two "hosts"), with the fitted configuration in models/; the
first (the writer) is seeded with ``--seed`` penn db photos through POST /references and the second starts
once they are indexed (it loads the writer's snapshot). Then ``--clients`` concurrent clients send only
/locate (penn query photos, ``bench.load``'s client) for ``--seconds``, first all against one replica, then
spread round-robin over both, alternating 1, 2, 1, 2 ... for ``--rounds`` so that both settings see the
same machine state. Prints each run and, per setting, the median requests/s over the rounds and /locate
p50/p95 over all its requests, with the ratio two/one.

On one host both replicas share the same cores: a second replica adds no CPU, so no gain is expected here;
what it shows is that two replicas serve side by side without one slowing the other beyond the CPU they
share. A gain needs replicas on hosts of their own.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import secrets
import statistics
import tempfile
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG
from bench.common import REPO, is_photo, machine, penn_rows, percentiles, post_references
from bench.load import LoadReport, run_load
from tools.postgres_server import PostgresServer
from tools.server_process import ServerProcess


def _replicas(root: Path, url: str, config: str, rows, n_seed: int, key: str) -> list[ServerProcess]:
    """Two API processes on one database: the writer seeded with ``n_seed`` db photos, then a second one."""
    env = {
        "GEOLOC_DATABASE_URL": url,
        "GEOLOC_IMAGES_DIR": str(root / "shared" / "images"),
        "GEOLOC_SNAPSHOTS_DIR": str(root / "shared" / "snapshots"),
    }
    servers: list[ServerProcess] = []
    try:
        a = ServerProcess(root / "host-a" / "data", REPO / "models", config, api_key=key, extra_env=env)
        servers.append(a)
        a.wait_ready(600)
        a.client.headers["X-API-Key"] = key
        seed = [r for r in rows if r.split == "db" and is_photo(r)][:n_seed]
        post_references(a.client, [(r.image.name, r.image.read_bytes(), r.lat, r.lon) for r in seed])
        b = ServerProcess(root / "host-b" / "data", REPO / "models", config, api_key=key, extra_env=env)
        servers.append(b)
        ready = b.wait_ready(600)
        if ready.get("index_size") != a.client.get("/ready").json().get("index_size"):
            raise RuntimeError(f"the replicas disagree: {ready}")
    except BaseException:
        for s in servers:
            s.stop()
        raise
    return servers


def _warm_up(servers: list[ServerProcess], rows, key: str) -> None:
    """A few /locate on each replica first: the first requests of a process pay one-off start-up costs."""
    for s in servers:
        run_load(s.url, 2, 10, locate_share=1.0, max_requests=6, api_key=key, rows=rows)


def _setting(reports: list[LoadReport]) -> dict:
    ms = [x.ms for r in reports for x in r.samples if x.op == "/locate" and 200 <= x.status < 300]
    errors = sum(1 for r in reports for x in r.samples if not 200 <= x.status < 300)
    rates = [len(r.samples) / r.seconds for r in reports]
    return {"req_per_s": statistics.median(rates), "runs": rates, "n": len(ms), "errors": errors, **percentiles(ms)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=DEFAULT_CONFIG, help="the fitted configuration in models/")
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=30, help="per run")
    ap.add_argument("--rounds", type=int, default=2, help="pairs of runs (one replica, then two)")
    ap.add_argument("--seed", type=int, default=40, help="penn db photos in the collection")
    args = ap.parse_args()
    rows = penn_rows()
    key = secrets.token_urlsafe(24)
    servers: list[ServerProcess] = []
    runs: dict[int, list[LoadReport]] = {1: [], 2: []}
    with tempfile.TemporaryDirectory(prefix="geoloc-bench-replicas-") as tmp:
        server = PostgresServer().start()
        try:  # the servers stopped before their folder goes (a stopping writer writes its last snapshot)
            servers = _replicas(Path(tmp), server.create_database(), args.config, rows, args.seed, key)
            size = servers[0].client.get("/ready").json()["index_size"]
            print(f"{machine()}; PostgreSQL {server.bin.parent.name}; {size} references; config {args.config}")
            _warm_up(servers, rows, key)
            for rnd in range(args.rounds):
                for n in (1, 2):
                    report = run_load(
                        [s.url for s in servers[:n]], args.clients, args.seconds, locate_share=1.0,
                        max_requests=10**6, api_key=key, seed=rnd, rows=rows,
                    )  # fmt: skip
                    runs[n].append(report)
                    summary = report.summary()
                    loc = summary["ops"].get("/locate", {})
                    print(
                        f"round {rnd + 1}, {n} replica(s): {summary['requests_per_s']:.2f} req/s, /locate p50 "
                        f"{loc.get('p50', float('nan')):.0f} ms p95 {loc.get('p95', float('nan')):.0f} ms, "
                        f"errors {summary['errors'] or 'none'}",
                        flush=True,
                    )
        finally:
            with contextlib.ExitStack() as stops:  # every stop runs, the database server's last
                stops.callback(server.stop)
                for replica in servers:
                    stops.callback(replica.stop)
    one, two = _setting(runs[1]), _setting(runs[2])
    print(f"{args.clients} clients, /locate only, {args.rounds} x {args.seconds:.0f} s per setting, interleaved:")
    for n, s in ((1, one), (2, two)):
        print(
            f"  {n} replica(s): {s['req_per_s']:.2f} req/s (runs {', '.join(f'{r:.2f}' for r in s['runs'])}), "
            f"/locate p50 {s['p50']:.0f} ms p95 {s['p95']:.0f} ms over {s['n']} requests, errors {s['errors']}"
        )
    print(
        f"  ratio two/one: req/s {two['req_per_s'] / one['req_per_s']:.2f}, p50 {two['p50'] / one['p50']:.2f}, "
        f"p95 {two['p95'] / one['p95']:.2f} (both replicas on this machine's {os.cpu_count()} cores)"
    )


if __name__ == "__main__":
    main()
