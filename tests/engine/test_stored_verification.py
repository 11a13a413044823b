"""Verification from stored features against today's re-extracting rerank, on real penn photos.

The claim under test: storing a reference's features (uint16 positions, uint8 descriptors) and matching
them in one batch changes no verdict that matters. Same pairs, same settings (RootSIFT at 800 px, 1,500
keypoints, ratio 0.9, H-or-F MAGSAC at 3 px): every pair's inlier count is within ``TOLERANCE`` of the
count ``app.usecases.locate.verify_candidate_pairs`` gives by decoding and re-extracting the candidate. The
tolerance is MAGSAC's own: today's count is not one number but depends on the order of the matches it
is given (USAC samples them in order; on penn, one pair gives 50-70 inliers over 12 orders of the same
174 matches), and quantising descriptors (at most 1/1024 per component) changes a few matches, hence the
order. So a stored pair's count must lie within the range today's rerank gives over ``ORDERS`` orders of
its own matches, widened by ``SLACK``; or, for chance pairs (no shared view: 11-17 "inliers" whatever is
matched), both at or under ``matchers.fusion.FUSION_FLOOR``, where the fused score ignores them.
"""

import numpy as np
import pytest

from app.engine import stored_features as sf
from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers.fusion import FUSION_FLOOR, FUSION_WEIGHT, fused_score
from app.engine.matchers.geometry import fit_geometry, mutual_matches
from app.engine.matchers.sift_mnn import PixelFeatures, SiftMnnMatcher, features_for_verification
from app.engine.stored_profiles import get_profile
from app.engine.stored_verification import matches_many, verify_stored
from app.usecases.locate import verify_candidate_pairs
from tests.conftest import PENN

ORDERS = 8
SLACK = 3


def todays_range(query: PixelFeatures, candidate: PixelFeatures, today: int) -> tuple[int, int]:
    """The least and most inliers today's rerank finds for this pair over ``ORDERS`` orders of its matches."""
    m = mutual_matches(query.descriptors, candidate.descriptors)
    rng = np.random.default_rng(0)
    counts = [today]
    for _ in range(ORDERS):
        p = m[rng.permutation(len(m))]
        counts.append(fit_geometry(query.xy[p[:, 0]], candidate.xy[p[:, 1]]).inliers)
    return min(counts), max(counts)


class _Images:
    """The penn photos as the rerank's ``ReferenceSource`` (it reads only ``image_bytes``)."""

    def __init__(self, paths):
        self.paths = paths

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.paths[ref_id].read_bytes()


#: A penn photo whose two nearest captures (within 25 m) share its view: 47 and 52 inliers at 800 px today.
QUERY_PHOTO = 31


@pytest.fixture(scope="module")
def pairs(penn_index):
    """The query photo, its two nearest other photos (within 25 m) and three photos over 150 m away."""
    photos = [r for r in penn_index if r["photo"]]
    lat = np.array([float(r["lat"]) for r in photos])
    lon = np.array([float(r["lon"]) for r in photos])
    q = QUERY_PHOTO
    d = haversine_m(lat[q], lon[q], lat, lon)
    d[q] = np.inf
    near = [int(i) for i in np.argsort(d)[:2]]
    assert d[near].max() <= 25
    far = [int(i) for i in np.flatnonzero((d > 150) & np.isfinite(d))[:3]]
    return PENN / photos[q]["photo"], [PENN / photos[i]["photo"] for i in near + far], len(near)


def _stored(path) -> sf.StoredFeatures:
    """What ingestion would store for a reference: its verification features, quantised, as bytes, read back."""
    rgb = load_image(path.read_bytes(), ImageLimits().stored()).rgb
    f = features_for_verification(rgb)
    h, w = rgb.shape[:2]
    s = 800 / max(h, w)
    w, h = (round(w * s), round(h * s)) if s < 1 else (w, h)
    return sf.decode(sf.encode(sf.from_pixels(f.xy, f.descriptors, w, h)))


