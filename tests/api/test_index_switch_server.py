"""GEOLOC_INDEX_SWITCH_AT on a real server: uploads carry the collection past the
(lowered) threshold, /ready and /metrics say the exact kind serves and then the compressed kinds with
their parameters, every upload is found first before and after the switch, a delete is gone at once, and
a restart (clean stop: the final snapshot records the kinds) serves the compressed kinds without a
rebuild."""

import os
import re
import subprocess
import sys
import time
from pathlib import Path

from app.manifests import write_manifest
from tests.api.conftest import CONFIG, Server, wait_job
from tests.api.test_live_index import KEY, H, _locate, _upload, metric, rows  # noqa: F401  (rows: a fixture)

SWITCH_AT = 8


def _kinds(client) -> dict:
    return {part: s["kind"] for part, s in client.get("/ready").json()["index"].items()}


def _found_first(client, photos, ids) -> None:
    for row, ref_id in zip(photos, ids, strict=True):
        assert _locate(client, row.image, top_k=3)["candidates"][0]["reference_id"] == ref_id, row.image.name


def test_the_kind_switches_by_size_on_a_server(tmp_path, fitted_models, rows):  # noqa: F811
    data = tmp_path / "data"
    env = {"GEOLOC_INDEX_SWITCH_AT": str(SWITCH_AT)}
    with Server(data, fitted_models, api_key=KEY, extra_env=env) as s:
        first = _upload(s.client, rows[: SWITCH_AT - 1])
        wait_job(s.client, first["job_id"])
        ready = s.client.get("/ready").json()
        assert _kinds(s.client) == {"float": "flat", "binary": "flat"}
        assert ready["index_choice"] == f"exact below {SWITCH_AT} references, then ivf-rabitq / binary-ivf"
        assert re.search(
            r'^geoloc_index_kind\{.*kind="flat".*part="float".*\} 1\.0$', s.client.get("/metrics").text, re.M
        )
        ids = first["reference_ids"]
        _found_first(s.client, rows[:3], ids[:3])

        more = _upload(s.client, rows[SWITCH_AT - 1 : SWITCH_AT + 3])
        wait_job(s.client, more["job_id"])
        ids += more["reference_ids"]
        deadline = time.time() + 120
        while _kinds(s.client)["float"] == "flat" and time.time() < deadline:  # built in the background
            _found_first(s.client, rows[:1], ids[:1])  # answers keep coming meanwhile
            time.sleep(0.2)
        ready = s.client.get("/ready").json()
        assert _kinds(s.client) == {"float": "ivf-rabitq", "binary": "binary-ivf"}, ready
        assert ready["index_size"] == SWITCH_AT + 3 and "switched from exact" in ready["index_choice"]
        assert {"nlist", "nprobe", "shortlist"} <= set(ready["index"]["float"])
        assert ready["index"]["float"]["quantizer"] == "flat"  # exact list assignment (README)
        text = s.client.get("/metrics").text
        line = re.search(r'^geoloc_index_kind\{[^}]*part="float"[^}]*\} 1\.0$', text, re.M).group(0)
        f = ready["index"]["float"]
        for label, value in (
            ("kind", "ivf-rabitq"),
            ("nlist", f["nlist"]),
            ("nprobe", f["nprobe"]),
            ("shortlist", 100),
            ("quantizer", "flat"),
        ):
            assert f'{label}="{value}"' in line, line
        assert metric(s, "geoloc_index_kind_switches") == 1 and metric(s, "geoloc_index_switching") == 0
        _found_first(s.client, rows[: SWITCH_AT + 3 : 2], ids[::2])

        gone = ids[1]
        assert s.client.delete(f"/references/{gone}", headers=H).status_code == 200
        assert gone not in [c["reference_id"] for c in _locate(s.client, rows[1].image, top_k=10)["candidates"]]
    with Server(data, fitted_models, api_key=KEY, extra_env=env) as again:
        ready = again.client.get("/ready").json()
        assert ready["index_loaded"] == "snapshot" and ready["index_size"] == SWITCH_AT + 2
        assert _kinds(again.client) == {"float": "ivf-rabitq", "binary": "binary-ivf"}
        assert metric(again, "geoloc_index_full_rebuilds") == 0 and metric(again, "geoloc_index_kind_switches") == 0
        _found_first(again.client, rows[2 : SWITCH_AT + 3 : 3], ids[2::3])


