"""Allocator tuning: applied on glibc (this machine, the Docker image), skippable by environment (read by
Settings, passed to app.runtime)."""

import os
import platform
import subprocess
import sys

import pytest

from app.runtime import tune_malloc
from app.settings import Settings
from tests.conftest import REPO


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")
def test_glibc_accepts_the_fixed_thresholds():
    assert tune_malloc() is True


def test_can_be_turned_off(monkeypatch):
    monkeypatch.setenv("GEOLOC_MALLOC_TUNING", "0")
    assert tune_malloc(Settings().malloc_tuning) is False


def _blas_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    # The process-wide pools only (numpy's OpenBLAS): an OpenMP-built BLAS (faiss ships one) keeps a limit
    # per thread, so another thread reads its own default there whatever the main thread set.
    return {
        i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas" and i.get("threading_layer") != "openmp"
    }


@pytest.fixture
def restored_blas():
    """Whatever these tests set, the rest of the session gets the BLAS threads it had."""
    import numpy  # noqa: F401  (its BLAS is the one limited)

    before = _blas_threads()
    assert before, "numpy's BLAS is visible to threadpoolctl"
    yield
    assert _blas_threads() == before


def _openmp_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"}


def test_serving_uses_one_blas_thread_and_a_fit_one_blas_and_openmp_thread(restored_blas):
    """A fit's numerics run on FIT_THREADS threads whatever the machine (the same fit everywhere).
    In a fresh interpreter: the thread limits are process state, and the suite's earlier tests (faiss's and
    scikit-learn's OpenMP runtimes loaded and limited in other orders) left the OpenMP limit at 1."""
    if not os.environ.get("GEOLOC_TEST_FRESH_PROCESS"):
        name = "tests/test_runtime.py::test_serving_uses_one_blas_thread_and_a_fit_one_blas_and_openmp_thread"
        env = {**os.environ, "GEOLOC_TEST_FRESH_PROCESS": "1"}
        p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", name], env=env,
                           capture_output=True, text=True, timeout=300, cwd=REPO)  # fmt: skip
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
        return
    import sklearn.cluster  # noqa: F401  (loads scikit-learn's OpenMP runtime)
    from threadpoolctl import threadpool_limits

    from app.runtime import FIT_THREADS, fit_threads, serving_blas_threads

    with threadpool_limits(limits=2):  # a machine with 2 threads for everything; undone at the end
        serving_blas_threads()
        assert _blas_threads() == {1}
        with fit_threads():
            assert _blas_threads() == {FIT_THREADS} and _openmp_threads() == {FIT_THREADS}
        assert _blas_threads() == {1}, "the serving limit is back after the fit"
        assert _openmp_threads() == {2}


def test_blas_threads_can_be_set(monkeypatch, restored_blas):
    from threadpoolctl import threadpool_limits

    from app.runtime import serving_blas_threads

    monkeypatch.setenv("GEOLOC_BLAS_THREADS", "2")
    with threadpool_limits(limits=None):
        assert serving_blas_threads(Settings().blas_threads) == 2 and _blas_threads() == {2}


def test_a_fit_on_another_thread_gets_its_threads(restored_blas):
    """The server sets the limit on its main thread and fits on its loader thread (the first start): the
    fit's limit must hold there too (threadpoolctl lets only one thread drive OpenBLAS's shared pool)."""
    import threading

    import sklearn.cluster  # noqa: F401
    from threadpoolctl import threadpool_limits

    from app.runtime import FIT_THREADS, fit_threads, serving_blas_threads

    seen: list[tuple[set[int], set[int]]] = []

    def fit() -> None:
        with fit_threads():
            seen.append((_blas_threads(), _openmp_threads()))
        seen.append((_blas_threads(), _openmp_threads()))

    with threadpool_limits(limits=2):
        serving_blas_threads()
        t = threading.Thread(target=fit)
        t.start()
        t.join()
        assert seen == [({FIT_THREADS}, {FIT_THREADS}), ({1}, {2})], seen
