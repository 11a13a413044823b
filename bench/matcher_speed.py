"""The cost of verification per pair and per query: ``xfeat-lighterglue`` against ``sift-mnn``, interleaved
query by query in one process.

Why interleaved: this machine is shared and its load changes by the minute, so each query is verified by
both matchers back to back, in alternating order, and the figures that matter are their ratios. Per query
(a penn photo and the ``K`` photos after it as candidates, all decoded from their files as the core does):

- ``per query``: ``app.usecases.locate.verify_candidate_pairs``, what /locate's rerank costs: the query's features,
  each candidate's features recomputed from its stored image, then the matches and the geometry
  (LighterGlue with its default ``BATCH`` pairs per network run);
- ``features``: one image's features (decode included), the part of a pair that storing keypoints at
  ingestion would remove;
- ``match``: matching plus geometry per pair on precomputed features; for LighterGlue pair by pair (one
  network run each) and batched (the K pairs in one run, padded, with masks).

    python -m bench.matcher_speed [--queries 8] [--k 10] [--keypoints 512] [--threads 2] [--write-docs]

``--write-docs`` writes the table into the "matcher" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers.lighterglue import LighterGlueMatcher
from app.engine.matchers.sift_mnn import SiftMnnMatcher
from app.engine.models.ort import set_session_threads
from app.usecases.locate import verify_candidate_pairs
from bench.common import REPO, machine, median_ms, write_section


class _Files:
    def __init__(self, paths: list[Path]):
        self.paths = paths

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.paths[ref_id].read_bytes()


def _ms(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return (time.perf_counter() - t0) * 1000, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=Path, default=REPO.parent / "shared" / "data" / "penn-campus-gps" / "photos")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--queries", type=int, default=8)
    ap.add_argument("--k", type=int, default=10, help="candidates verified per query")
    ap.add_argument("--keypoints", type=int, default=0, help="LighterGlue keypoints (0: the matcher's default)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime threads (Settings.ort_threads)")
    ap.add_argument("--write-docs", action="store_true", help="write the matcher section of docs/benchmarks.md")
    args = ap.parse_args()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load_before = os.getloadavg()[0]
    set_session_threads(args.threads)

    photos = sorted(args.photos.glob("*.jpg"))
    refs = _Files(photos)
    kw = {"max_keypoints": args.keypoints} if args.keypoints else {}
    matchers = {"sift-mnn": SiftMnnMatcher(), "xfeat-lighterglue": LighterGlueMatcher(args.models_dir, **kw)}
    matchers["xfeat-lighterglue"].load()
    limits = ImageLimits()
    step = max(1, len(photos) // args.queries)
    queries = [q for q in range(0, len(photos), step)][: args.queries]
    cand = {q: [(q + 1 + j) % len(photos) for j in range(args.k)] for q in queries}
    rgb0 = load_image(photos[0].read_bytes()).rgb
    for m in matchers.values():  # warm-up: sessions, allocator
        verify_candidate_pairs(rgb0, cand[queries[0]][:2], refs, limits, m)

    t: dict[str, dict[str, list[float]]] = {n: {"query": [], "features": [], "match": []} for n in matchers}
    t["xfeat-lighterglue"]["match batched"] = []
    for n, q in enumerate(queries):
        rgb = load_image(photos[q].read_bytes()).rgb
        order = list(matchers) if n % 2 == 0 else list(reversed(matchers))
        for name in order:
            m = matchers[name]
            ms, _ = _ms(lambda m=m, rgb=rgb, q=q: verify_candidate_pairs(rgb, cand[q], refs, limits, m))
            t[name]["query"].append(ms)
            feats = []
            for c in cand[q]:
                ms, f = _ms(lambda c=c, m=m: m.features(load_image(refs.image_bytes(c), limits).rgb))
                t[name]["features"].append(ms)
                feats.append(f)
            qf = m.features(rgb)
            if name == "xfeat-lighterglue":
                ms, _ = _ms(lambda m=m, qf=qf, feats=feats: [m.match(qf, f) for f in feats])
                t[name]["match"].append(ms / len(feats))
                batched = LighterGlueMatcher(args.models_dir, batch=len(feats), **kw)
                batched.xfeat, batched.glue = m.xfeat, m.glue  # the same sessions
                ms, _ = _ms(lambda b=batched, qf=qf, feats=feats: b.match_many(qf, feats))
                t[name]["match batched"].append(ms / len(feats))
            else:
                ms, _ = _ms(lambda m=m, qf=qf, feats=feats: [m.match(qf, f) for f in feats])
                t[name]["match"].append(ms / len(feats))

    lg = matchers["xfeat-lighterglue"]
    s, g = t["sift-mnn"], t["xfeat-lighterglue"]
    ratios = [a / b for a, b in zip(g["query"], s["query"], strict=True)]
    lines = [
        f"`.venv/bin/python -m bench.matcher_speed --queries {args.queries} --k {args.k}"
        f"{f' --keypoints {args.keypoints}' if args.keypoints else ''} --threads {args.threads}` ({started}, "
        f"{machine()}; load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after): "
        f"{len(queries)} penn query photos, each verified against the {args.k} photos after it, by both matchers "
        f"back to back in alternating order. LighterGlue on {lg.max_keypoints} XFeat keypoints at {lg.long_side} "
        "px, one pair per network run; sift-mnn on RootSIFT at 800 px. Medians, ms.",
        "",
        "| matcher | per query (K candidates) | features per image (decode included) | match + geometry per pair |",
        "|---|---|---|---|",
    ]
    for name in matchers:
        r = t[name]
        lines.append(
            f"| {name} | {median_ms(r['query']):.0f} | {median_ms(r['features']):.0f} | {median_ms(r['match']):.0f} |"
        )
    lines += [
        "",
        f"Ratios xfeat-lighterglue / sift-mnn: per query {median_ms(ratios):.2f} (median of per-query ratios), "
        f"features {median_ms(g['features']) / median_ms(s['features']):.2f}, match per pair "
        f"{median_ms(g['match']) / median_ms(s['match']):.2f}. LighterGlue with the K pairs of a query batched "
        f"into one run (padded, masks): {median_ms(g['match batched']):.0f} ms per pair against "
        f"{median_ms(g['match']):.0f} pair by pair.",
    ]
    text = "\n".join(lines)
    print(text)
    if args.write_docs:
        write_section("matcher", "## Learned matching: verification cost per pair and per query\n\n" + text)


if __name__ == "__main__":
    main()
