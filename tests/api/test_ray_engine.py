"""The Ray engine on a real local Ray instance (127.0.0.1, 2 CPUs): the same codes as the local path with
shipped bytes and with a shared filesystem, an encoder killed mid-job still ends with every reference
indexed exactly once, and a bad image becomes a failed row, not a crash."""

from __future__ import annotations

import collections
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.domain import Upload
from app.ingestion.encoding.items import EncodeItem
from app.ingestion.encoding.local import LocalEngine, encode_and_complete, make_engine
from app.usecases.service import GeolocService
from tests.api.conftest import CONFIG
from tests.conftest import PENN

ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install geoloc[ray])")
from app.ingestion.encoding.ray import RayEngine, RayEngineError, connect  # noqa: E402

pytestmark = pytest.mark.ray


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[None]:
    """A fresh Ray instance on this machine (2 CPUs), started with a timeout and shut down after the module."""
    if ray.is_initialized():
        ray.shutdown()
    assert connect("local", num_cpus=2, timeout_s=120)
    yield
    ray.shutdown()


def crops(penn_index, n: int, skip: int = 0) -> list[Upload]:
    """``n`` real 224 px crops with their capture's position (one crop per capture, in a fixed order)."""
    rows = penn_index[skip : skip + n]
    return [
        Upload((PENN / r["crops"].split(";")[0]).read_bytes(), Path(r["crops"].split(";")[0]).name, float(r["lat"]),
               float(r["lon"]))
        for r in rows
    ]  # fmt: skip


def pending_items(service: GeolocService) -> list[EncodeItem]:
    return [EncodeItem(i, p) for i, p in service.store.pending(10_000)]


@pytest.fixture()
def service(tmp_path, fitted_models) -> Iterator[GeolocService]:
    s = GeolocService.open(tmp_path / "data", fitted_models, CONFIG)
    yield s
    s.store.close()


def by_id(results) -> dict[int, object]:
    return {r.ref_id: r for r in results}


@pytest.mark.parametrize("shared_fs", [False, True], ids=["shipped", "shared-fs"])
def test_ray_gives_the_local_paths_codes(ray_cluster, service, penn_index, shared_fs):
    service.accept(crops(penn_index, 12))
    items = pending_items(service)
    local = by_id(LocalEngine(service.pipeline, service.limits).run(items))
    with RayEngine(service.pipeline.source, service.limits, address="local", workers=2, shared_fs=shared_fs,
                   batch_size=3) as engine:  # fmt: skip
        remote = by_id(engine.run(items))
    assert sorted(remote) == sorted(local) == sorted(i.ref_id for i in items)
    for ref_id, r in remote.items():
        want = local[ref_id]
        assert r.error is None and want.error is None and not r.retry
        np.testing.assert_allclose(r.float_code, want.float_code, atol=1e-5)
        differing = np.unpackbits(r.binary_code ^ want.binary_code).sum()
        assert differing <= 2, f"reference {ref_id}: {differing} binary bits differ"


def test_an_encoder_killed_mid_job_still_indexes_each_reference_once(ray_cluster, service, penn_index):
    service.accept(crops(penn_index, 24, skip=12))
    items = pending_items(service)
    with RayEngine(service.pipeline.source, service.limits, address="local", workers=2, batch_size=2) as engine:
        before = engine.actor_pids()
        killed: list[int] = []

        def feed() -> Iterator[EncodeItem]:
            for n, item in enumerate(items):
                if n == 8:  # 4 batches are in flight: kill the first actor's process while it encodes
                    os.kill(before[0], signal.SIGKILL)
                    killed.append(before[0])
                yield item

        done = encode_and_complete(service, feed(), engine, batch=5)
        after = engine.actor_pids()
    assert killed and after[0] != before[0] and after[1] == before[1]  # the killed actor was restarted
    ids = sorted(i.ref_id for i in items)
    assert done == len(ids)
    assert service.store.count("indexed") == len(ids) and service.store.count("pending") == 0
    assert service.collection.size == len(ids)
    adds = collections.Counter(c.ref_id for c in service.store.changes_since(0) if c.op == "add")
    assert sorted(adds) == ids and set(adds.values()) == {1}


