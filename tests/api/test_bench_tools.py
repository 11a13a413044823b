"""The benchmark commands the README shows run on real photos with tiny budgets: each prints its table
(the figures themselves are measured on demand, never asserted here)."""

import subprocess
import sys

import pytest

from tests.api.conftest import CONFIG


def bench(*args: str) -> str:
    p = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, f"{' '.join(args)} failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    return p.stdout


def test_compare_configs_interleaves_two_servers(fitted_models, mini_manifest):
    out = bench(
        "bench.compare_configs", "--configs", f"{CONFIG},{CONFIG}:rerank=false", "--models-dir", str(fitted_models),
        "--manifest", str(mini_manifest), "--reps", "1", "--limit", "2", "--no-doc",
    )  # fmt: skip
    rows = [line for line in out.splitlines() if line.startswith(f"| {CONFIG}")]
    assert len(rows) == 2 and rows[0].split("|")[4].strip() == "1.00"  # the first is the baseline
    assert rows[1].startswith(f"| {CONFIG}:rerank=false (") and rows[1].split("|")[6].strip() == "0.0"  # none verified
    assert all("float flat" in r for r in rows)  # each side's index kinds, as its /ready names them


def test_ingest_resume_compares_with_and_without_the_journal(fitted_models):
    out = bench("bench.ingest_resume", "--models-dir", str(fitted_models), "--config", CONFIG, "--limit", "3",
                "--repeat", "1")  # fmt: skip
    assert "added" in out and "no journal / journal = " in out


@pytest.mark.ray
def test_ingest_speed_local_and_ray(fitted_models):
    out = bench(
        "bench.ingest_speed", "--models-dir", str(fitted_models), "--config", CONFIG, "--photos", "2",
        "--crops", "3", "--repeat", "1", "--workers", "1", "2", "--split-images", "2",
    )  # fmt: skip
    assert "| photos | 2 |" in out and "| crops | 3 |" in out and "Per-image cost" in out


def test_crafted_uploads_reports_peak_and_answer_time(fitted_models, mini_manifest):
    out = bench(
        "bench.crafted_uploads", "--models-dir", str(fitted_models), "--config", CONFIG, "--only", "49000x32",
        "--manifest", str(mini_manifest),
    )  # fmt: skip
    assert "| 49000x32 png | 422 |" in out and "Worst of all shapes" in out
