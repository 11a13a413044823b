"""Write docs/benchmarks.md: every speed and memory figure of the service, measured in one run.

    .venv/bin/python -m bench.benchmarks            # `make bench`; about 15-20 minutes on 2 cores

1. a real server (``geoloc serve``, default configuration) on a fresh data dir: ingestion rate through
   POST /references, then /locate on the 12 MP originals and on 1600 px photos, interleaved with the floor
   (decode + SqueezeNet + local features alone) in this process;
2. a short bounded load run against that server (bench/load.py);
   then /locate of the default against hybrid-xfeat on two servers, interleaved (bench/compare_configs.py);
3. the thesis-style baseline against our pipelines on penn-campus-gps (recall and time per query);
4. search latency and bytes per reference at 1k to 1M references (synthetic codes of production size).

Everything is a median unless it says otherwise, and every ratio compares two figures from this run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG, get_config
from bench import baseline as baseline_mod
from bench import compare_configs, search_scaling
from bench.common import MANIFEST, REPO, is_photo, machine, marked_sections, penn_rows, write_section
from bench.load import format_report, run_load
from bench.locate_latency import Floor, collection_rows, full_size_queries, ingest, measure_locate
from tools.server_process import ServerProcess

SHARED = REPO.parent / "shared"
COMMAND = ".venv/bin/python -m bench.benchmarks"
COMPARED = "hybrid-xfeat"  # compared for speed: its /locate p50 against the default's, in this run
BINARY = "hybrid-bin"  # the same descriptor with a Hamming shortlist: what to run at 10^5-10^6 references


def _git_commit() -> str:
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True
        ).stdout.strip()
        return head + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def service_figures(rows, models_dir: Path, config: str, reps_full: int, reps_1600: int, load_seconds: float) -> dict:
    full = full_size_queries(rows, SHARED / "data" / "penn-campus-gps" / "photos-full")
    if not full:
        raise SystemExit("no 12 MP originals found in ../shared/data/penn-campus-gps/photos-full")
    photos_1600 = [r for r in rows if r.split == "query" and is_photo(r)]
    collection = collection_rows(rows, {r.group for r in full})
    with (
        tempfile.TemporaryDirectory(prefix="geoloc-bench-") as tmp,
        ServerProcess(Path(tmp) / "data", models_dir, config) as server,
    ):
        print(f"ingesting {len(collection)} references through POST /references ...")
        ingestion = [
            ingest(server.client, [r for r in collection if is_photo(r)], "1600 px photos"),
            ingest(server.client, [r for r in collection if not is_photo(r)], "224 px crops"),
        ]
        floor = Floor(models_dir, get_config(config))
        print(f"/locate: {len(full)} 12 MP x {reps_full}, {len(photos_1600)} 1600 px x {reps_1600}")
        locate = [
            measure_locate(server.client, floor, full, "12 MP originals (photos-full)", reps_full),
            measure_locate(server.client, floor, photos_1600, "1600 px photos (query split)", reps_1600),
        ]
        print(f"load: 4 clients for {load_seconds:.0f} s ...")
        load = run_load(server.url, 4, load_seconds, 0.8, 3000, api_key=server.api_key, rows=rows)
    return {
        "collection_size": len(collection),
        "ingestion": [{**asdict(i), "images_per_s": i.images_per_s} for i in ingestion],
        "locate": [
            {**asdict(m), "ratio_to_floor": m.ratio_to_floor, "ratio_to_server_floor": m.ratio_to_server_floor}
            for m in locate
        ],
        "load": load.summary(),
    }


def projected(baseline_runs: list[dict], scaling: list[search_scaling.SearchFigures]) -> list[dict]:
    """Per-query time at N references: penn's measured work before the search, plus the search measured at
    N on synthetic codes of the same size (the baseline's 8,192-d floats, our 256-d floats)."""
    by = {r["config"]: r for r in baseline_runs}
    measured_base = [(f.n, f.median_ms) for f in scaling if f.mode == "float (baseline)"]
    out = []
    for n in sorted({f.n for f in scaling}):
        search = {f.mode: f.median_ms for f in scaling if f.n == n}
        row = {"n": n, "baseline_extrapolated": False}
        if "float (baseline)" not in search and measured_base:
            # Exhaustive search is linear in N: scale the largest measured baseline search.
            n0, ms0 = max(measured_base)
            search["float (baseline)"] = ms0 * n / n0
            row["baseline_extrapolated"] = True
        for name, mode in (
            (baseline_mod.BASELINE, "float (baseline)"),
            (DEFAULT_CONFIG, "float"),
            (BINARY, "two-stage"),
        ):
            if name in by and mode in search:
                ms = by[name]["ms_per_query"]
                row[name] = ms["total"] - ms.get("search", 0.0) + search[mode]
        if baseline_mod.BASELINE in row and DEFAULT_CONFIG in row:
            row["speedup"] = row[baseline_mod.BASELINE] / row[DEFAULT_CONFIG]
        if baseline_mod.BASELINE in row and BINARY in row:
            row["speedup_two_stage"] = row[baseline_mod.BASELINE] / row[BINARY]
        out.append(row)
    return out


# -- the report ----------------------------------------------------------------------------------------


def _f(x: float | None, nd: int = 1) -> str:
    return "n/a" if x is None else f"{x:,.{nd}f}"


def summary_lines(fig: dict) -> list[str]:
    s = fig["service"]
    out = []
    for m in s["locate"]:
        out.append(
            f"- /locate, {m['label']}: p50 {m['client_ms']['p50']:.0f} ms (p95 {m['client_ms']['p95']:.0f} ms) "
            f"against a floor of {m['floor_stages_ms']['total']:.0f} ms measured alone: "
            f"{m['ratio_to_floor']:.2f}x the floor; the same floor stages timed inside the server take "
            f"{m['server_floor_ms']:.0f} ms: {m['ratio_to_server_floor']:.2f}x."
        )
    runs = {r["config"]: r for r in fig["baseline"]}
    base, ours = runs.get(baseline_mod.BASELINE), runs.get(DEFAULT_CONFIG)
    if base and ours:
        b, o = base["ms_per_query"]["total"], ours["ms_per_query"]["total"]
        out.append(
            f"- Thesis-style baseline ({baseline_mod.BASELINE}) vs the default ({DEFAULT_CONFIG}) on penn-campus-gps: "
            f"R@1 {base['recall_at']['1']:.3f} vs {ours['recall_at']['1']:.3f}, R@5 {base['recall_at']['5']:.3f} vs "
            f"{ours['recall_at']['5']:.3f}; {b:.1f} vs {o:.1f} ms per query, a speed ratio of {b / o:.2f} "
            f"(the default pays for SqueezeNet); codes {base['bytes_per_reference']:,.0f} vs "
            f"{ours['bytes_per_reference']:,.0f} bytes per reference."
        )
    for p in fig["projected"][-1:]:
        if "speedup" in p:
            out.append(
                f"- At {p['n']:,} references the search dominates the baseline: {p[baseline_mod.BASELINE]:.0f}"
                f" vs {p[DEFAULT_CONFIG]:.0f} ms per query, a speed ratio of {p['speedup']:.1f} in favour of the "
                "default" + (" (baseline search extrapolated)" if p["baseline_extrapolated"] else "") + "."
            )
        if "speedup_two_stage" in p:
            out.append(
                f"- {BINARY} (two-stage: Hamming shortlist, float re-rank) at {p['n']:,} references: "
                f"{p[BINARY]:.0f} ms per query, {p['speedup_two_stage']:.1f}x the baseline's speed; see the search "
                "table for how often its top-1 agrees with the exact float search."
            )
    ing = ", ".join(f"{i['images_per_s']:.1f} images/s ({i['kind']})" for i in s["ingestion"])
    out.append(f"- Ingestion through the API: {ing}.")
    ld = s["load"]
    out.append(
        f"- Load, {ld['clients']} clients: {ld['requests_per_s']:.1f} requests/s, /locate p50 "
        f"{ld['ops'].get('/locate', {}).get('p50', float('nan')):.0f} ms, errors: {ld['errors'] or 'none'}."
    )
    return out


def render(fig: dict) -> str:
    s = fig["service"]
    L = [
        "# Benchmarks",
        "",
        f"Written by `{fig['command']}` (`make bench`) on {fig['date']}, commit {fig['commit']}, in "
        f"{fig['elapsed_min']:.1f} min.",
        f"Machine: {fig['machine']}. Server and bench share the machine; onnxruntime uses all cores, "
        "FAISS one thread per search (the service defaults).",
        "All times are medians unless marked p95/p99; ratios compare two figures from this same run. "
        "Accuracy figures are in docs/results.md (`make results`); the recalls quoted here are from this run.",
        "",
        "## Summary",
        "",
        *summary_lines(fig),
        "",
        "## /locate on a real server, stage by stage, against the floor",
        "",
        f"`geoloc serve --config {fig['config']}` on a fresh data dir holding {s['collection_size']} penn-campus-gps "
        "references (db rows minus the captures used as queries). Client time is the HTTP round trip on loopback, "
        "upload included; server stages come from the response's `timings_ms`. The floor is decode + SqueezeNet + "
        "local features alone (same code and thread settings, in the bench process), interleaved request by "
        "request with the server's /locate. The same three stages as the server times them are given too: in "
        "our runs local features came out faster inside the warm server than alone in the bench process "
        "(see the stage table; same code, same allocator settings), so the ratio to the in-server floor "
        "is the stricter measure of what /locate adds (hybrid sampling, aggregation, codes, search, HTTP).",
        "",
        "| query images | images x reps | client p50 | p95 | p99 | server total | floor alone | p50 / floor "
        "| floor stages in the server | p50 / those | top-1 within 25 m |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in s["locate"]:
        c = m["client_ms"]
        L.append(
            f"| {m['label']} | {m['n_images']} x {m['requests'] // m['n_images']} | {_f(c['p50'])} ms | "
            f"{_f(c['p95'])} ms | {_f(c['p99'])} ms | {_f(m['server_stages_ms'].get('total'))} ms | "
            f"{_f(m['floor_stages_ms']['total'])} ms | {m['ratio_to_floor']:.2f} | {_f(m['server_floor_ms'])} ms | "
            f"{m['ratio_to_server_floor']:.2f} | {m['top1_within_25m']:.0%} |"
        )
    L += ["", "Stages (median ms):", ""]
    stages = list(dict.fromkeys(k for m in s["locate"] for k in m["server_stages_ms"]))
    head = "| stage | " + " | ".join(f"{m['label']} server | floor" for m in s["locate"]) + " |"
    L += [head, "|---|" + "---|---|" * len(s["locate"])]
    for st in stages:
        cells = []
        for m in s["locate"]:
            cells += [_f(m["server_stages_ms"].get(st), 2), _f(m["floor_stages_ms"].get(st), 2)]
        L.append(f"| {st} | " + " | ".join(cells) + " |")
    L += [
        "",
        "## Ingestion through the API",
        "",
        "POST /references in batches of 8 (position in the form), the in-process worker encoding; time from the "
        "first POST to the last finished job.",
        "",
        "| images | count | seconds | images/s |",
        "|---|---|---|---|",
    ]
    for i in s["ingestion"]:
        L.append(f"| {i['kind']} | {i['images']} | {_f(i['seconds'])} | {_f(i['images_per_s'], 2)} |")
    ld = s["load"]
    L += [
        "",
        "## Load",
        "",
        f"`bench/load.py` against the same server: {ld['clients']} concurrent clients for {ld['seconds']} s, "
        f"{ld['locate_share']:.0%} /locate (penn query photos and crops) and the rest /references (distinct 480 px "
        "JPEGs cut from penn photos). Run it alone with `.venv/bin/python -m bench.load --clients 8 --seconds 120`.",
        "",
        "```",
        format_report(ld),
        "```",
        "",
        "## Thesis-style baseline against our pipelines (penn-campus-gps)",
        "",
        f"`evaluate` (as `geoloc eval`) with {fig['folds']} folds, extraction on one thread, the same run. Speed "
        "ratio = baseline time per query / this configuration's (above 1: faster than the baseline).",
        "",
        "| configuration | R@1 | R@5 | R@10 | ms/query | of which extraction | search | bytes/ref "
        "| speed vs baseline |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    runs = fig["baseline"]
    base_ms = next(r["ms_per_query"]["total"] for r in runs if r["config"] == baseline_mod.BASELINE)
    for r in runs:
        ms = r["ms_per_query"]
        extraction = sum(ms.get(k, 0.0) for k in ("decode", "local_features", "cnn", "hybrid"))
        rc = r["recall_at"]
        L.append(
            f"| {r['config']} ({r['mode']}) | {rc['1']:.3f} | {rc['5']:.3f} | {rc['10']:.3f} | {_f(ms['total'])} | "
            f"{_f(extraction)} | {_f(ms.get('search'), 3)} | {r['bytes_per_reference']:,.0f} | "
            f"{base_ms / ms['total']:.2f} |"
        )
    L += [
        "",
        f"Projected time per query at N references: the penn figures above without their search, plus the search "
        f"measured at N below ({search_scaling.BASELINE_DIM}-d floats for the baseline, 256-d floats for "
        f"{DEFAULT_CONFIG}, the two-stage search for {BINARY}).",
        "",
        f"| references | {baseline_mod.BASELINE} ms | {DEFAULT_CONFIG} ms | speed vs baseline | {BINARY} two-stage ms "
        "| speed vs baseline |",
        "|---|---|---|---|---|---|",
    ]
    for p in fig["projected"]:
        mark = " (search extrapolated linearly: does not fit in memory)" if p["baseline_extrapolated"] else ""
        L.append(
            f"| {p['n']:,} | {_f(p.get(baseline_mod.BASELINE))}{mark} | {_f(p.get(DEFAULT_CONFIG))} | "
            f"{_f(p.get('speedup'), 2)} | {_f(p.get(BINARY))} | {_f(p.get('speedup_two_stage'), 2)} |"
        )
    L += [
        "",
        "## Search at 1k to 1M references",
        "",
        search_scaling.__doc__.strip().split("\n\n")[1].replace("\n", " "),
        "",
        "| references | mode | code | median ms | bytes/ref in the index | top-1 = exact float top-1 | ms vs float |",
        "|---|---|---|---|---|---|---|",
    ]
    sc = fig["search"]
    for f in sc:
        flt = next(g["median_ms"] for g in sc if g["n"] == f["n"] and g["mode"] == "float")
        agree = "" if f["agrees_with_float_top1"] is None else f"{f['agrees_with_float_top1']:.0%}"
        L.append(
            f"| {f['n']:,} | {f['mode']} | {f['dim']} | {_f(f['median_ms'], 3)} | {f['bytes_per_ref']:,.1f} | "
            f"{agree} | {f['median_ms'] / flt:.2f} |"
        )
    L += [
        "",
        f"The baseline stops at {search_scaling.BASELINE_MAX:,} references: at 32,776 bytes each, 1M would need "
        "33 GB, more than this machine's 24 GB. Bytes per reference are the serialised FAISS index size divided "
        "by its count (8 bytes of it are the id map); the SQLite store keeps a second copy of the codes for "
        "rebuilds, and the original images.",
        "",
    ]
    return "\n".join(L)


def write_kept(out: Path, text: str) -> None:
    """Write the rendered figures, keeping what other benchmarks own as it is: everything from the first
    marked section on (bench/scale.py, bench/ingest_speed.py, bench/compare_configs.py, and their notes)."""
    old = out.read_text() if out.exists() else ""
    first = marked_sections(old)
    tail = old[old.index(first[0]) :] if first else ""
    out.write_text(text.rstrip() + ("\n\n" + tail if tail else "\n"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--sizes", default=",".join(str(n) for n in search_scaling.SIZES))
    ap.add_argument("--reps-full", type=int, default=5, help="repetitions over the 6 12 MP originals")
    ap.add_argument("--reps-1600", type=int, default=2, help="repetitions over the 1600 px query photos")
    ap.add_argument("--load-seconds", type=float, default=30)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks.md")
    ap.add_argument("--json", type=Path, default=REPO / "out" / "bench" / "benchmarks.json")
    ap.add_argument("--render-only", action="store_true", help="rewrite --out from the figures in --json")
    args = ap.parse_args()
    if args.render_only:
        fig = json.loads(args.json.read_text())
        scaling = [search_scaling.SearchFigures(**f) for f in fig["search"]]
        fig["projected"] = projected(fig["baseline"], scaling)
        write_kept(args.out, render(fig))
        print(f"rendered {args.out} from {args.json}")
        return
    os.environ.setdefault("GEOLOC_FAISS_THREADS", "1")
    t0 = time.time()
    rows = penn_rows()
    fig = {
        "command": " ".join([COMMAND, *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "commit": _git_commit(),
        "machine": machine(),
        "config": args.config,
        "folds": args.folds,
    }
    fig["service"] = service_figures(
        rows, args.models_dir, args.config, args.reps_full, args.reps_1600, args.load_seconds
    )
    print(f"/locate of {args.config} against {COMPARED}, interleaved on two servers ...")
    fig["configs"] = compare_configs.run(args.models_dir, [args.config, COMPARED], reps=2)
    fig["baseline"] = baseline_mod.run(MANIFEST, args.models_dir, args.folds)
    sizes = tuple(int(x) for x in args.sizes.split(","))
    scaling = search_scaling.run(sizes)
    fig["search"] = [asdict(f) for f in scaling]
    fig["projected"] = projected(fig["baseline"], scaling)
    fig["elapsed_min"] = (time.time() - t0) / 60
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(fig, indent=1))
    write_kept(args.out, render(fig))
    write_section("configs", compare_configs.render(fig["configs"], fig["command"]), args.out)
    print(f"wrote {args.out} and {args.json} in {fig['elapsed_min']:.1f} min")


if __name__ == "__main__":
    main()
