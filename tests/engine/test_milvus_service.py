"""The ``milvus`` index kind through the real service, on a real Milvus server (the ``milvus`` wheel's
embedded standalone, started once for the module's session) and real penn photos.

A fitted pipeline's codes are served from Milvus (``GEOLOC_MILVUS_URI``: ``IndexSizing.shared``): the
writer fills and updates the server's collections, a second service on the same store (a replica) builds
nothing and finds what the writer indexed, in every search mode, with the region filter (run by Milvus on
the positions it stores), and a delete or a move holds at once through both. Milvus stopped and started
again: tests/api/test_milvus_hosts.py, through a real server (one restart of the session's Milvus for both
modules: it is most of a minute on two cores)."""

from __future__ import annotations

import pytest

from app.engine import configs as configs_mod
from app.engine.configs import PipelineConfig
from app.manifests import read_manifest

pytestmark = pytest.mark.milvus

#: Small and fast codes (SqueezeNet GeM, 64-d floats and 64 bits): float, binary and two-stage search.
CONFIG = PipelineConfig(
    name="squeezenet-gem-milvus-test",
    description="SqueezeNet GeM codes, float and binary (test)",
    local=None,
    codebook=None,
    cnn_global_weight=1.0,
    cnn_short_side=224,
    pca_dim=64,
    binary="itq",
    bits=64,
)
MODES = ("two-stage", "float", "binary")


@pytest.fixture(scope="module")
def fitted_models(models_dir, mini_manifest, tmp_path_factory):
    from app.cli import fit

    configs_mod.CONFIGS[CONFIG.name] = CONFIG
    models = tmp_path_factory.mktemp("milvus-models")
    (models / "squeezenet1_1.onnx").symlink_to(models_dir / "squeezenet1_1.onnx")
    fit(
        manifest=mini_manifest,
        config=CONFIG.name,
        models_dir=models,
        seed=0,
        svm_bank=None,
        svm_bank_kind="contrastive",
    )
    yield models
    configs_mod.CONFIGS.pop(CONFIG.name, None)


def _sizing(server, collection: str):
    from app.policies import IndexSizing, SharedIndex

    return IndexSizing(shared=SharedIndex(server.uri, collection, wait_seconds=5.0))


def _indexed(service, uploads) -> list[int]:
    from app.ingestion.worker import IngestWorker

    accepted = service.accept(uploads)
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    return accepted.reference_ids


def _first(service, image: bytes, mode: str, region=None) -> int | None:
    from app.domain import LocateOptions

    answer = service.locate(image, LocateOptions(top_k=5, mode=mode, region=region))
    return answer.candidates[0].reference_id if answer.candidates else None


def test_writer_and_replica_share_one_milvus_index(fitted_models, mini_manifest, milvus_server, tmp_path):
    from app.domain import Region, Upload
    from app.usecases.service import GeolocService

    sizing = _sizing(milvus_server, "share")
    writer = GeolocService.open(tmp_path / "data", fitted_models, CONFIG.name, sizing=sizing)
    writer.collection.hold_writer_role(True)
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    ids = _indexed(writer, [Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db[:8]])
    stats = writer.collection.index.stats()
    assert {p: (s["kind"], s["size"], s["collection"]) for p, s in stats.items()} == {
        "float": ("milvus", 8, "share_float_g0"),
        "binary": ("milvus", 8, "share_binary_g0"),
    }
    assert "milvus at every size" in writer.collection.index_choice()

    replica = GeolocService.open(tmp_path / "data", fitted_models, CONFIG.name, sizing=sizing)
    assert replica.collection.stats.full_rebuilds == 0 and not replica.collection.writes_shared
    for svc in (writer, replica):
        for mode in MODES:
            assert _first(svc, db[3].image.read_bytes(), mode) == ids[3], mode

    # the region filter: a circle around another place leaves only the references inside it
    other = next(r for r in db[:8] if (r.lat, r.lon) != (db[3].lat, db[3].lon))
    inside = {i for i, r in zip(ids, db[:8], strict=True) if (r.lat, r.lon) == (other.lat, other.lon)}
    region = Region(lat=other.lat, lon=other.lon, radius_m=1.0)
    for mode in MODES:
        assert _first(replica, db[3].image.read_bytes(), mode, region) in inside, mode

    # an upload indexed by the writer is found first through the replica at once (no catch-up call)
    (new,) = _indexed(writer, [Upload(db[9].image.read_bytes(), db[9].image.name, db[9].lat, db[9].lon)])
    for mode in MODES:
        assert _first(replica, db[9].image.read_bytes(), mode) == new, mode

    # a delete through the replica (which does not write to Milvus) is gone at once once the writer applied it
    assert replica.delete(ids[3]) is not None
    writer.collection.catch_up()  # the writer's next catch-up (its worker or its change listener in a server)
    for svc in (replica, writer):
        for mode in MODES:
            assert _first(svc, db[3].image.read_bytes(), mode) != ids[3], mode
    assert writer.collection.size == replica.collection.size == 8
    assert writer.collection.stats.full_rebuilds == 1  # filled once; every later change applied, not refilled
    writer.store.close()
    replica.store.close()


