"""The benchmarking seeder fills a data dir through the bulk path with references the service can load."""

from app.collection import Collection
from app.engine.pipeline import load_pipeline
from app.store import ReferenceStore
from bench.seed import seed
from tests.service.conftest import CONFIG
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