def test_a_start_above_the_threshold_is_ready_only_with_the_compressed_kind(tmp_path, fitted_models, rows):  # noqa: F811
    """A data dir left exact above the threshold (here: served with the switch off, as after a bulk load or a
    restore without a snapshot) is not served by the exact search: /ready answers 200 once the compressed
    kinds serve and their snapshot is written, and says meanwhile how far their build is (the same lines go
    to the log)."""
    data = tmp_path / "data"
    with Server(data, fitted_models, api_key=KEY, extra_env={"GEOLOC_INDEX_SWITCH_AT": "0"}) as s:
        up = _upload(s.client, rows[: SWITCH_AT + 3])
        wait_job(s.client, up["job_id"])
        assert _kinds(s.client) == {"float": "flat", "binary": "flat"}
    ids = up["reference_ids"]
    with Server(data, fitted_models, api_key=KEY, extra_env={"GEOLOC_INDEX_SWITCH_AT": str(SWITCH_AT)}) as again:
        ready = again.client.get("/ready").json()  # the first 200 the start gave
        assert _kinds(again.client) == {"float": "ivf-rabitq", "binary": "binary-ivf"}, ready
        assert ready["index_loaded"] == "snapshot" and ready["index_size"] == SWITCH_AT + 3
        assert metric(again, "geoloc_index_kind_switches") == 1 and metric(again, "geoloc_index_switching") == 0
        # ...and its snapshot written before it served: no write of the new index beside the first requests
        assert metric(again, "geoloc_snapshot_writes") >= 1
        log = Path(again.log.name).read_text()
        said = log.index(f"building the index {SWITCH_AT + 3:,} references call for")
        assert said < log.index("index switched to") < log.index("ready: config")
        _found_first(again.client, rows[: SWITCH_AT + 3 : 3], ids[::3])
        more = _upload(again.client, rows[SWITCH_AT + 3 : SWITCH_AT + 5])
        wait_job(again.client, more["job_id"])
        _found_first(again.client, rows[SWITCH_AT + 3 : SWITCH_AT + 5], more["reference_ids"])
        gone = ids[0]
        assert again.client.delete(f"/references/{gone}", headers=H).status_code == 200
        assert gone not in [c["reference_id"] for c in _locate(again.client, rows[0].image, top_k=10)["candidates"]]


def test_a_bulk_ingest_past_the_threshold_leaves_the_compressed_kind_for_the_next_start(
    tmp_path,
    fitted_models,
    rows,  # noqa: F811
):
    """`geoloc ingest` ends with the kind the size calls for in its final snapshot: the next start loads it
    and serves at once, with no switch and no rebuild."""
    manifest = tmp_path / "some.csv"
    write_manifest(manifest, rows[: SWITCH_AT + 2])
    data = tmp_path / "data"
    env = {**os.environ, "GEOLOC_INDEX_SWITCH_AT": str(SWITCH_AT), "GEOLOC_ORT_THREADS": "1"}
    cmd = [sys.executable, "-m", "app.cli", "ingest", "--manifest", str(manifest), "--split", "db"]
    cmd += ["--config", CONFIG, "--data-dir", str(data), "--models-dir", str(fitted_models)]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    # said whether the switch ran at the end or after a batch meanwhile, and whatever the thread's timing
    said = f"index switched to float ivf-rabitq, binary binary-ivf at {SWITCH_AT + 2:,} references"
    assert said in run.stdout, run.stdout + run.stderr
    with Server(data, fitted_models, api_key=KEY, extra_env={"GEOLOC_INDEX_SWITCH_AT": str(SWITCH_AT)}) as s:
        ready = s.client.get("/ready").json()
        assert _kinds(s.client) == {"float": "ivf-rabitq", "binary": "binary-ivf"}, ready
        assert ready["index_loaded"] == "snapshot" and ready["index_size"] == SWITCH_AT + 2
        assert metric(s, "geoloc_index_kind_switches") == 0 and metric(s, "geoloc_index_full_rebuilds") == 0
        for row in rows[: SWITCH_AT + 2 : 3]:  # each photo's own reference first, from the loaded kind
            found = _locate(s.client, row.image, top_k=3)["candidates"][0]
            assert (found["lat"], found["lon"]) == (row.lat, row.lon) and found["score"] > 0.99, row.image.name
