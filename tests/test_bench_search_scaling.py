"""The search-scaling benchmark on a small collection: the figures it reports mean what they say."""

import numpy as np

from bench import search_scaling


def test_modes_codes_and_agreement_on_a_small_collection():
    figs = {f.mode: f for f in search_scaling.measure_ours(3000, 30)}
    assert set(figs) == {"float", "binary", "two-stage"}
    assert figs["float"].agrees_with_float_top1 == 1.0
    # 256 float32 + an 8-byte id; 32 bytes of bits + an 8-byte id
    assert 1032 <= figs["float"].bytes_per_ref < 1040
    assert 40 <= figs["binary"].bytes_per_ref < 48
    assert figs["two-stage"].bytes_per_ref == figs["float"].bytes_per_ref + figs["binary"].bytes_per_ref
    # the re-rank of a 100-long Hamming shortlist recovers the exact answer on 3,000 references
    assert figs["two-stage"].agrees_with_float_top1 >= 0.9
    assert all(f.median_ms > 0 for f in figs.values())


def test_noisy_queries_stay_nearest_to_their_source():
    rng = np.random.default_rng(0)
    refs = search_scaling.synthetic_codes(2000, 256, rng)
    q = search_scaling.noisy_queries(refs, 50, np.random.default_rng(1))
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
    cos_to_best = (q @ refs.T).max(axis=1)
    assert 0.3 < float(np.median(cos_to_best)) < 0.6