def test_refit_fills_new_collections_and_both_switch(fitted_models, mini_manifest, milvus_server, tmp_path):
    """A re-fit's new codes go into the next generation's collections: the writer fills them as it loads the
    generation, the replica switches once they are filled, and both find a reference's own photo first."""
    from app.domain import Upload
    from app.jobs.refit import RefitOptions, refit
    from app.usecases.service import GeolocService

    sizing = _sizing(milvus_server, "refit")
    data = tmp_path / "data"
    writer = GeolocService.open(data, fitted_models, CONFIG.name, sizing=sizing)
    writer.collection.hold_writer_role(True)
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    ids = _indexed(writer, [Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    replica = GeolocService.open(data, fitted_models, CONFIG.name, sizing=sizing)

    refit(data, fitted_models, RefitOptions(svm_bank="none", sample=len(db), calibration_sample=len(db)))
    writer.collection.catch_up()
    writer.collection.refresh_generation(wait=True)
    assert writer.collection.generation == 1, writer.collection.reload_error
    assert writer.collection.index.stats()["float"]["collection"] == "refit_float_g1"
    replica.collection.catch_up()
    replica.collection.refresh_generation(wait=True)
    assert replica.collection.generation == 1, replica.collection.reload_error
    for svc in (writer, replica):
        assert svc.collection.size == len(db)
        for mode in MODES:
            assert _first(svc, db[6].image.read_bytes(), mode) == ids[6], mode
    writer.store.close()
    replica.store.close()


def test_milvus_reads_at_the_writers_timestamp_see_its_writes_and_deletes(milvus_server):
    """Two clients of one collection, as a writer and a replica: after the writer's upsert and delete, a
    timestamp it takes (``fence``) makes the replica's reads at it (``read_after``) see both at once, with no
    strongly consistent read; a replica with no timestamp reads strongly."""
    import numpy as np

    from app.engine.index.kinds.milvus import MilvusIndex

    writer = MilvusIndex(64, False, uri=milvus_server.uri, collection="fence")
    replica = MilvusIndex(64, False, uri=milvus_server.uri, collection="fence")
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200, 64)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    writer.add(np.arange(200), x, np.zeros((200, 2)))
    assert replica.read_ts is None and replica._consistency() == {"consistency_level": "Strong"}
    replica.read_after(writer.fence())
    assert replica._consistency()["consistency_level"] == "Customized"
    assert replica.search(x[:1], 1)[1][0, 0] == 0 and replica.size == 200
    writer.remove([0])
    writer.add(np.array([500]), x[1:2], np.zeros((1, 2)))
    replica.read_after(writer.fence())
    ids = replica.search(x[:2], 2)[1]
    assert 0 not in ids[0] and set(ids[1]) == {1, 500} and replica.size == 200
    assert replica.reconstruct([500]).shape == (1, 64)
    writer.drop()


def test_the_region_filter_runs_on_the_positions_milvus_holds(fitted_models, mini_manifest, milvus_server, tmp_path):
    """Each reference's position is stored in Milvus beside its codes, and a region is a filter on them that
    the server applies inside the search (the store is not asked for the region's ids): a circle and a box
    keep to the references inside, a region with none says so, and a reference moved through a replica is
    written again at its new position by the writer, found inside its new region and no longer in its old."""
    from app.domain import LocateOptions, ReferenceEdit, Region, Upload
    from app.engine.calibration import NO_REFERENCES
    from app.usecases.service import GeolocService

    sizing = _sizing(milvus_server, "region")
    writer = GeolocService.open(tmp_path / "data", fitted_models, CONFIG.name, sizing=sizing)
    writer.collection.hold_writer_role(True)
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:8]
    ids = _indexed(writer, [Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    replica = GeolocService.open(tmp_path / "data", fitted_models, CONFIG.name, sizing=sizing)
    assert writer.collection.index.holds_positions and replica.collection.index.holds_positions
    stored = _stored_positions(writer, ids)
    assert stored == {i: (r.lat, r.lon) for i, r in zip(ids, db, strict=True)}

    photo = db[3].image.read_bytes()
    other = next(r for r in db if (r.lat, r.lon) != (db[3].lat, db[3].lon))
    inside = {i for i, r in zip(ids, db, strict=True) if (r.lat, r.lon) == (other.lat, other.lon)}
    circle = Region(lat=other.lat, lon=other.lon, radius_m=1.0)
    box = Region(bbox=(other.lon - 1e-6, other.lat - 1e-6, other.lon + 1e-6, other.lat + 1e-6))
    for region in (circle, box):
        for mode in MODES:
            answer = replica.locate(photo, LocateOptions(top_k=5, mode=mode, region=region))
            assert answer.candidates and {c.reference_id for c in answer.candidates} <= inside, (region, mode)
            assert "region" not in answer.timings_ms  # no read of the region's ids from the store

    far = Region(lat=other.lat + 0.5, lon=other.lon, radius_m=1000.0)
    answer = replica.locate(photo, LocateOptions(top_k=5, region=far))
    assert not answer.candidates and answer.reason_code == NO_REFERENCES, answer.reason

    # moved through the replica (which does not write to Milvus): the writer's catch-up writes it again
    assert replica.update(ids[3], ReferenceEdit(lat=other.lat, lon=other.lon)) is not None
    writer.collection.catch_up()
    assert _stored_positions(writer, [ids[3]]) == {ids[3]: (other.lat, other.lon)}
    for svc in (replica, writer):
        for mode in MODES:
            assert _first(svc, photo, mode, circle) == ids[3], mode
            assert _first(svc, photo, mode, Region(lat=db[3].lat, lon=db[3].lon, radius_m=1.0)) != ids[3], mode
    assert writer.collection.size == replica.collection.size == 8
    writer.store.close()
    replica.store.close()


def _stored_positions(service, ids) -> dict[int, tuple[float, float]]:
    """(lat, lon) of ``ids`` as the Milvus collections hold them (the same in every part)."""
    found = []
    for part in service.collection.index.parts().values():
        rows = part._call(
            "read positions",
            lambda c, part=part: c.query(
                part.collection, filter=f"id in {[int(i) for i in ids]}", output_fields=["id", "lat", "lon"]
            ),
        )
        found.append({int(r["id"]): (r["lat"], r["lon"]) for r in rows})
    assert all(f == found[0] for f in found), found
    return found[0]


def test_collections_filled_without_positions_are_filled_again_by_the_writer(
    fitted_models, mini_manifest, milvus_server, tmp_path
):
    """A data dir whose Milvus collections an earlier version filled (codes only, no positions; its version
    recorded under the earlier meta key): the writer's first catch-up fills them again from the store, with
    positions, and a region search runs on them."""
    from pymilvus import DataType, MilvusClient

    from app.domain import Region, Upload
    from app.usecases.service import GeolocService

    sizing = _sizing(milvus_server, "layout")
    data = tmp_path / "data"
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:6]
    first = GeolocService.open(data, fitted_models, CONFIG.name, sizing=sizing)
    first.collection.hold_writer_role(True)
    ids = _indexed(first, [Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    parts = {name: (p.collection, p.dim, p.binary) for name, p in first.collection.index.parts().items()}
    first.store.close()

    client = MilvusClient(uri=milvus_server.uri)
    old = GeolocService.open(data, fitted_models, CONFIG.name)
    version, stored_ids, f, b = old.store.all_codes()
    assert sorted(stored_ids.tolist()) == sorted(ids)
    codes = {"float": f, "binary": b}
    for name, (collection, dim, binary) in parts.items():  # the earlier layout: an id and a code
        client.drop_collection(collection)
        schema = MilvusClient.create_schema(auto_id=False, enable_dynamic_field=False)
        schema.add_field("id", DataType.INT64, is_primary=True)
        schema.add_field("code", DataType.BINARY_VECTOR if binary else DataType.FLOAT_VECTOR, dim=dim)
        params = client.prepare_index_params()
        params.add_index(
            field_name="code", index_type="BIN_FLAT" if binary else "FLAT", metric_type="HAMMING" if binary else "IP"
        )
        client.create_collection(collection, schema=schema, index_params=params, consistency_level="Strong")
        rows = [
            {"id": int(i), "code": c.tobytes() if binary else c.tolist()}
            for i, c in zip(stored_ids, codes[name], strict=True)
        ]
        client.upsert(collection, rows)
    with old.store.transaction() as sql:  # the earlier version recorded what it filled under the earlier key
        sql.execute("DELETE FROM meta WHERE key = ?", (sizing.shared.version_key(0),))
    old.store.set_meta("shared_index_version:milvus:layout:g0", str(version))
    old.store.close()

    writer = GeolocService.open(data, fitted_models, CONFIG.name, sizing=sizing)
    writer.collection.hold_writer_role(True)
    writer.collection.catch_up()
    assert writer.collection.stats.full_rebuilds == 1
    assert _stored_positions(writer, ids) == {i: (r.lat, r.lon) for i, r in zip(ids, db, strict=True)}
    for mode in MODES:
        assert _first(writer, db[2].image.read_bytes(), mode, Region(lat=db[2].lat, lon=db[2].lon, radius_m=1.0)) in {
            i for i, r in zip(ids, db, strict=True) if (r.lat, r.lon) == (db[2].lat, db[2].lon)
        }, mode
    writer.store.close()


def test_a_search_in_a_box_is_exact_where_the_box_holds_few(milvus_server):
    """A box that few references fall in is searched exactly (their codes read and scored here: Milvus's
    filtered HNSW search misses many of the best when the filter passes few rows); above the threshold the
    server applies the filter inside its own search. Either way only references inside come back."""
    import numpy as np

    from app.engine.index.kinds.milvus import MilvusIndex

    rng = np.random.default_rng(1)
    x = rng.standard_normal((2000, 64)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    at = rng.uniform(0.0, 1.0, (2000, 2))  # lat, lon
    index = MilvusIndex(64, False, uri=milvus_server.uri, collection="box")
    index.add(np.arange(2000), x, at)
    box = (0.2, 0.3, 0.45, 0.5)  # min_lon, min_lat, max_lon, max_lat
    inside = np.flatnonzero((at[:, 0] >= 0.3) & (at[:, 0] <= 0.5) & (at[:, 1] >= 0.2) & (at[:, 1] <= 0.45))
    assert 50 < len(inside) < 200
    for q in x[:20:4] + 0.5 * x[20:40:4]:
        q = q / np.linalg.norm(q)
        best = inside[np.argsort(-(x[inside] @ q), kind="stable")[:10]]
        scores, ids = index.search(q[None], 10, box=box)
        assert ids[0].tolist() == best.tolist() and np.all(np.diff(scores[0]) <= 0)
        index.exact_filtered = 0  # the server's filtered search
        assert set(index.search(q[None], 10, box=box)[1][0].tolist()) <= set(inside.tolist())
        index.exact_filtered = len(inside)
    assert (index.search(x[:1], 10, box=(0.2, 1.5, 0.3, 1.6))[1] == -1).all()  # nothing there
    index.drop()
