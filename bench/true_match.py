"""The rank of a penn query's true match among synthetic distractors: what a user feels of an index at size.

Agreement with the exact top-1 measures the crowd once the distractors outnumber the real references (the
exact top-1 of most penn queries is then a distractor). What a user needs is that the *true match*, a
reference taken within ``radius_m`` of the query's own position, still comes back near the top. So for each
penn query with at least one such reference this module gives the true match's rank under the exact search
(one more than the number of other codes scoring strictly above its best true reference, counted chunk by
chunk over the memory-mapped codes) and under an index (its position in the index's top k).

The region filter is what a coarse prior gives back: only references within ``region_m`` of the query count.
Synthetic distractors carry no position, so each is given one drawn uniformly over a square ``extent_m``
wide centred on the penn campus (a collection spread over one metropolitan region); a distractor counts
under the filter when its drawn position lies within ``region_m`` of the query. The draw depends on the
code's id and the seed only, so a larger collection holds the smaller one's positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.engine.geo import haversine_m
from bench.scale_codes import CHUNK, chunks

#: The ranks reported (R@k: the share of queries whose true match ranks within the top k).
RANKS = (1, 10, 100)
M_PER_DEG_LAT = 111_320.0


@dataclass
class Positions:
    """Real positions (degrees) of penn's references and queries, in the order of their codes."""

    refs: np.ndarray  # (n_refs, 2) lat, lon
    queries: np.ndarray  # (n_queries, 2) lat, lon


@dataclass
class TrueMatches:
    """The penn queries that have a true match, and which references are theirs."""

    rows: np.ndarray  # indices into the penn queries
    matches: list[np.ndarray]  # each query's reference ids within radius_m
    xy: np.ndarray  # (len(rows), 2) the query's position in metres from the campus centre
    near_refs: np.ndarray  # (len(rows), n_refs) bool: penn references within the region of the query
    n_queries: int  # penn queries in all (with or without a true match)

    @property
    def count(self) -> int:
        return len(self.rows)


def find_true_matches(pos: Positions, radius_m: float = 25.0, region_m: float = 1000.0) -> TrueMatches:
    """Each penn query's references within ``radius_m`` (queries without any are left out)."""
    d = haversine_m(pos.queries[:, None, 0], pos.queries[:, None, 1], pos.refs[None, :, 0], pos.refs[None, :, 1])
    rows = np.flatnonzero((d <= radius_m).any(axis=1))
    centre = pos.refs.mean(axis=0)
    q = pos.queries[rows]
    xy = np.stack(
        [(q[:, 1] - centre[1]) * M_PER_DEG_LAT * np.cos(np.radians(centre[0])), (q[:, 0] - centre[0]) * M_PER_DEG_LAT],
        axis=1,
    )
    return TrueMatches(
        rows, [np.flatnonzero(d[r] <= radius_m) for r in rows], xy, d[rows] <= region_m, len(pos.queries)
    )


def distractor_xy(lo: int, count: int, extent_m: float, seed: int) -> np.ndarray:
    """Drawn positions (metres from the campus centre) of the codes ``lo .. lo+count`` (one chunk)."""
    rng = np.random.default_rng([seed, 23, lo // CHUNK])
    return rng.uniform(-extent_m / 2, extent_m / 2, (count, 2)).astype(np.float32)


@dataclass
class ExactRanks:
    """The true match's rank under the exact search, without and with the region filter."""

    ranks: np.ndarray  # (count,)
    region_ranks: np.ndarray  # (count,)
    region_distractors: float  # median number of synthetic codes within the region of a query


def exact_ranks(
    codes: np.ndarray,
    n: int,
    queries: np.ndarray,
    truth: TrueMatches,
    n_penn: int,
    extent_m: float,
    region_m: float = 1000.0,
    seed: int = 0,
) -> ExactRanks:
    """Ranks of each query's best true reference among the first ``n`` codes; ``queries`` are the penn
    queries' codes, ``codes`` holds penn's references at ids 0..n_penn-1."""
    q = np.ascontiguousarray(queries[truth.rows], dtype=np.float32)
    refs = np.asarray(codes[:n_penn], dtype=np.float32)
    best = np.array([(q[i] @ refs[m].T).max() for i, m in enumerate(truth.matches)], dtype=np.float32)
    is_match = np.zeros((len(q), n_penn), bool)  # the true references never count against themselves
    for i, m in enumerate(truth.matches):
        is_match[i, m] = True
    above = np.zeros(len(q), np.int64)
    above_region = np.zeros(len(q), np.int64)
    inside_count = np.zeros(len(q), np.int64)
    for lo, x in chunks(codes, n):
        s = q @ x.T
        higher = s > best[:, None]
        synthetic = max(lo, n_penn)
        if lo < n_penn:  # penn's own references: their real positions decide the region
            k = min(n_penn, lo + len(x)) - lo
            higher[:, :k] &= ~is_match[:, lo : lo + k]
            above_region += (higher[:, :k] & truth.near_refs[:, lo : lo + k]).sum(axis=1)
        above += higher.sum(axis=1)
        if synthetic < lo + len(x):
            xy = distractor_xy(lo, len(x), extent_m, seed)[synthetic - lo :]
            d2 = ((truth.xy[:, None, :] - xy[None, :, :]) ** 2).sum(axis=2)
            inside = d2 <= region_m**2
            inside_count += inside.sum(axis=1)
            above_region += (higher[:, synthetic - lo :] & inside).sum(axis=1)
    return ExactRanks(above + 1, above_region + 1, float(np.median(inside_count)))


def found_ranks(found: np.ndarray, truth: TrueMatches) -> np.ndarray:
    """Ranks of the true match in an index's results (``found``: the penn queries' top-k ids, in the penn
    queries' order); beyond the k returned: k + 1."""
    k = found.shape[1]
    out = np.full(truth.count, k + 1, np.int64)
    for i, (row, m) in enumerate(zip(truth.rows, truth.matches, strict=True)):
        hit = np.flatnonzero(np.isin(found[row], m))
        if len(hit):
            out[i] = hit[0] + 1
    return out


def recall_at(ranks: np.ndarray, ks=RANKS) -> dict[int, float]:
    """R@k of the true match for each k."""
    return {k: float(np.mean(ranks <= k)) for k in ks}


def kept(ranks: np.ndarray, exact: np.ndarray, k: int = 10) -> float | None:
    """Of the queries whose true match the exact search ranks within ``k``, the share the index also returns
    within ``k`` (None where the exact search ranks none there)."""
    mask = exact <= k
    return float(np.mean(ranks[mask] <= k)) if mask.any() else None
