"""Stored local features for verification: which form to store, what it costs, and
whether verifying against it separates the right place from the wrong one as well as re-extracting does.

For each candidate form (``PROFILES``: RootSIFT from the pipeline's own decode at its own 384 px, or at
800 / 1,024 px, keeping the strongest N keypoints; XFeat's 64-d descriptors), on the 40 whole-photo queries
of ``penn-photos-40.csv`` against its 341 references:

(a) bytes per reference (``app.engine.stored_features``: uint16 positions, uint8 descriptors), over the
    1600 px photos (the crops are smaller) and the time to extract them from the decoded reference;
(b) the time to verify a query against its top K global candidates from STORED features (records decoded
    from bytes, one BLAS product, USAC: ``app.engine.stored_verification``), against today's rerank, which
    decodes and re-extracts every candidate (``app.usecases.locate.verify_candidate_pairs``, ``sift-mnn``), measured
    interleaved per query, with the pipeline's own time per query (decode, extract, encode, search) as
    the "without verification" baseline;
(c) inliers of pairs within 25 m against pairs over 150 m apart (median, p90) and of the top-1 global
    candidate when it is right (within 25 m) or wrong, and R@1 after re-ordering by ``matchers.fusion.fused_score``;
(d) the query's features from the pipeline's own extraction (RootSIFT at 384 px, 1,000 keypoints) against
    each reference form, instead of extracting the query at the form's size;
and the adaptive stop (``stop_margin``): candidates verified, time, R@1.

    nice -n 10 .venv/bin/python -m bench.stored_verification            # prints the figures
    nice -n 10 .venv/bin/python -m bench.stored_verification --write    # and writes docs/benchmarks.md

Global candidates are the pipeline's float codes ranked by inner product (what the flat float index
returns). Timings: one process on a shared 2-core machine; medians.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine import stored_features as sf
from app.engine.configs import DEFAULT_CONFIG
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits, load_image
from app.engine.local_features import RootSift
from app.engine.matchers.fusion import fused_score
from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.pipeline import Pipeline, load_pipeline
from app.engine.registry import Kind, create
from app.engine.stored_verification import Settings, verify_stored
from app.evaluation.evaluate import RowReferences
from app.manifests import read_manifest
from app.usecases.locate import verify_candidate_pairs
from bench.common import REPO, machine, write_section

MANIFEST = Path("/work/shared/manifests/penn-photos-40.csv")
BUDGET_BYTES = 64 * 1024
LIMITS = ImageLimits().stored()


@dataclass(frozen=True)
class Profile:
    """One stored form: the extractor, on which decode, at which long side, keeping how many keypoints."""

    name: str
    long_side: int
    max_keypoints: int
    decode: str = "pipeline"  # "pipeline": the encoder's own decode; "full": the image at full size
    kind: str = "rootsift"
    pca_dim: int = 0  # RootSIFT projected on this many principal directions (uncentred: stays in [-1, 1])


PROFILES = [
    Profile("rootsift-384-n480 (pipeline's own)", 384, 480),
    Profile("rootsift-800-n480", 800, 480),
    Profile("rootsift-800-n1500 (today's rerank)", 800, 1500),
    Profile("rootsift-1024-n480", 1024, 480, "full"),
    Profile("rootsift-1024-n2000", 1024, 2000, "full"),
    Profile("xfeat-640-n900", 640, 900, "pipeline", "xfeat"),
    Profile("xfeat-512-n900", 512, 900, "pipeline", "xfeat"),  # smaller inputs: the ingestion-rate knob
    Profile("xfeat-448-n900", 448, 900, "pipeline", "xfeat"),
    Profile("rootsift-800-n1500-pca32", 800, 1500, pca_dim=32),
    Profile("rootsift-800-n1500-pca24", 800, 1500, pca_dim=24),
]


def _basis(descs: list[np.ndarray], dim: int) -> np.ndarray:
    """(128, dim) orthonormal directions of most energy (uncentred PCA: projections of unit RootSIFT stay in
    [-1, 1], the stored form's signed range)."""
    d = np.concatenate([x for x in descs if len(x)])
    d = d[np.random.default_rng(0).permutation(len(d))[:50_000]]
    _, _, vt = np.linalg.svd(d, full_matrices=False)
    return np.ascontiguousarray(vt[:dim].T, np.float32)


def extractor(p: Profile, models_dir: Path) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, int, int]]:
    """rgb -> (pixel positions, float descriptors, width, height) of the image the extractor saw."""
    if p.kind == "xfeat":
        from app.engine.models.xfeat import XFeat

        net = XFeat.from_models_dir(models_dir)
        net.load()

        def run_xfeat(rgb: np.ndarray):
            h, w = rgb.shape[:2]
            s = min(1.0, p.long_side / max(h, w))
            small = rgb if s == 1 else _resize(rgb, s)
            out = net.detect_and_compute(small, top_k=p.max_keypoints)
            return out.keypoints, out.descriptors, small.shape[1], small.shape[0]

        return run_xfeat
    rs = RootSift(max_keypoints=p.max_keypoints, long_side=p.long_side)

    def run_sift(rgb: np.ndarray):
        f = rs(rgb)
        h, w = rgb.shape[:2]
        s = p.long_side / max(h, w)
        if s < 1:
            w, h = round(w * s), round(h * s)
        return f.xy * np.array([w, h], np.float32), f.descriptors, w, h

    return run_sift


