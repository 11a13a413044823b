"""LighterGlue (XFeat's small LightGlue) as a model: XFeat keypoints of two images in, matches with confidences
out (the ``xfeat-lighterglue`` matcher, ``app.engine.matchers.lighterglue``, runs it).

Why a learned matcher: counting inliers of nearest-neighbour matches cannot tell lookalike buildings
apart; LightGlue decides matchability from both images' keypoints in context, so wrong pairs
get few, unconfident matches. The graph is ours (``app.engine.convert.lighterglue_onnx``); around it,
numpy: keypoints normalised as upstream (``normalize_keypoints``), pairs padded into batches with masks
(``BATCH`` pairs per run), mutual-best filtering of the log assignment (``filter_matches``, upstream's),
then the matcher fits the H-or-F MAGSAC geometry (``app.engine.matchers.geometry``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.models.base import OnnxModel

MODEL_FILENAME = "xfeat-lighterglue.onnx"
#: The graph's tensor names, per image of the pair (the converter writes them).
KEYPOINTS = ("keypoints0", "keypoints1")  # (B, N, 2) float, normalised (``normalize_keypoints``)
DESCRIPTORS = ("descriptors0", "descriptors1")  # (B, N, 64) float, XFeat's unit descriptors
MASKS = ("mask0", "mask1")  # (B, N) float, 1 for a real keypoint, 0 for padding
SCORES_OUTPUT = "log_assignment"  # (B, M, N): log P(i matches j), dustbins left out
INPUT_DIM = 64
#: Upstream's point pruning (``width_confidence`` 0.95): a point with matchability <= 0.05 after a layer
#: leaves the later layers.
PRUNE_THRESHOLD = 1 - 0.95
#: Upstream's ``filter_threshold`` (``min_conf``): a mutual best match is kept above this probability.
MATCH_THRESHOLD = 0.1
#: What the matcher extracts per image: XFeat at this long side (never upscaled), the best keypoints.
#: Chosen by measurement on penn-campus-gps (docs/benchmarks.md, "Learned matching").
LONG_SIDE = 640
MAX_KEYPOINTS = 512
#: Pairs per network run. The graph takes any batch (padding + masks), but on 2 CPU cores one pair per run
#: measured faster than the K = 10 candidates of a query in one run (``bench.matcher_speed``,
#: docs/benchmarks.md): ten 512 x 512 attention maps do not stay in cache, and
#: a run's overhead is small next to its arithmetic. A GPU deployment would batch.
BATCH = 1


def normalize_keypoints(xy: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """Upstream's ``normalize_keypoints``: centred on the image, divided by half its longer side."""
    size = np.asarray(size_wh, np.float64)
    return ((np.asarray(xy, np.float64) - size / 2) / (size.max() / 2)).astype(np.float32)


def filter_matches(scores: np.ndarray, threshold: float = MATCH_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """Upstream's ``filter_matches`` on one pair's (M, N) log assignment: (K, 2) index pairs (i, j) that
    are each other's best and whose probability exp(score) exceeds ``threshold``, and those probabilities."""
    m, n = scores.shape
    if m == 0 or n == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
    m0 = scores.argmax(axis=1)
    m1 = scores.argmax(axis=0)
    idx = np.arange(m)
    conf = np.exp(scores[idx, m0].astype(np.float64))
    valid = (m1[m0] == idx) & (conf > threshold)
    return np.stack([idx[valid], m0[valid]], axis=1), conf[valid].astype(np.float32)


@dataclass(frozen=True)
class KeypointFeatures:
    """One image's XFeat keypoints for matching: positions in pixels of the image as the extractor saw it
    (long side at most ``LONG_SIDE``; RANSAC thresholds are in pixels), unit descriptors, and that size."""

    xy: np.ndarray  # (N, 2) float32 pixels
    descriptors: np.ndarray  # (N, 64) float32
    size_wh: tuple[int, int]

    def __len__(self) -> int:
        return len(self.xy)


@dataclass(frozen=True)
class PairMatches:
    """LighterGlue's matches of one pair: (K, 2) indices into (image 0, image 1) and their probabilities."""

    pairs: np.ndarray
    confidence: np.ndarray


class LighterGlue(OnnxModel):
    """The converted LighterGlue graph: a batch of padded pairs in, matches per pair out."""

    filename = MODEL_FILENAME

    def log_assignment(
        self, feats0: Sequence[KeypointFeatures], feats1: Sequence[KeypointFeatures]
    ) -> list[np.ndarray]:
        """The (len(a), len(b)) log assignment of each pair (feats0[k], feats1[k]), in one run: every
        image's keypoints padded to the longest of its side with a mask (padding never takes part)."""
        if len(feats0) != len(feats1):
            raise ValueError("as many first as second images")
        inputs: dict[str, np.ndarray] = {}
        for side, feats in enumerate((feats0, feats1)):
            n = max(1, max(len(f) for f in feats))
            kp = np.zeros((len(feats), n, 2), np.float32)
            desc = np.zeros((len(feats), n, INPUT_DIM), np.float32)
            mask = np.zeros((len(feats), n), np.float32)
            for b, f in enumerate(feats):
                kp[b, : len(f)] = normalize_keypoints(f.xy, f.size_wh)
                desc[b, : len(f)] = f.descriptors
                mask[b, : len(f)] = 1
            inputs |= {KEYPOINTS[side]: kp, DESCRIPTORS[side]: desc, MASKS[side]: mask}
        (scores,) = self.predict(inputs, [SCORES_OUTPUT])
        return [scores[b, : len(a), : len(c)] for b, (a, c) in enumerate(zip(feats0, feats1, strict=True))]

    def match_many(
        self,
        query: KeypointFeatures,
        candidates: Sequence[KeypointFeatures],
        threshold: float = MATCH_THRESHOLD,
        batch: int = BATCH,
    ) -> list[PairMatches]:
        """The query against each candidate, ``batch`` pairs per run (the query repeated)."""
        out: list[PairMatches] = []
        for start in range(0, len(candidates), batch):
            chunk = list(candidates[start : start + batch])
            live = [c for c in chunk if len(c) and len(query)]
            scores = iter(self.log_assignment([query] * len(live), live) if live else [])
            for c in chunk:
                s = next(scores) if len(c) and len(query) else np.zeros((len(query), len(c)), np.float32)
                out.append(PairMatches(*filter_matches(s, threshold)))
        return out
