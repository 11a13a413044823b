"""A real server's cold start at size, and where its resident memory goes, this tree against a baseline tree.

    .venv/bin/python -m bench.cold_start --sizes 10000,1000000 --engines sqlite,postgres \
        --baseline /tmp/base --repeats 2

``--baseline`` is another tree's ``app`` (``git archive <commit> app | tar -x -C DIR``), run by the same
interpreter: the two are started in turn on the same data dir, ``--repeats`` times, so both see the same
machine load (interleaved, medians reported).

Per engine and size a data dir is seeded once: the first ``--images`` references through ``bench.seed`` (the
bulk path with placeholder images; it also binds the data dir to the fitted pipeline), the rest straight into
the store's tables by ``bench.pg_catchup``'s seeding (rows and change log entries as ``add_many`` writes them,
COPY on PostgreSQL, no image files: nothing here reads a reference's image). PostgreSQL is a throw-away server
(``tools.postgres_server``, Debian's package, as the tests use).

Each start: every snapshot of the data dir is deleted first, so the server rebuilds its index from the store
(the cold start: ``Collection._rebuild``); then ``geoloc serve`` (``tools.server_process``) is started and
timed until /ready answers 200. Read from /proc: the server's peak resident memory up to ready (VmHWM) and its
resident memory at ready; again after the snapshot the rebuild makes due has been written (from the served
index itself, or a compacted copy of it where deletions are due to be dropped); and after ``--locates``
/locate of real penn photos (RSS, and its anonymous part, the heap, and file-backed part, mapped files:
before the ``ivf-rabitq`` kind read its float codes by ``pread``, they were mapped from its snapshot file,
and a kernel with large page-cache folios mapped about a megabyte of the file per code the re-rank read).
The rebuild's own seconds come from the server's log line ("index rebuilt from N stored codes in S s").

``--switch-at N`` (issue 35, item 2) starts the servers with GEOLOC_INDEX_SWITCH_AT=N: a collection of N or
more references switches to the compressed kinds after the rebuild (trained and built in the background),
and for this tree the start also waits for the switch and the snapshot it makes due, then reads the
resident memory again ("after switch"). A baseline without the setting keeps its exact index.

``--restart``: after each start is stopped (a clean stop writes a last snapshot if one is due), the same
tree is started again on the snapshot it left, as a replica made ready from a snapshot is: seconds to /ready,
its peak resident memory (VmHWM) up to ready against the snapshot files' size, and its memory after
``--locates`` /locates.

``--uploads N`` (default 5): after the /locates of each start, N penn reference photos are uploaded through
POST /references one at a time; after each one's job, /locate of the same photo should answer its new
reference first, and after DELETE /references/{id} the next /locate should not name it (issue 35: "each
uploaded photo found first after its job, deletes gone at once", on the served kind at that size).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from app.engine.configs import DEFAULT_CONFIG
from app.engine.pipeline import load_pipeline
from app.storage.settings import StorageSettings
from app.storage.store import ReferenceStore
from bench.common import is_photo, machine, penn_rows
from bench.pg_catchup import FLOAT_DIM, _seed_rows
from bench.seed import seed
from tools.process_memory import MiB, PeakRss, rss_bytes
from tools.server_process import ServerProcess, wait_job

REBUILT = re.compile(r"index rebuilt from (\d+) stored codes in ([0-9.]+) s")


def _status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} for {pid}")


def seed_data_dir(data: Path, refs: int, images: int, models: Path, config: str, batch: int = 50_000) -> float:
    """``refs`` indexed references in ``data`` (and in GEOLOC_DATABASE_URL's database when set); seconds."""
    t0 = time.perf_counter()
    seed(data, min(images, refs), models, config)
    store = ReferenceStore(data, backend=StorageSettings().backend(data))
    rng = np.random.default_rng(1)
    for start in range(min(images, refs), refs, batch):
        _seed_rows(store, rng, start, min(batch, refs - start))
    if store.engine == "postgres":  # what add_many's after_bulk_insert does after a load
        store.db.execute("ANALYZE refs, changes")
    store.close()
    return time.perf_counter() - t0


def _drop_snapshots(data: Path) -> None:
    for f in [data / "index.json", *data.glob("*-v*.faiss")]:
        f.unlink(missing_ok=True)


def _wait_snapshot(server: ServerProcess, timeout: float = 600, writes: int = 1) -> float:
    """Seconds until the server has written ``writes`` snapshots (``geoloc_snapshot_writes``)."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        text = server.client.get("/metrics").text
        m = re.search(r"^geoloc_snapshot_writes (\S+)", text, re.M)
        if m and float(m.group(1)) >= writes:
            return time.perf_counter() - t0
        time.sleep(0.5)
    raise TimeoutError("no snapshot written")


def _wait_switched(server: ServerProcess, data: Path, timeout: float = 1800) -> float:
    """Seconds until the index serves the compressed kind and a snapshot of it is written (its manifest names
    the kind)."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        try:
            kind = json.loads((data / "index.json").read_text())["files"]["float"].get("kind")
        except (FileNotFoundError, ValueError, KeyError):
            kind = None
        if kind not in (None, "flat"):
            return time.perf_counter() - t0
        time.sleep(1.0)
    raise TimeoutError("the index did not switch kind")


def _locate(server: ServerProcess, photos: list[Path], locates: int) -> list[float]:
    ms = []
    for i in range(locates):
        photo = photos[i % len(photos)]
        t = time.perf_counter()
        r = server.client.post("/locate", files=[("image", ("q.jpg", photo.read_bytes(), "image/jpeg"))])
        ms.append((time.perf_counter() - t) * 1e3)
        if r.status_code != 200:
            raise RuntimeError(f"/locate answered {r.status_code}: {r.text[:300]}")
    return ms


def uploads_found_then_deleted(server: ServerProcess, photos: list[Path]) -> dict:
    """Each photo uploaded as a new reference (the API's job: accepted, encoded, added to the served index),
    then located: is its own reference the first candidate? Then deleted: is it gone from the next /locate
    at once? The issue's "each uploaded photo found first after its job, deletes gone at once", at size."""
    job_ms, first, gone = [], 0, 0
    for n, photo in enumerate(photos):
        body = photo.read_bytes()
        t = time.perf_counter()
        r = server.client.post(
            "/references",
            files=[("image", (photo.name, body, "image/jpeg"))],
            data={"lat": 39.95 + n * 1e-4, "lon": -75.19, "label": f"cold-start upload {n}"},
        )
        r.raise_for_status()
        ref = r.json()["reference_ids"][0]
        job = wait_job(server.client, r.json()["job_id"], timeout=600)
        job_ms.append((time.perf_counter() - t) * 1e3)
        if job["status"] != "done":
            raise RuntimeError(f"upload job failed: {job}")
        files = [("image", ("q.jpg", body, "image/jpeg"))]
        top = server.client.post("/locate", files=files).json()["candidates"]
        first += bool(top) and top[0]["reference_id"] == ref
        server.client.delete(f"/references/{ref}").raise_for_status()
        after = server.client.post("/locate", files=files).json()["candidates"]
        gone += all(c["reference_id"] != ref for c in after)
    return {
        "upload_job_p50_ms": statistics.median(job_ms) if job_ms else float("nan"),
        "uploads_found_first": float(first),
        "deletes_gone": float(gone),
        "uploads": float(len(photos)),
    }


def restart(data: Path, models: Path, config: str, code: Path | None, photos: list[Path], locates: int, env) -> dict:
    """A second start on the snapshot the first one left (a replica made ready from a snapshot): seconds to
    /ready, peak and resident memory then, and after ``locates`` /locates; the snapshot files' bytes."""
    manifest = json.loads((data / "index.json").read_text())
    out = {"snapshot_file_mb": sum(f["bytes"] for f in manifest["files"].values()) / MiB}
    t0 = time.perf_counter()
    server = ServerProcess(data, models, config, code=code, extra_env=env)
    pid = server.proc.pid
    try:
        server.wait_ready(timeout=900)
        out["restart_ready_s"] = time.perf_counter() - t0
        out["restart_hwm_ready_mb"] = _status_kb(pid, "VmHWM") / 1024
        out["restart_rss_ready_mb"] = rss_bytes(pid) / MiB
        out["restart_anon_ready_mb"] = _status_kb(pid, "RssAnon") / 1024
        ms = _locate(server, photos, locates)
        out["restart_locate_p50_ms"] = statistics.median(ms) if ms else float("nan")
        out["restart_rss_locates_mb"] = rss_bytes(pid) / MiB
        out["restart_anon_locates_mb"] = _status_kb(pid, "RssAnon") / 1024
    finally:
        server.stop()
    log = Path(server.log.name).read_text()
    out["restart_rebuilt"] = float(bool(REBUILT.search(log)))  # 1: the snapshot was not used
    return out


def one_start(
    data: Path,
    models: Path,
    config: str,
    code: Path | None,
    photos: list[Path],
    locates: int,
    switch_at: int | None = None,
    size: int = 0,
    restarts: bool = False,
    uploads: list[Path] | None = None,
) -> dict:
    _drop_snapshots(data)
    t0 = time.perf_counter()
    env = {"GEOLOC_INDEX_SWITCH_AT": str(switch_at)} if switch_at is not None else None
    server = ServerProcess(data, models, config, code=code, extra_env=env)
    pid = server.proc.pid
    try:
        with PeakRss(pid, every_s=0.05):
            server.wait_ready(timeout=900)
        out = {"ready_s": time.perf_counter() - t0, "hwm_ready_mb": _status_kb(pid, "VmHWM") / 1024}
        out["rss_ready_mb"] = rss_bytes(pid) / MiB
        out["snapshot_s"] = _wait_snapshot(server)
        time.sleep(1.0)
        out["rss_snapshot_mb"] = rss_bytes(pid) / MiB
        out["hwm_snapshot_mb"] = _status_kb(pid, "VmHWM") / 1024
        if switch_at is not None and code is None and size >= switch_at:  # the baseline has no switch
            out["switch_s"] = _wait_switched(server, data)
            time.sleep(1.0)
            out["rss_switched_mb"] = rss_bytes(pid) / MiB
            out["anon_switched_mb"] = _status_kb(pid, "RssAnon") / 1024
            out["hwm_switched_mb"] = _status_kb(pid, "VmHWM") / 1024
        ms = _locate(server, photos, locates)
        out["locate_p50_ms"] = statistics.median(ms) if ms else float("nan")
        out["rss_locates_mb"] = rss_bytes(pid) / MiB
        out["anon_locates_mb"] = _status_kb(pid, "RssAnon") / 1024  # the heap; the rest is mapped files
        out["file_locates_mb"] = _status_kb(pid, "RssFile") / 1024  # (ivf-rabitq's float codes, libraries)
        if uploads:
            out.update(uploads_found_then_deleted(server, uploads))
        out["hwm_end_mb"] = _status_kb(pid, "VmHWM") / 1024
    finally:
        server.stop()
    m = REBUILT.search(Path(server.log.name).read_text())
    out["rebuild_s"] = float(m.group(2)) if m else float("nan")
    out["rebuilt_refs"] = int(m.group(1)) if m else -1
    if restarts:
        out.update(restart(data, models, config, code, photos, locates, env))
    return out


FIELDS = (
    ("rebuild_s", "rebuild s (log)", "{:.2f}"),
    ("ready_s", "start to /ready s", "{:.1f}"),
    ("hwm_ready_mb", "peak RSS to ready MB", "{:,.0f}"),
    ("rss_ready_mb", "RSS at ready MB", "{:,.0f}"),
    ("rss_snapshot_mb", "RSS after first snapshot MB", "{:,.0f}"),
    ("hwm_snapshot_mb", "peak RSS with snapshot MB", "{:,.0f}"),
    ("switch_s", "switch to compressed s (after ready)", "{:.0f}"),
    ("rss_switched_mb", "RSS after switch and its snapshot MB", "{:,.0f}"),
    ("hwm_switched_mb", "peak RSS with switch MB", "{:,.0f}"),
    ("anon_switched_mb", "RssAnon after switch MB", "{:,.0f}"),
    ("rss_locates_mb", "RSS after /locates MB", "{:,.0f}"),
    ("anon_locates_mb", "RssAnon after /locates MB", "{:,.0f}"),
    ("file_locates_mb", "RssFile after /locates MB", "{:,.0f}"),
    ("locate_p50_ms", "/locate p50 ms", "{:.0f}"),
    ("uploads", "uploads", "{:.0f}"),
    ("upload_job_p50_ms", "upload job p50 ms", "{:.0f}"),
    ("uploads_found_first", "uploads found first after the job", "{:.0f}"),
    ("deletes_gone", "deleted at once", "{:.0f}"),
    ("snapshot_file_mb", "snapshot files MB", "{:,.0f}"),
    ("restart_ready_s", "restart: to /ready s", "{:.1f}"),
    ("restart_hwm_ready_mb", "restart: peak RSS to ready MB", "{:,.0f}"),
    ("restart_rss_ready_mb", "restart: RSS at ready MB", "{:,.0f}"),
    ("restart_anon_ready_mb", "restart: RssAnon at ready MB", "{:,.0f}"),
    ("restart_rss_locates_mb", "restart: RSS after /locates MB", "{:,.0f}"),
    ("restart_anon_locates_mb", "restart: RssAnon after /locates MB", "{:,.0f}"),
    ("restart_locate_p50_ms", "restart: /locate p50 ms", "{:.0f}"),
    ("restart_rebuilt", "restart: rebuilt (1) or from the snapshot (0)", "{:.0f}"),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10000,1000000")
    ap.add_argument("--engines", default="sqlite,postgres")
    ap.add_argument("--baseline", type=Path, help="another tree holding an `app` package (the code before)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--locates", type=int, default=5)
    ap.add_argument("--images", type=int, default=2000, help="of each size, seeded with image files")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--models-dir", type=Path, default=Path("models"))
    ap.add_argument("--work", type=Path, help="where the data dirs go (default: a temporary folder)")
    ap.add_argument(
        "--switch-at", type=int, help="GEOLOC_INDEX_SWITCH_AT for the servers; this tree's start waits for the switch"
    )
    ap.add_argument(
        "--restart",
        action="store_true",
        help="after each start, start again on the snapshot it left (a replica ready from a snapshot)",
    )
    ap.add_argument(
        "--uploads",
        type=int,
        default=5,
        help="after the /locates, upload this many penn reference photos, locate each, delete it, locate again",
    )
    args = ap.parse_args()
    args.models_dir = args.models_dir.resolve()  # the baseline server runs in its own tree
    pipe = load_pipeline(args.models_dir, args.config)
    if pipe.float_dim != FLOAT_DIM or pipe.bits:
        raise SystemExit(f"the seeding writes {FLOAT_DIM}-float codes only; {args.config} has others")
    photos = [r.image for r in penn_rows() if is_photo(r) and r.split == "query"][: max(args.locates, 1)]
    uploads = [r.image for r in penn_rows() if is_photo(r) and r.split == "db"][: max(args.uploads, 0)]
    trees = {"this tree": None, **({"baseline": args.baseline.resolve()} if args.baseline else {})}
    print(machine(), f"config {args.config}", flush=True)
    results: dict[tuple[str, int, str], list[dict]] = {}
    work = Path(args.work or tempfile.mkdtemp(prefix="geoloc-cold-"))
    for engine in args.engines.split(","):
        server = None
        if engine == "postgres":
            from tools.postgres_server import PostgresServer

            server = PostgresServer().start()
        try:
            for size in (int(s) for s in args.sizes.split(",")):
                data = work / f"{engine}-{size}" / "data"
                shutil.rmtree(data.parent, ignore_errors=True)
                if server is not None:
                    os.environ["GEOLOC_DATABASE_URL"] = server.create_database()
                took = seed_data_dir(data, size, args.images, args.models_dir, args.config)
                print(f"{engine} {size:,d}: seeded in {took:.0f} s", flush=True)
                for rep in range(args.repeats):
                    for name, code in trees.items() if rep % 2 == 0 else reversed(trees.items()):
                        r = one_start(
                            data,
                            args.models_dir,
                            args.config,
                            code,
                            photos,
                            args.locates,
                            args.switch_at,
                            size,
                            args.restart,
                            uploads,
                        )
                        results.setdefault((engine, size, name), []).append(r)
                        print(f"  {engine} {size:,d} {name} #{rep + 1}: " + ", ".join(
                            f"{k} {v:.1f}" for k, v in r.items()), flush=True)  # fmt: skip
                shutil.rmtree(data.parent, ignore_errors=True)
        finally:
            os.environ.pop("GEOLOC_DATABASE_URL", None)
            if server is not None:
                server.stop()
    print()
    print("| engine | references | code | " + " | ".join(label for _, label, _ in FIELDS) + " |")
    print("|---|---|---|" + "---|" * len(FIELDS))
    for (engine, size, name), runs in results.items():
        cells = [
            fmt.format(statistics.median(r[key] for r in runs)) if key in runs[0] else "" for key, _, fmt in FIELDS
        ]
        print(f"| {engine} | {size:,d} | {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
