"""The confident answers' stated radius against the constant rule's, on the same queries of one evaluation.

    python -m bench.stated_radius out/eval/radius-5fold.json

Why: ``geoloc eval`` reports how the radius it served holds (``answers.radius_coverage``); whether that is
better than today's constant rule (farthest fused candidate + 40 m, ``app.engine.estimate.fuse_position``)
needs that rule's radius on the very same answers. The rule reads only the fused candidates, which the
evaluation records (the first 10 of each query's ranked candidates, without verification), so it is
recomputed here exactly; the weakest quartile is the same one as the evaluation's (lowest ``answer_p``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m
from app.usecases.locate import ESTIMATE_CANDIDATES


def compare(report: dict) -> dict[str, dict]:
    """Per rule (``stated``: the radius the evaluation served; ``constant``: today's rule; ``guarded``: the
    larger of the two, what ``Calibration.stated_radius`` serves since the conformal radii alone held for 72 %
    of penn's confident answers; exact whenever ``stated`` is the bare conformal radius): the share of
    confident answers whose truth lies within the radius, overall and in the weakest quartile, and the median
    radius."""
    rows = []
    for q in report["queries"]:
        e = q.get("estimate")
        if not e or not e["confident"]:
            continue
        c = np.array(q["candidates"][:ESTIMATE_CANDIDATES], float)
        constant = fuse_position(c[:, 0], c[:, 1], c[:, 2]).radius_m
        error = float(haversine_m(q["lat"], q["lon"], e["lat"], e["lon"]))
        strength = e["answer_p"] if e.get("answer_p") is not None else e["confidence"]
        rows.append((strength, error, e.get("radius_m", np.nan), constant))  # a report from before: none
    if not rows:
        return {}
    strength, error, stated, constant = (np.array(x, float) for x in zip(*rows, strict=True))
    weakest = np.argsort(strength, kind="stable")[: max(1, len(rows) // 4)]
    out = {}
    rules = (("stated", stated), ("constant", constant), ("guarded", np.maximum(stated, constant)))
    for name, radius in rules:
        if np.isnan(radius).any():
            continue
        held = error <= radius
        out[name] = {
            "confident": len(rows),
            "coverage": float(held.mean()),
            "coverage_weakest_quartile": float(held[weakest].mean()),
            "median_radius_m": float(np.median(radius)),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="a `geoloc eval --json` report (without --rerank)")
    report = json.loads(ap.parse_args().report.read_text())
    if report.get("rerank"):
        raise SystemExit("a --rerank report's fused candidates are verified: the constant rule cannot be recomputed")
    for name, f in compare(report).items():
        print(
            f"{name:8s} confident {f['confident']}: truth within the radius {f['coverage']:.1%} (weakest quartile "
            f"{f['coverage_weakest_quartile']:.1%}), median radius {f['median_radius_m']:.0f} m"
        )


if __name__ == "__main__":
    main()
