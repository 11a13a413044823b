"""Allocator tuning: applied on glibc (this machine, the Docker image), skippable by environment."""

import os
import platform

import pytest

from app.runtime import tune_malloc


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")
def test_glibc_accepts_the_fixed_thresholds():
    assert tune_malloc() is True


def test_can_be_turned_off(monkeypatch):
    monkeypatch.setenv("GEOLOC_MALLOC_TUNING", "0")
    assert tune_malloc() is False


def _blas_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}


@pytest.fixture
def restored_blas():
    """Whatever these tests set, the rest of the session gets the BLAS threads it had."""
    import numpy  # noqa: F401  (its BLAS is the one limited)

    before = _blas_threads()
    assert before, "numpy's BLAS is visible to threadpoolctl"
    yield
    assert _blas_threads() == before


def test_serving_uses_one_blas_thread_and_a_fit_gets_every_core(restored_blas):
    from threadpoolctl import threadpool_limits

    from app.runtime import all_blas_threads, serving_blas_threads

    with threadpool_limits(limits=None):  # undone at the end, as the fixture checks
        assert serving_blas_threads() == 1
        assert _blas_threads() == {1}
        with all_blas_threads():
            assert _blas_threads() == {os.cpu_count()}
        assert _blas_threads() == {1}, "the serving limit is back after the fit"


def test_blas_threads_can_be_set(monkeypatch, restored_blas):
    from threadpoolctl import threadpool_limits

    from app.runtime import serving_blas_threads

    monkeypatch.setenv("GEOLOC_BLAS_THREADS", "2")
    with threadpool_limits(limits=None):
        assert serving_blas_threads() == 2 and _blas_threads() == {2}
