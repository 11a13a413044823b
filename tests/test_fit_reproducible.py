"""The same manifest gives the same fitted pipeline with 1 and with 2 threads (the README's demo figures once
came from a fit on another machine, and a fresh `make run` printed others).

Two real `geoloc fit` processes on 40 penn captures (120 photos and crops), one with every thread setting at
1 (BLAS, OpenMP, onnxruntime: the run's shared fit, ``forty_fitted``), one at 2; their codebooks,
PCA-whitenings, binarisers and calibrations must be equal, and a query photo must get the same ranked
references from both."""

from __future__ import annotations

import json

import numpy as np

from tests.forty import CONFIG, fit_forty, linked_models


def _arrays(directory) -> dict[str, np.ndarray]:
    out = {}
    for path in sorted(directory.glob("*.npz")) + sorted(directory.glob("*.npy")):
        loaded = np.load(path)
        for k in getattr(loaded, "files", [""]):
            out[f"{path.name}:{k}"] = loaded[k] if k else loaded
    return out


def test_a_fit_with_1_and_with_2_threads_gives_the_same_pipeline(tmp_path, models_dir, forty_fitted):
    from app.engine.imageio import load_image
    from app.engine.pipeline import load_pipeline
    from app.engine.training.svm_training import index_of
    from app.manifests import read_manifest

    one_thread, manifest, query = forty_fitted
    dirs = {1: one_thread, 2: linked_models(tmp_path / "models-2", models_dir)}
    fit_forty(manifest, dirs[2], threads=2)
    fitted = {n: d / "pipelines" / CONFIG for n, d in dirs.items()}
    cal = {n: json.loads((fitted[n] / "calibration.json").read_text()) for n in fitted}
    assert cal[1]["source"] == "collection", cal[1]["note"]  # a real calibration, not the conservative rule
    assert cal[1] == cal[2]
    a1, a2 = _arrays(fitted[1]), _arrays(fitted[2])
    assert a1.keys() == a2.keys() and a1
    for k in a1:
        assert np.array_equal(a1[k], a2[k]), k
    rows = read_manifest(manifest)
    pipes = {n: load_pipeline(dirs[n], CONFIG) for n in fitted}
    # Extraction uses nothing fitted (the features are the same with any thread count, checked by the fits
    # above): extracted once, encoded by each pipeline.
    feats = [pipes[1].extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    query_feats = pipes[1].extract(load_image(query.read_bytes()).rgb)
    ranked = {}
    for n, pipe in pipes.items():
        index = index_of(pipe, np.arange(len(rows)), feats)
        codes = pipe.encode_features(query_feats)
        scores, ids = index.search(codes.float_, codes.binary, 10)
        ranked[n] = ids.tolist()
    assert ranked[1] == ranked[2]
