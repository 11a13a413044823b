"""Does verification's evidence make ``p_within_25m`` and the confidence rule better? (issue 20, item 2)

    python -m bench.verified_evidence --config lite2-hybrid-384 --matcher xfeat-lighterglue \
        --record out/verified-lg.json

Each query of each fold (the evaluation's folds, fits and searches, ``svm_bank`` off as in ``geoloc eval``)
is located through ``app.locate.locate_features``, as /locate serves it, four times: its place present
and absent (every reference within ``--absent-radius`` removed), each without and with verification by
``--matcher``. Each answer's evidence (``app.engine.evidence``) is recorded. Then the calibration
(``app.engine.calibration.fit_calibration``, the rule ``geoloc fit`` serves) is fitted on four folds' answers
and applied to the fifth, once on the global columns of plain answers and once on the global and verified
columns of verified answers. Calibrating on other queries rather than on the collection is the most
favourable case for both: it shows what the evidence itself carries, whatever the collection's sample.

``--record`` keeps the answers (and re-analyses them without locating again when the file exists).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

import app.locate as locate
from app.domain import LocateOptions
from app.engine.calibration import Sample, answer_probability, fit_calibration
from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.evidence import GLOBAL_NAMES, VERIFIED_NAMES, Evidence
from app.engine.pipeline import Pipeline
from app.engine.registry import Kind, create
from app.engine.training.svm_training import Geotagged, index_of
from app.evaluation.datasets import read_manifest
from app.evaluation.evaluate import RowReferences, assign_folds, extract_cached
from app.fitting import calibration_sample, near_ids


class CachingMatcher:
    """The matcher with each image's features and each pair's outcome computed once: every query is
    verified twice (place present and absent) against candidates that recur across queries. It has
    ``features`` and ``match_many`` only: all that ``verify_candidate_pairs`` calls."""

    def __init__(self, inner):
        self.inner, self.features_of, self.pairs, self.computed = inner, {}, {}, 0

    def features(self, rgb: np.ndarray):
        key = id(rgb)  # the arrays are kept alive below, so an id is never reused
        if key not in self.features_of:
            self.features_of[key] = (rgb, key, self.inner.features(rgb))
        return self.features_of[key]

    def match_many(self, query, candidates) -> list:
        todo = [c for c in candidates if (query[1], c[1]) not in self.pairs]
        if todo:
            got = self.inner.match_many(query[2], [c[2] for c in todo])
            self.computed += len(todo)
            self.pairs.update({(query[1], c[1]): v for c, v in zip(todo, got, strict=True)})
        return [self.pairs[(query[1], c[1])] for c in candidates]


def decode_once() -> None:
    """The core decodes each candidate's stored photo for every verification; here the same photos recur
    thousands of times, so their decodes are kept (the same function, called once per photo)."""
    load, decoded = locate.load_image, {}

    def cached(data: bytes, limits):
        key = hashlib.blake2b(data, digest_size=16).digest()
        if key not in decoded:
            decoded[key] = load(data, limits)
        return decoded[key]

    locate.load_image = cached


def record(args) -> list[dict]:
    config = get_config(args.config)
    rows = read_manifest(args.manifest)
    base = Pipeline(config, models_dir=args.models_dir)
    extracted = extract_cached(base, rows, args.cache, 2)
    matcher = create(Kind.MATCHER, args.matcher, args.models_dir)
    if hasattr(matcher, "load"):
        matcher.load()
    matcher = CachingMatcher(matcher)
    decode_once()
    out, t0 = [], time.perf_counter()
    for f, groups in enumerate(assign_folds(rows, args.folds, args.seed)):
        qset = set(groups)
        q_idx = [i for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
        db_idx = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        fit_idx = db_idx + [i for i, r in enumerate(rows) if r.split == "train"]
        pipe = Pipeline(config, base.global_model, models_dir=args.models_dir)
        pipe.fit([extracted[i].features for i in fit_idx], seed=args.seed + f)
        pipe._matcher = matcher
        index = index_of(pipe, db_idx, (extracted[i].features for i in db_idx))
        geotagged = {i: Geotagged(extracted[i].features, rows[i].lat, rows[i].lon, rows[i].group) for i in db_idx}
        refs = RowReferences(rows, db_idx)
        for i in q_idx:
            feats = extracted[i].features
            if config.local is not None and feats.n_local < locate.MIN_LOCAL_FEATURES:
                continue
            codes = pipe.encode_features(feats, pipe.select(feats))
            rgb = pipe.decode(rows[i].image.read_bytes()).rgb
            gone = near_ids(geotagged, rows[i].lat, rows[i].lon, args.absent_radius)
            for absent, searched in ((False, index), (True, locate.Excluding(index, gone))):
                for verify in (False, True):
                    options = LocateOptions(top_k=locate.ESTIMATE_CANDIDATES, rerank=verify)
                    answer = locate.locate_features(pipe, searched, refs, feats, options, rgb, codes=codes)
                    s = calibration_sample(answer, rows[i].lat, rows[i].lon, absent)
                    if s is not None:
                        out.append(
                            {
                                "fold": f,
                                "query": i,
                                "absent": absent,
                                "verified": verify,
                                "names": list(s.evidence.names),
                                "x": s.evidence.values.round(5).tolist(),
                                "within": s.within.tolist(),
                                "members": s.members.tolist(),
                                "estimate_within": s.estimate_within,
                                "verify_ms": answer.timings_ms.get("rerank"),
                            }
                        )
        print(f"fold {f + 1}: {matcher.computed} pairs verified, {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def held_out(records: list[dict], verified: bool, names: tuple[str, ...]) -> dict:
    """Calibrate on the other folds' answers, apply to each fold's; pooled figures."""
    samples = [
        (
            r["fold"],
            Sample(
                Evidence(names, Evidence(tuple(r["names"]), np.asarray(r["x"], float)).columns(names)),
                np.asarray(r["within"], bool),
                np.asarray(r["members"], bool),
                r["estimate_within"],
                r["absent"],
            ),
        )
        for r in records
        if r["verified"] == verified
    ]
    p_all, y_all, r1, confident, right, absent_best, absent_conf, ranked = [], [], [], 0, 0, [], 0, []
    for f in sorted({g for g, _ in samples}):
        cal = fit_calibration([s for g, s in samples if g != f])
        for s in (s for g, s in samples if g == f):
            p, ap = cal.probabilities(s.evidence), answer_probability(cal, s)
            if s.absent:
                absent_best.append(float(p.max()))
                absent_conf += int(ap >= cal.confident_p)
                continue
            p_all.append(p)
            y_all.append(s.within)
            r1.append(bool(s.within[0]))
            ranked.append((ap, s.estimate_within))
            if ap >= cal.confident_p:
                confident, right = confident + 1, right + int(s.estimate_within)
    from sklearn.metrics import roc_auc_score

    p, y = np.concatenate(p_all), np.concatenate(y_all).astype(float)
    ranked.sort(key=lambda t: -t[0])
    n = len(ranked)
    return {
        "queries": n,
        "r1": float(np.mean(r1)),
        "brier": float(np.mean((p - y) ** 2)),
        "auc": float(roc_auc_score(y, p)),
        "confident": confident / n,
        "confident_right": right / confident if confident else None,
        # Whatever the threshold: the precision of the answers ranked first by their own probability.
        "precision_at_coverage": {
            f"{c:.2f}": float(np.mean([ok for _, ok in ranked[: int(c * n)]])) for c in (0.1, 0.2, 0.3)
        },
        "absent_confident": absent_conf / max(len(absent_best), 1),
        "absent_mean_best_p": float(np.mean(absent_best)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, default=Path("data/manifests/penn-campus-gps.csv"))
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--matcher", default="xfeat-lighterglue")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--absent-radius", type=float, default=100.0)
    ap.add_argument("--models-dir", type=Path, default=Path("models"))
    ap.add_argument("--cache", type=Path, default=Path("out/cache"))
    ap.add_argument("--record", type=Path, required=True, help="the answers' JSON (read back when it exists)")
    args = ap.parse_args()
    if args.record.exists():
        records = json.loads(args.record.read_text())
    else:
        records = record(args)
        args.record.parent.mkdir(parents=True, exist_ok=True)
        args.record.write_text(json.dumps(records))
    n = len({r["query"] for r in records})
    # No time here: features and pairs are cached across the four locates (bench.matcher_speed times them).
    print(f"{args.config}, verified by {args.matcher}: {n} queries, held-out calibration per fold")
    rows = (
        ("plain answers, global evidence", False, GLOBAL_NAMES),
        ("verified answers, global evidence", True, GLOBAL_NAMES),
        ("verified answers, global + verified", True, GLOBAL_NAMES + VERIFIED_NAMES),
    )
    print(
        "| answers, evidence | R@1 | Brier | AUC | confident / then right | precision at 10 / 20 / 30 % coverage "
        "| absent: confident, mean best p |"
    )
    print("|---|---|---|---|---|---|---|")
    for label, verified, names in rows:
        q = held_out(records, verified, names)
        right = "n/a" if q["confident_right"] is None else f"{q['confident_right']:.0%}"
        prec = " / ".join(f"{v:.0%}" for v in q["precision_at_coverage"].values())
        print(
            f"| {label} | {q['r1']:.3f} | {q['brier']:.4f} | {q['auc']:.3f} | {q['confident']:.1%} / {right} "
            f"| {prec} | {q['absent_confident']:.1%}, {q['absent_mean_best_p']:.3f} |"
        )


if __name__ == "__main__":
    main()
