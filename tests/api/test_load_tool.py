"""bench/load.py against a real server: a few seconds, bounded, so the tool itself cannot rot.
The figures it prints are not checked (they belong to docs/benchmarks.md, not to a test)."""

import pytest

from app.manifests import read_manifest
from bench.load import format_report, run_load
from tests.api.conftest import Server


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    with Server(tmp_path_factory.mktemp("load") / "data", fitted_models) as s:
        yield s


def test_mixed_load_is_served_without_errors(server, mini_manifest):
    rows = read_manifest(mini_manifest)
    report = run_load(
        server.url, clients=2, seconds=4, locate_share=0.5, max_requests=30, api_key=server.api_key, rows=rows, seed=1
    )
    summary = report.summary()
    assert 0 < summary["requests"] <= 30
    assert summary["errors"] == {}, summary
    assert set(summary["ops"]) == {"/locate", "/references"}
    assert summary["rss_before_mb"] > 0 and summary["rss_after_mb"] > 0
    # every accepted reference is distinct (the pool defeats de-duplication) and ends up indexed
    accepted = summary["ops"]["/references"]["ok"]
    listed = server.client.get("/references", params={"limit": 1}).json()["total"]
    assert listed == accepted
    assert "req/s" in format_report(summary)


def test_refuses_a_non_loopback_target(mini_manifest):
    with pytest.raises(SystemExit, match="loopback"):
        run_load("http://192.0.2.1:8000", clients=1, seconds=1, rows=read_manifest(mini_manifest))
