"""R@1 of fusion rules replayed on the verified pairs a ``geoloc eval --json`` run recorded, paired against its
unverified answers.

    .venv/bin/python -m bench.fusion_replay [--recorded-floor 12] out/eval/sv-5fold.json out/eval/sv-40.json

Why: with stored XFeat verification (``lite2-hybrid-384-sv``) R@1 fell below the same queries unverified. A
verified ``geoloc eval`` run records, per query, the retrieval order (reference, global score, whether
it lies within the run's radius) and each verified candidate's matches and H / F inliers
(``queries[].verification``). Which candidate comes first depends on nothing else, so a fusion rule's R@1 on
those queries is replayed without extracting or matching again, exactly but for one thing: a candidate the
run's adaptive stop left unverified stays so (a rule whose stop reads a higher floor would have verified it).
The replay of the rule the run was made with (``--recorded-floor``, default the profile's) must give the
run's own R@1: printed as a check. Rules:

- ``floor=F``: ``matchers.fusion.fused_score`` with the inlier floor ``F`` (the run's own is marked);
- ``lofo-pQ``: the floor per fold set to the Q-th percentile of the inliers of the verified candidates that
  were wrong (beyond the radius) in the other folds: the chance level of the candidates retrieval actually
  confuses, not of random far pairs, and chosen without the fold's own queries (one fold: no replay);
- ``switch=T,R``: the global first candidate stays unless a verified one has at least ``T`` inliers and at
  least ``R`` times the first's; then the one with most inliers comes first.

Paired against the unverified first candidate: wins (became right), losses (became wrong), sign test.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from app.engine.matchers.fusion import fused_score
from bench.paired_r1 import sign_test

#: One query's verified head: (global score, within the radius, inliers or None when not verified) in
#: retrieval order.
Head = list[tuple[float, bool, int | None]]
Rule = Callable[[Head, int], int]


def chosen_inliers(pair: list | None) -> int | None:
    """The chosen model's inliers from a recorded pair ``[matches, H inliers, F inliers, confidence]``: the rule
    of ``matchers.geometry.fit_geometry`` (H when it explains 80 % of F's inliers)."""
    if pair is None:
        return None
    _, h, f, _ = pair
    if f == 0:
        return 0
    return h if h >= 0.8 * f else f


def heads(run: dict) -> list[tuple[int, Head]]:
    """(fold, head) per query of a verified run."""
    out = []
    for q in run["queries"]:
        v = q.get("verification")
        if v is None:
            raise SystemExit("the run recorded no verification: run geoloc eval with a stored-features config")
        pairs = v["pairs"]
        out.append(
            (int(q.get("fold") or 0), [(s, bool(ok), chosen_inliers(pairs.get(str(r)))) for r, s, ok in v["retrieval"]])
        )
    return out


def by_floor(floor: float) -> Rule:
    def first(head: Head, fold: int) -> int:
        fused = [fused_score(s, n or 0, floor=floor) for s, _, n in head]
        return int(np.argmax(fused))  # the first of equal scores: retrieval order, as order_by_verification

    return first


def lofo_floor(runs: list[tuple[int, Head]], q: float) -> tuple[Rule, dict[int, float]]:
    floors = {}
    for fold in {f for f, _ in runs}:
        wrong = [n for f, h in runs if f != fold for _, ok, n in h if n is not None and not ok]
        floors[fold] = float(np.percentile(wrong, q)) if wrong else float("nan")

    def first(head: Head, fold: int) -> int:
        return by_floor(floors[fold])(head, fold)

    return first, floors


def by_switch(min_inliers: int, ratio: float) -> Rule:
    def first(head: Head, fold: int) -> int:
        top = head[0][2] or 0
        best = max(range(len(head)), key=lambda i: (head[i][2] or 0, -i))
        n = head[best][2] or 0
        return best if n >= min_inliers and n >= ratio * max(top, 1) else 0

    return first


def replay(runs: list[tuple[int, Head]], rule: Rule) -> dict:
    folds = [f for f, _ in runs]
    base = [h[0][1] for _, h in runs]
    got = [h[rule(h, f)][1] for f, h in runs]

    def r1(hits: list[bool]) -> float:  # as geoloc eval reports it: the mean of the folds' R@1
        return float(np.mean([np.mean([x for x, g in zip(hits, folds, strict=True) if g == f]) for f in set(folds)]))

    wins = sum(g and not b for g, b in zip(got, base, strict=True))
    losses = sum(b and not g for g, b in zip(got, base, strict=True))
    return {
        "r1": round(r1(got), 3),
        "unverified_r1": round(r1(base), 3),
        "wins": wins,
        "losses": losses,
        "p": round(sign_test(wins, losses), 3),
    }


def rules(runs: list[tuple[int, Head]], recorded_floor: int) -> list[tuple[str, Rule]]:
    out: list[tuple[str, Rule]] = [(f"floor={recorded_floor} (the run's)", by_floor(recorded_floor))]
    out += [(f"floor={f}", by_floor(f)) for f in (12, 16, 20, 25, 30, 40, 48, 60) if f != recorded_floor]
    if len({f for f, _ in runs}) > 1:
        for q in (90, 95, 99):
            rule, floors = lofo_floor(runs, q)
            shown = ", ".join(f"{floors[k]:.0f}" for k in sorted(floors))
            out.append((f"lofo-p{q} (floors {shown})", rule))
    out += [(f"switch={t},{r:g}", by_switch(t, r)) for t in (20, 30, 40) for r in (2.0, 3.0)]
    return out


def recorded_r1(run: dict) -> tuple[float, float]:
    """The run's own R@1, verified and not: a finished run's, or the mean of the folds a ``.partial.json`` holds."""
    if "recall_at" in run:
        return run["recall_at"]["1"], run["without_rerank"]["recall_at"]["1"]
    n = len(run["recall_at_per_fold"])
    plain = run["without_rerank_recall_at_per_fold"][:n]
    return float(np.mean([f["1"] for f in run["recall_at_per_fold"]])), float(np.mean([f["1"] for f in plain]))


def main(argv: Sequence[str] | None = None) -> None:
    from app.engine.stored_profiles import get_profile

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="geoloc eval --json of a verified configuration")
    ap.add_argument("--recorded-floor", type=int, help="the floor the runs were made with; default the profile's")
    a = ap.parse_args(argv)
    recorded = a.recorded_floor if a.recorded_floor is not None else get_profile("xfeat-640-n900").fusion_floor
    for path in a.runs:
        run = json.loads(path.read_text())
        if "recall_at" not in run:  # a .partial.json: only the folds whose R@1 it holds
            run["queries"] = [q for q in run["queries"] if (q.get("fold") or 0) < len(run["recall_at_per_fold"])]
        hs = heads(run)
        wrong = [n for _, h in hs for _, ok, n in h if n is not None and not ok]
        right = [n for _, h in hs for _, ok, n in h if n is not None and ok]
        verified, unverified = recorded_r1(run)
        print(
            f"{path.name}: {len(hs)} queries, R@1 recorded {verified:.3f} (verified) / "
            f"{unverified:.3f} (unverified); verified candidates: "
            f"{len(right)} right (inliers p50 {np.median(right):.0f}, p90 {np.percentile(right, 90):.0f}), "
            f"{len(wrong)} wrong (p50 {np.median(wrong):.0f}, p90 {np.percentile(wrong, 90):.0f}, "
            f"p95 {np.percentile(wrong, 95):.0f}, p99 {np.percentile(wrong, 99):.0f})"
        )
        print("| rule | R@1 | unverified R@1 | wins | losses | sign test p |")
        print("|---|---|---|---|---|---|")
        for name, rule in rules(hs, recorded):
            r = replay(hs, rule)
            print(f"| {name} | {r['r1']:.3f} | {r['unverified_r1']:.3f} | {r['wins']} | {r['losses']} | {r['p']} |")


if __name__ == "__main__":
    main()