@pytest.fixture(scope="module")
def both(pairs):
    query, candidates, n_near = pairs
    rgb = load_image(query.read_bytes(), ImageLimits().stored()).rgb
    today = verify_candidate_pairs(rgb, range(len(candidates)), _Images(candidates), ImageLimits(), SiftMnnMatcher())
    q = features_for_verification(rgb)
    stored = verify_stored(q, [_stored(p) for p in candidates])
    ranges = [
        todays_range(q, features_for_verification(load_image(p.read_bytes()).rgb), today[i].inliers)
        for i, p in enumerate(candidates)
    ]
    return today, stored, n_near, ranges


def test_stored_features_give_todays_inlier_counts(both):
    today, stored, n_near, ranges = both
    got = [(r, v.inliers) for r, v in zip(ranges, stored.verifications, strict=True)]
    for (lo, hi), n in got:
        assert lo - SLACK <= n <= hi + SLACK or max(hi, n) <= FUSION_FLOOR, got
    assert min(today[i].inliers for i in range(n_near)) > FUSION_FLOOR, got  # real views, held to the range
    assert stored.stopped_after is None and all(v is not None for v in stored.verifications)


def test_stored_verification_still_tells_near_from_far(both):
    """Not only close counts: the places within 25 m keep more inliers than every one over 150 m."""
    _, stored, n_near, _ = both
    inl = [v.inliers for v in stored.verifications]
    assert max(inl[:n_near]) > max(inl[n_near:]), inl


def test_one_product_for_many_candidates_matches_as_pairwise_matching_does(pairs):
    """Unquantised descriptors through the batch give exactly ``matchers.geometry.mutual_matches``' pairs."""
    query, candidates, _ = pairs
    q = features_for_verification(load_image(query.read_bytes()).rgb)
    cs = [features_for_verification(load_image(p.read_bytes()).rgb).descriptors for p in candidates[:3]]
    batch = matches_many(q.descriptors, cs + [np.zeros((0, 128), np.float32)])
    for m, c in zip(batch, cs, strict=False):
        one = mutual_matches(q.descriptors, c)
        same = len({tuple(x) for x in m} & {tuple(x) for x in one})
        assert same >= 0.99 * len(one) and abs(len(m) - len(one)) <= 0.01 * len(one) + 1
    assert len(batch[-1]) == 0


@pytest.mark.parametrize("floor", [FUSION_FLOOR, get_profile("xfeat-640-n900").fusion_floor, 0])
def test_the_exact_adaptive_stop_never_changes_the_first_candidate(pairs, floor):
    """With the margin at the fusion weight, stopping early picks the candidate full verification picks, at
    the floor the candidates are then ordered by (the stored profile's is not the re-extracting rerank's)."""
    query, candidates, _ = pairs
    q = features_for_verification(load_image(query.read_bytes()).rgb)
    recs = [_stored(p) for p in candidates]
    near_first = [0.70, 0.69, 0.68, 0.67, 0.66]  # the near photos ranked first: a clear answer
    full = verify_stored(q, recs, near_first)
    early = verify_stored(q, recs, near_first, stop_margin=FUSION_WEIGHT, floor=floor)

    def first(out):
        inl = [0 if v is None else v.inliers for v in out.verifications]
        return max(range(len(recs)), key=lambda n: (fused_score(near_first[n], inl[n], floor=floor), -n))

    assert first(early) == first(full)
    if early.stopped_after is not None:
        assert all(v is None for v in early.verifications[early.stopped_after :])
    # a margin of 0 stops as soon as anything is verified
    assert verify_stored(q, recs, near_first, stop_margin=0.0).stopped_after == 1
    with pytest.raises(ValueError, match="global scores"):
        verify_stored(q, recs, stop_margin=0.5)


def test_a_candidate_without_stored_features_is_unverified(pairs):
    query, candidates, _ = pairs
    q = features_for_verification(load_image(query.read_bytes()).rgb)
    out = verify_stored(q, [None, _stored(candidates[0])])
    assert out.verifications[0] is None and out.verifications[1] is not None
