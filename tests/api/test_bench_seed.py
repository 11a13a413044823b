"""The benchmarking seeder fills a data dir through the bulk path with references the service can load."""

from app.engine.pipeline import load_pipeline
from app.storage.store import ReferenceStore
from app.usecases.collection import Collection
from bench.seed import seed
from tests.api.conftest import CONFIG
from tests.test_cli import geoloc


def test_seed_fills_a_consistent_data_dir(tmp_path, fitted_models):
    data = tmp_path / "seeded"
    r = seed(data, 2_500, fitted_models, CONFIG, batch=1_000)
    assert r["added"] == 2_500 and r["rows_per_second"] > 0
    assert seed(data, 2_500, fitted_models, CONFIG)["added"] == 0  # already there: nothing more
    store = ReferenceStore(data)
    assert store.count() == 2_500 and store.version == 2_500 and len(list(store.images_dir.iterdir())) == 2_500
    col = Collection(store, load_pipeline(fitted_models, CONFIG))
    assert col.size == 2_500
    ok = geoloc("check", "--data-dir", str(data), "--models-dir", str(fitted_models))
    assert "ok:" in ok.stdout


def test_scale_bench_compares_sizes_in_one_process(tmp_path, fitted_models):
    from bench.scale import interleaved, interleaved_table
    from tests.conftest import PENN

    for n in (300, 900):
        seed(tmp_path / f"n{n}", n, fitted_models, CONFIG, batch=500)
    res = interleaved([300, 900], tmp_path, fitted_models, CONFIG, sorted((PENN / "photos").glob("*.jpg"))[:2])
    assert set(res) == {300, 900} and all(r["locate_p50_ms"] > 0 and r["job_p50_ms"] > 0 for r in res.values())
    store = ReferenceStore(tmp_path / "n900")  # two uploads encoded, indexed, then deleted: the seeded rows remain
    assert store.count() == 900 and store.version > 900
    assert "900" in interleaved_table(res)
