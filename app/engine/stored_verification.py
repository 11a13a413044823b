"""Verify one query against many candidates' STORED local features in one batch.

Why: the re-extracting rerank (``app.engine.matchers`` through ``app.usecases.locate.verify_candidate_pairs``) decodes
each candidate's image and extracts its features on every request. Here the query's features are extracted
once and each candidate's come from its stored record (``app.engine.stored_features``), so what is left is
matching and geometry. The tentative matches of all candidates come from one BLAS matrix product (the
query's descriptors against every candidate's, stacked), cut into each candidate's columns; the rules are
``matchers.geometry.mutual_matches``' (mutual nearest neighbours by L2 distance, Lowe's ratio test), and the geometry is
``matchers.geometry.fit_geometry`` itself, so a stored pair is judged exactly as a re-extracted one with the same
features (tests/engine/test_stored_verification.py compares them on penn photos).

Adaptive stop (``stop_margin``): candidates are verified in retrieval order and, once the best fused score
so far (``matchers.fusion.fused_score``) is at least the next candidate's global score plus ``stop_margin``, the
rest are left unverified. With ``stop_margin = matchers.fusion.FUSION_WEIGHT`` this never changes the first
candidate (no later one can gain more than the weight, and their global scores only fall); smaller margins
stop sooner at a measured risk (bench/stored_verification.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.matchers.base import Verification
from app.engine.matchers.fusion import FUSION_FLOOR, fused_score
from app.engine.matchers.geometry import MIN_MATCHES_TO_FIT, fit_geometry
from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.stored_features import StoredFeatures

#: At most this many float32 distances are held at once (query keypoints x stacked candidate keypoints):
#: 16 M entries, 64 MB, so K = 20 candidates of 2,000 keypoints each are matched in a few products.
MAX_BLOCK_ENTRIES = 16_000_000


@dataclass(frozen=True)
class Settings:
    """The matching and geometry settings; the defaults are the re-extracting rerank's (``verify_features``)."""

    ratio: float | None = 0.9
    min_cos: float | None = None
    threshold_px: float = 3.0
    h_share: float = 0.8
    min_matches: int = MIN_MATCHES_TO_FIT


@dataclass(frozen=True)
class BatchOutcome:
    """Per candidate (in the order given): its verification, or None where it was not verified (no stored
    features, or left out by the adaptive stop: ``stopped_after`` says how many were verified in all)."""

    verifications: list[Verification | None]
    stopped_after: int | None = None  # None: every candidate with features was verified


def matches_many(
    query_desc: np.ndarray,
    candidates_desc: Sequence[np.ndarray],
    ratio: float | None = 0.9,
    min_cos: float | None = None,
) -> list[np.ndarray]:
    """``matchers.geometry.mutual_matches(query_desc, c)`` for every ``c`` of ``candidates_desc``: (M, 2) index pairs
    each, from one matrix product per block of candidates instead of one per candidate."""
    a = np.ascontiguousarray(query_desc, np.float32)
    out: list[np.ndarray] = [np.zeros((0, 2), np.int64)] * len(candidates_desc)
    if len(a) == 0:
        return out
    na = (a * a).sum(1)
    idx = np.arange(len(a))
    for block in _blocks([len(c) for c in candidates_desc], len(a)):
        b = np.concatenate([np.asarray(candidates_desc[i], np.float32) for i in block])
        if len(b) == 0:
            continue
        gram = a @ b.T  # the one BLAS product of this block
        nb = (b * b).sum(1)
        start = 0
        for i in block:
            n = len(candidates_desc[i])
            if n:
                sq = na[:, None] + nb[None, start : start + n] - 2 * gram[:, start : start + n]
                out[i] = _mutual(np.sqrt(np.maximum(sq, 0)), a, b[start : start + n], idx, ratio, min_cos)
            start += n
    return out


def _blocks(sizes: Sequence[int], n_query: int) -> list[list[int]]:
    """Consecutive candidate groups whose stacked keypoints times the query's stay under the block size."""
    blocks: list[list[int]] = [[]]
    total = 0
    for i, n in enumerate(sizes):
        if blocks[-1] and (total + n) * n_query > MAX_BLOCK_ENTRIES:
            blocks.append([])
            total = 0
        blocks[-1].append(i)
        total += n
    return blocks


def _mutual(dist, a, b, idx, ratio, min_cos) -> np.ndarray:
    """``matchers.geometry.mutual_matches``' rule on a precomputed distance matrix (the same operations, same order)."""
    nn12 = dist.argmin(axis=1)
    nn21 = dist.argmin(axis=0)
    keep = nn21[nn12] == idx
    best = dist[idx, nn12]
    if ratio is not None and dist.shape[1] > 1:
        second = np.partition(dist, 1, axis=1)[:, 1]
        keep &= best < ratio * np.maximum(second, 1e-12)
    if min_cos is not None:
        keep &= (a[idx] * b[nn12]).sum(1) > min_cos
    return np.stack([idx[keep], nn12[keep]], axis=1)


def verify_stored(
    query: PixelFeatures,
    candidates: Sequence[StoredFeatures | None],
    global_scores: Sequence[float] | None = None,
    settings: Settings = Settings(),
    stop_margin: float | None = None,
    floor: int = FUSION_FLOOR,
) -> BatchOutcome:
    """Verify ``query`` (features extracted once, positions in pixels) against each candidate's stored
    features, in the order given (retrieval order). ``stop_margin`` with ``global_scores``: the adaptive
    stop of the module's docstring; None verifies every candidate. ``floor``: the fused score's inlier floor
    the candidates will be ordered by (the stop is exact only when it reads the same score)."""
    if stop_margin is not None and global_scores is None:
        raise ValueError("the adaptive stop needs the candidates' global scores")
    have = [i for i, c in enumerate(candidates) if c is not None and len(c) > 0]
    descs = [candidates[i].descriptors for i in have]
    matched = dict(zip(have, matches_many(query.descriptors, descs, settings.ratio, settings.min_cos), strict=True))
    out: list[Verification | None] = [None] * len(candidates)
    best_fused = -np.inf
    for n, i in enumerate(range(len(candidates))):
        c = candidates[i]
        if c is None:
            continue
        m = matched.get(i, np.zeros((0, 2), np.int64))
        out[i] = fit_geometry(
            query.xy[m[:, 0]], c.xy_px[m[:, 1]], settings.threshold_px, settings.h_share, settings.min_matches
        )
        if stop_margin is None:
            continue
        best_fused = max(best_fused, fused_score(float(global_scores[i]), out[i].inliers, floor=floor))
        if n + 1 < len(candidates) and best_fused >= float(global_scores[n + 1]) + stop_margin:
            return BatchOutcome(out, stopped_after=n + 1)
    return BatchOutcome(out)
