"""Allocator tuning: applied on glibc (this machine, the Docker image), skippable by environment."""

import platform

import pytest

from app.runtime import tune_malloc


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")
def test_glibc_accepts_the_fixed_thresholds():
    assert tune_malloc() is True


def test_can_be_turned_off(monkeypatch):
    monkeypatch.setenv("GEOLOC_MALLOC_TUNING", "0")
    assert tune_malloc() is False