def _resize(rgb: np.ndarray, s: float) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    return cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


def _pct(a, q) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def run(manifest: Path, k: int, profiles: list[Profile], max_queries: int | None) -> str:
    rows = read_manifest(manifest)
    queries = [i for i, r in enumerate(rows) if r.split == "query"][:max_queries]
    db = [i for i, r in enumerate(rows) if r.split == "db"]
    models_dir = REPO / "models"
    pipe = load_pipeline(models_dir, DEFAULT_CONFIG)
    data = {i: rows[i].image.read_bytes() for i in queries + db}
    lat = np.array([r.lat for r in rows])
    lon = np.array([r.lon for r in rows])

    # -- the pipeline: decodes, its own RootSIFT (384 px), codes; the global-only time per query ---------------
    decoded: dict[int, np.ndarray] = {}
    codes: dict[int, np.ndarray] = {}
    own: dict[int, PixelFeatures] = {}
    global_ms: list[float] = []
    for i in queries + db:
        t0 = time.perf_counter()
        img = pipe.decode(data[i], LIMITS)
        f = pipe.extract(img.rgb)
        c = pipe.encode_features(f, pipe.select(f) if i in queries else None)
        if i in queries:
            global_ms.append((time.perf_counter() - t0) * 1000)
        decoded[i] = img.rgb
        codes[i] = c.float_
        own[i] = _own_features(pipe, img.rgb, f)
    db_codes = np.stack([codes[i] for i in db])
    ranked: dict[int, tuple[list[int], list[float]]] = {}
    for q in queries:
        s = db_codes @ codes[q]
        order = np.argsort(-s, kind="stable")[:k]
        ranked[q] = ([db[j] for j in order], [float(s[j]) for j in order])

    def dist(a: int, b: int) -> float:
        return float(haversine_m(lat[a], lon[a], lat[b], lon[b]))

    # Pairs of whole photos (what a user's collection holds; the 224 px crops have few features at any size)
    rng = np.random.default_rng(0)
    db_photos = [j for j in db if rows[j].image.parent.name == "photos"]
    near_pairs, far_pairs = [], []
    for q in queries:
        d = np.array([dist(q, j) for j in db_photos])
        near_pairs += [(q, db_photos[j]) for j in np.argsort(d)[:10] if d[j] <= 25]
        far = [db_photos[j] for j in np.flatnonzero(d > 150)]
        far_pairs += [(q, j) for j in rng.choice(far, min(10, len(far)), replace=False)]
    right1 = {q: dist(q, ranked[q][0][0]) <= 25 for q in queries}
    r1_global = np.mean(list(right1.values()))

    # -- today's rerank: re-extract every candidate (timed per query) ----------------------------------------
    matcher = create(Kind.MATCHER, "sift-mnn")
    refs = RowReferences(rows, db)
    today_ms = []
    for q in queries:
        rgb = load_image(data[q], LIMITS).rgb  # /locate hands the rerank the query's decoded image
        t0 = time.perf_counter()
        verify_candidate_pairs(rgb, ranked[q][0], refs, ImageLimits(), matcher)
        today_ms.append((time.perf_counter() - t0) * 1000)

    lines = [
        f"Machine: {machine()}; load shared with other sessions. `{manifest.name}`: {len(queries)} whole-photo "
        f"queries, {len(db)} references ({sum(rows[i].image.parent.name == 'photos' for i in db)} photos, the "
        f"rest 224 px crops); global candidates: `{DEFAULT_CONFIG}` float codes; K = {k}. "
        f"Pairs, whole photos only: {len(near_pairs)} within 25 m (up to the 10 nearest reference photos of each "
        f"query), {len(far_pairs)} over 150 m (10 random per query). Global R@1 {r1_global:.3f}.",
        "",
        f"Per query without verification (pipeline decode + extract + encode, search excluded): "
        f"**{np.median(global_ms):.0f} ms** median. Today's rerank (decode and re-extract the {k} candidates, "
        f"RootSIFT 800 px 1,500 keypoints, match, H-or-F): **{np.median(today_ms):.0f} ms** median, p90 "
        f"{_pct(today_ms, 90):.0f} ms.",
        "",
        "| stored form | bytes/ref photos (median, max) | crops (median) | fits 64 KB "
        "| extract ms/ref (photo, median) | verify K ms (median, p90) | vs today | /locate x (est.) "
        "| near inliers p50 / p90 | far p50 / p90 | top-1 right / wrong (median) | R@1 fused "
        "| query = pipeline's 384: near / far p50, p90 far, R@1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    early: list[str] = []
    for p in profiles:
        ext = extractor(p, models_dir)
        # XFeat's descriptors are matched as its upstream matcher does (mutual NN, cosine > 0.82, no ratio)
        settings = Settings(ratio=None, min_cos=0.82) if p.kind == "xfeat" else Settings()
        stored: dict[int, bytes] = {}
        q_feats: dict[int, PixelFeatures] = {}
        ext_ms = []
        raw = {}
        for i in queries + db:
            rgb = decoded[i] if p.decode == "pipeline" else load_image(data[i], LIMITS).rgb
            t0 = time.perf_counter()
            raw[i] = ext(rgb)
            if rows[i].image.parent.name == "photos":
                ext_ms.append((time.perf_counter() - t0) * 1000)
        kind = p.kind
        if p.pca_dim:  # fitted on the reference crops' descriptors, applied to everything
            basis = _basis([raw[i][1] for i in db if rows[i].image.parent.name != "photos"], p.pca_dim)
            raw = {i: (xy, desc @ basis, w, h) for i, (xy, desc, w, h) in raw.items()}
            kind = "rootsift-pca"
        for i, (xy, desc, w, h) in raw.items():
            if i in queries:
                q_feats[i] = PixelFeatures(np.asarray(xy, np.float32), np.asarray(desc, np.float32))
            else:
                stored[i] = sf.encode(sf.from_pixels(xy, desc, w, h, kind))
        photos = [len(stored[i]) for i in db if rows[i].image.parent.name == "photos"]
        crops = [len(stored[i]) for i in db if rows[i].image.parent.name != "photos"]

        def verify_pairs(pairs, query_feats, stored=stored, settings=settings):
            got = {}
            for q, j in pairs:
                v = verify_stored(query_feats[q], [sf.decode(stored[j])], settings=settings).verifications[0]
                got[(q, j)] = 0 if v is None else v.inliers
            return got

        verify_ms, top1, fused_right = [], {}, []
        for q in queries:
            ids, scores = ranked[q]
            t0 = time.perf_counter()
            # bytes -> records -> verdicts, as /locate would after reading the K files
            out = verify_stored(q_feats[q], [sf.decode(stored[j]) for j in ids], settings=settings)
            verify_ms.append((time.perf_counter() - t0) * 1000)
            inl = [0 if v is None else v.inliers for v in out.verifications]
            top1[q] = inl[0]
            best = max(range(len(ids)), key=lambda n: (fused_score(scores[n], inl[n]), -n))
            fused_right.append(dist(q, ids[best]) <= 25)
        near = list(verify_pairs(near_pairs, q_feats).values())
        far = list(verify_pairs(far_pairs, q_feats).values())
        right = [top1[q] for q in queries if right1[q]]
        wrong = [top1[q] for q in queries if not right1[q]]
        d_cols = "(same)"
        if p.kind == "rootsift" and not p.pca_dim:
            near_o = list(verify_pairs(near_pairs, own).values())
            far_o = list(verify_pairs(far_pairs, own).values())
            r1_own = []
            for q in queries:
                ids, scores = ranked[q]
                out = verify_stored(own[q], [sf.decode(stored[j]) for j in ids])
                inl = [0 if v is None else v.inliers for v in out.verifications]
                best = max(range(len(ids)), key=lambda n: (fused_score(scores[n], inl[n]), -n))
                r1_own.append(dist(q, ids[best]) <= 25)
            d_cols = f"{np.median(near_o):.0f} / {np.median(far_o):.0f}, {_pct(far_o, 90):.0f}, {np.mean(r1_own):.3f}"
        # /locate with verification over without: the query's extraction at this form's size (none when it
        # is the pipeline's own) plus verifying K, over the pipeline's time per query.
        added = 0.0 if p.long_side == 384 and p.decode == "pipeline" and p.kind == "rootsift" else np.median(ext_ms)
        locate_x = (np.median(global_ms) + added + np.median(verify_ms)) / np.median(global_ms)
        lines.append(
            f"| {p.name} | {np.median(photos) / 1024:.1f} KB, {max(photos) / 1024:.1f} KB | "
            f"{np.median(crops) / 1024:.1f} KB | {'yes' if max(photos) <= BUDGET_BYTES else 'no'} | "
            f"{np.median(ext_ms):.0f} | {np.median(verify_ms):.0f}, {_pct(verify_ms, 90):.0f} | "
            f"{np.median(verify_ms) / np.median(today_ms):.2f}x | {locate_x:.2f}x | "
            f"{np.median(near):.0f} / {_pct(near, 90):.0f} | "
            f"{np.median(far):.0f} / {_pct(far, 90):.0f} | {np.median(right) if right else float('nan'):.0f} / "
            f"{np.median(wrong) if wrong else float('nan'):.0f} | {np.mean(fused_right):.3f} | {d_cols} |"
        )
        print(lines[-1], flush=True)
        early += _early_stop(p, q_feats, stored, ranked, queries, dist, settings)
    lines += [
        "",
        "Adaptive stop (`stop_margin`: stop once the best fused score is at least the next candidate's global "
        "score plus the margin; 0.5 = the fusion weight, which provably never changes the first candidate):",
        "",
        "| stored form | stop margin | candidates verified (mean) | verify ms (median) | R@1 fused |",
        "|---|---|---|---|---|",
        *early,
    ]
    return "\n".join(lines)


def _own_features(pipe: Pipeline, rgb: np.ndarray, f) -> PixelFeatures:
    """The pipeline's own local features (its RootSIFT, before the hybrid join) in pixels of its resize."""
    ls = pipe.config.local_long_side
    h, w = rgb.shape[:2]
    s = ls / max(h, w)
    if s < 1:
        w, h = round(w * s), round(h * s)
    raw = RootSift(max_keypoints=pipe.config.max_keypoints, long_side=ls)(rgb)  # f.local is the hybrid join
    return PixelFeatures(raw.xy * np.array([w, h], np.float32), raw.descriptors)


def _early_stop(p, q_feats, stored, ranked, queries, dist, settings: Settings) -> list[str]:
    out = []
    for margin in (None, 0.5, 0.25):
        n_ver, ms, right = [], [], []
        for q in queries:
            ids, scores = ranked[q]
            t0 = time.perf_counter()
            res = verify_stored(q_feats[q], [sf.decode(stored[j]) for j in ids], scores, settings, margin)
            ms.append((time.perf_counter() - t0) * 1000)
            n_ver.append(res.stopped_after or len(ids))
            inl = [0 if v is None else v.inliers for v in res.verifications]
            best = max(range(len(ids)), key=lambda n: (fused_score(scores[n], inl[n]), -n))
            right.append(dist(q, ids[best]) <= 25)
        label = "none" if margin is None else f"{margin}"
        out.append(f"| {p.name} | {label} | {np.mean(n_ver):.1f} | {np.median(ms):.0f} | {np.mean(right):.3f} |")
        print(out[-1], flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, default=MANIFEST)
    ap.add_argument("--k", type=int, default=10, help="global candidates verified per query")
    ap.add_argument("--profiles", nargs="*", help="names (prefixes) of PROFILES to measure, in this order; default all")
    ap.add_argument("--max-queries", type=int, default=None)
    ap.add_argument("--write", action="store_true", help="write the section of docs/benchmarks.md")
    a = ap.parse_args()
    chosen = PROFILES if not a.profiles else [p for x in a.profiles for p in PROFILES if p.name.startswith(x)]
    body = run(a.manifest, a.k, chosen, a.max_queries)
    print(body)
    if a.write:
        cmd = "nice -n 10 .venv/bin/python -m bench.stored_verification --write"
        write_section("stored-verification", f"## Stored local features for verification\n\n`{cmd}`\n\n{body}")


if __name__ == "__main__":
    main()