def test_a_batch_lost_for_good_raises_after_completing_what_came_back(ray_cluster, service, penn_index):
    """No restarts: the killed actor's batches fail, the job raises, and nothing that came back is lost;
    a second run completes the rest, so every reference ends indexed exactly once."""
    service.accept(crops(penn_index, 16, skip=50))
    items = pending_items(service)
    with RayEngine(service.pipeline.source, service.limits, address="local", workers=2, batch_size=2,
                   max_restarts=0, max_task_retries=0) as engine:  # fmt: skip
        pids = engine.actor_pids()

        def feed() -> Iterator[EncodeItem]:
            for n, item in enumerate(items):
                if n == 8:  # one batch has come back, four are in flight
                    os.kill(pids[0], signal.SIGKILL)
                yield item

        with pytest.raises(RayEngineError, match="failed after its retries"):
            encode_and_complete(service, feed(), engine, batch=1)  # each result completed as it arrives
    first = service.store.count("indexed")
    assert 0 < first < len(items) and service.store.count("pending") == len(items) - first
    with RayEngine(service.pipeline.source, service.limits, address="local", workers=2) as engine:
        assert encode_and_complete(service, pending_items(service), engine) == len(items) - first
    adds = collections.Counter(c.ref_id for c in service.store.changes_since(0) if c.op == "add")
    assert sorted(adds) == sorted(i.ref_id for i in items) and set(adds.values()) == {1}
    assert service.collection.size == len(items)


def test_a_bad_image_becomes_a_failed_row(ray_cluster, service, penn_index):
    accepted = service.accept(crops(penn_index, 6, skip=40))
    corrupt, missing, *good = accepted.reference_ids
    service.image_path(corrupt).write_bytes(b"this is not a JPEG")
    service.image_path(missing).unlink()
    engine = make_engine(service, ray="local", workers=2)  # what `geoloc ingest --ray local` builds
    try:
        assert isinstance(engine, RayEngine) and len(engine.actor_pids()) == 2
        done = encode_and_complete(service, pending_items(service), engine, batch=4)
    finally:
        engine.close()
    assert done == len(good)
    rows = service.store.get_many(accepted.reference_ids)
    assert rows[corrupt].status == "failed" and rows[corrupt].error
    assert rows[missing].status == "failed" and "missing" in rows[missing].error
    assert all(rows[i].status == "indexed" for i in good)
    assert service.collection.size == len(good)


def test_a_pool_larger_than_the_cluster_times_out_with_a_clear_error(ray_cluster, fitted_models):
    from app.engine.imageio import ImageLimits
    from app.engine.pipeline import PipelineSource

    source = PipelineSource.default(fitted_models, CONFIG)
    with pytest.raises(RayEngineError, match="timed out .* the encoder pool to start .* 2 CPUs"):
        RayEngine(source, ImageLimits(), address="local", workers=3, shared_fs=True, start_timeout_s=8)
    # the pool was removed: the 2 CPUs are free again for the next engine
    with RayEngine(source, ImageLimits(), address="local", workers=2, shared_fs=True) as engine:
        assert len(engine.actor_pids()) == 2


def test_the_shipped_package_loads_the_same_pipeline(tmp_path, fitted_models):
    from app.engine.pipeline import PipelineSource
    from app.ingestion.encoding.ray import PipelinePackage, model_files

    source = PipelineSource.default(fitted_models, CONFIG)
    package = PipelinePackage.of(source)
    assert "squeezenet1_1.onnx" in package.files and f"pipelines/{CONFIG}/pipeline.json" in package.files
    unpacked = package.unpack(tmp_path / "actor")
    assert unpacked.load().fingerprint == source.load().fingerprint
    with pytest.raises(RayEngineError, match="no fitted pipeline"):
        model_files(PipelineSource.default(fitted_models, "hybrid"))  # never fitted in the test models dir
