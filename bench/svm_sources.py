"""The SVM bank by training source, side by side (issue 14): print the markdown table for docs/RESULTS.md.

Reads the JSON of ``geoloc eval --json`` runs named ``bank-<source>-<selection>.json`` (source: off, train,
collection; selection: positive, negative) from one folder, so the figures in the table are exactly those
runs; the commands that produce them are printed above the table.

    python bench/svm_sources.py --dir out/eval
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RUNS = [
    ("off", "all", "none (every feature)"),
    ("train", "positive", "16 training captures (train rows)"),
    ("train", "negative", "16 training captures (train rows)"),
    ("collection", "positive", "the collection (fold's db rows + train rows)"),
    ("collection", "negative", "the collection (fold's db rows + train rows)"),
]

COMMAND = (
    "/work/main/.venv/bin/python -m app.cli eval --manifest data/manifests/penn-campus-gps.csv --config hybrid "
    "--folds 5 --models-dir models --cache out/cache"
)


def _path(folder: Path, source: str, selection: str) -> Path:
    return folder / ("bank-off.json" if source == "off" else f"bank-{source}-{selection}.json")


def command(source: str, selection: str) -> str:
    if source == "off":
        return f"{COMMAND} --json out/eval/bank-off.json"
    # One BLAS thread: how the bank rows were run on the shared machine (docs/RESULTS.md, "The runs").
    return (
        f"OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 {COMMAND} --svm-bank {selection} "
        f"--svm-bank-source {source} --json out/eval/bank-{source}-{selection}.json"
    )


def row(source: str, selection: str, label: str, r: dict, base_r1: float) -> str:
    rec, ms, bank = r["recall_at"], r["ms_per_query"], r["svm_bank"]
    kept = bank["kept_fraction_median"]
    folds = bank.get("folds") or []
    fractions = ", ".join(str(f["chosen_keep_fraction"]) for f in folds) or "-"
    train_s = [f["train_seconds"] for f in folds]
    photos = [f["training"]["training_photos"] for f in folds]
    return (
        f"| {label} | {selection} | {'1.00' if kept is None else f'{kept:.2f}'} | {fractions} | "
        f"{rec['1']:.3f} ({rec['1'] - base_r1:+.3f}) | {rec['5']:.3f} | {rec['10']:.3f} | "
        f"{ms.get('svm', 0.0):.1f} | {ms['total']:.1f} | "
        + (f"{min(train_s):.0f}-{max(train_s):.0f} s, {min(photos)}-{max(photos)} labelled photos" if folds else "-")
        + " |"
    )


def table(folder: Path) -> str:
    paths = {(s, sel): _path(folder, s, sel) for s, sel, _ in RUNS}
    results = {k: json.loads(p.read_text()) for k, p in paths.items() if p.exists()}
    base = results[("off", "all")]["recall_at"]["1"]
    lines = [
        "```sh",
        *[command(s, sel) for s, sel, _ in RUNS],
        "```",
        "",
        "| bank trained on | features aggregated | kept (median) | keep fraction per fold | R@1 (vs none) | R@5 | "
        "R@10 | svm ms | total ms/query | bank training per fold (fastest-slowest) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *[
            row(s, sel, label, results[(s, sel)], base)
            if (s, sel) in results
            else f"| {label} | {sel} | not measured ({paths[(s, sel)].name} missing) |" + " |" * 7
            for s, sel, label in RUNS
        ],
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, default=Path("out/eval"))
    print(table(ap.parse_args().dir))


if __name__ == "__main__":
    main()
