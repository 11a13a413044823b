"""End to end over HTTP: add references, wait for the job, locate, delete, restart, locate again."""

import json

import pytest

from app.manifests import read_manifest
from tests.api.conftest import Server, wait_job
from tests.conftest import PENN

API_KEY = "test-key-123"


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    with Server(tmp_path_factory.mktemp("svc") / "data", fitted_models, api_key=API_KEY) as s:
        yield s


def _files(rows):
    return [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in rows]


def test_full_cycle_and_restart(server, mini_manifest, tmp_path):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    c = server.client
    meta = [{"lat": r.lat, "lon": r.lon, "label": r.image.name} for r in rows]
    r = c.post("/references", files=_files(rows), data={"metadata": json.dumps(meta)}, headers={"X-API-Key": API_KEY})
    assert r.status_code == 202, r.text
    body = r.json()
    assert len(body["reference_ids"]) == len(rows) and not any(body["duplicates"])
    job = wait_job(c, body["job_id"])
    assert job["status"] == "done" and job["indexed"] == len(rows)

    # The same bytes again: the existing id comes back, nothing is stored twice.
    again = c.post("/references", files=_files(rows[:1]), data={"lat": 1, "lon": 1}, headers={"X-API-Key": API_KEY})
    assert again.json()["reference_ids"] == body["reference_ids"][:1] and again.json()["duplicates"] == [True]

    # A photo with EXIF GPS and no position fields: the position comes from the photo.
    exif_photo = sorted((PENN / "photos").glob("*.jpg"))[40]  # not in the mini manifest
    r = c.post(
        "/references",
        files=[("image", ("x.jpg", exif_photo.read_bytes(), "image/jpeg"))],
        headers={"X-API-Key": API_KEY},
    )
    assert r.status_code == 202, r.text
    wait_job(c, r.json()["job_id"])
    exif_id = r.json()["reference_ids"][0]
    assert abs(c.get(f"/references/{exif_id}").json()["lat"] - 39.95) < 0.01

    query = next(r for r in rows if "/photos/" in str(r.image))
    loc = c.post("/locate", files=[("image", ("q.jpg", query.image.read_bytes(), "image/jpeg"))], data={"top_k": 5})
    assert loc.status_code == 200, loc.text
    res = loc.json()
    top = res["candidates"][0]
    assert top["label"] == query.image.name and top["score"] > 0.95
    assert res["mode"] == "two-stage" and res["index"]["size"] == len(rows) + 1
    assert res["features"]["extracted"] > 100
    assert {"queue", "decode", "cnn", "local_features", "search", "total"} <= set(res["timings_ms"])

    # Binary mode, a region that excludes the answer, a thumbnail without EXIF.
    assert (
        c.post("/locate", files=[("image", ("q.jpg", query.image.read_bytes()))], data={"mode": "binary"}).json()[
            "candidates"
        ][0]["reference_id"]
        == top["reference_id"]
    )
    far = c.post(
        "/locate", files=[("image", ("q.jpg", query.image.read_bytes()))], data={"lat": 0, "lon": 0, "radius_m": 100}
    ).json()
    assert far["candidates"] == [] and far["estimate"] is None and "region" in far["reason"]
    thumb = c.get(f"/references/{top['reference_id']}/image")
    assert thumb.status_code == 200 and thumb.headers["content-type"] == "image/jpeg"
    assert b"Exif" not in thumb.content[:200] and len(thumb.content) < 100_000

    # Delete: gone from search at once, and its image and metadata with it.
    assert c.delete(f"/references/{top['reference_id']}").status_code == 401
    d = c.delete(f"/references/{top['reference_id']}", headers={"X-API-Key": API_KEY})
    assert d.status_code == 200
    assert c.get(f"/references/{top['reference_id']}").status_code == 404
    after = c.post("/locate", files=[("image", ("q.jpg", query.image.read_bytes()))], data={"top_k": 5}).json()
    assert top["reference_id"] not in [x["reference_id"] for x in after["candidates"]]
    listing = c.get("/references", params={"limit": 100}).json()
    assert listing["total"] == len(rows)  # len(rows) + 1 added, 1 deleted
    # Paging by id: the same rows as by offset, the deleted id skipped, cursors that end; and backwards.
    by_offset = [r["id"] for r in listing["items"]]
    assert listing["next_after"] is None and listing["prev_before"] is None
    seen, cursor = [], {"after": 0}
    while cursor:
        page = c.get("/references", params={**cursor, "limit": 7}).json()
        assert page["total"] is None and page["offset"] is None and len(page["items"]) <= 7
        seen += [r["id"] for r in page["items"]]
        cursor = {"after": page["next_after"]} if page["next_after"] is not None else None
    assert seen == by_offset and top["reference_id"] not in seen
    last = c.get("/references", params={"before": 2**63 - 1, "limit": 7, "total": "true"}).json()
    assert [r["id"] for r in last["items"]] == by_offset[-7:] and last["next_after"] is None
    assert last["total"] == len(rows) and last["prev_before"] == by_offset[-7]
    back = c.get("/references", params={"before": last["prev_before"], "limit": 7}).json()
    assert [r["id"] for r in back["items"]] == by_offset[-14:-7] and back["next_after"] == by_offset[-8]
    lats = sorted(r["lat"] for r in listing["items"])
    lons = [r["lon"] for r in listing["items"]]
    box = f"{min(lons)},{lats[0]},{max(lons)},{lats[len(lats) // 2]}"  # the southern half
    in_box = [r["id"] for r in c.get("/references", params={"bbox": box, "limit": 500}).json()["items"]]
    assert 0 < len(in_box) < len(by_offset)
    boxed = c.get("/references", params={"bbox": box, "after": 0, "limit": 500}).json()
    assert [r["id"] for r in boxed["items"]] == in_box
    for bad in ({"after": 1, "before": 5}, {"after": 1, "offset": 2}, {"after": -1}):
        r = c.get("/references", params=bad)
        assert r.status_code == 422 and r.json()["error"] and r.json()["message"], (bad, r.text)

    # Stop, start again on the same data dir: same answer.
    server.stop()
    again_server = Server(server.data_dir, server.models_dir, api_key=API_KEY)
    try:
        again_server.wait_ready()
        re = again_server.client.post(
            "/locate", files=[("image", ("q.jpg", query.image.read_bytes()))], data={"top_k": 5}
        ).json()
        assert [x["reference_id"] for x in re["candidates"]] == [x["reference_id"] for x in after["candidates"]]
        assert [x["score"] for x in re["candidates"]] == pytest.approx([x["score"] for x in after["candidates"]])
        assert re["index"]["size"] == after["index"]["size"]
    finally:
        again_server.stop()


def test_health_metrics_openapi(tmp_path, fitted_models):
    s = Server(tmp_path / "data", fitted_models)
    try:
        ready = s.wait_ready()
        assert s.client.get("/health").json() == {"status": "ok"}
        assert ready["config"] == "hybrid-bin" and ready["worker"] == "in-process"
        # Which index kind serves each part, and its parameters (``VectorIndex.stats``).
        binary = ready["index"]["binary"]
        assert ready["index"]["float"]["kind"] == "flat" and binary["code_bytes"] == binary["dim"] // 8
        s.client.get("/references")
        text = s.client.get("/metrics").text
        labels = 'kind="flat",m="None",nlist="None",nprobe="None",part="binary",quantizer="None",shortlist="None"'
        assert f"geoloc_index_kind{{{labels}}} 1.0" in text
        for name in (
            "geoloc_http_requests_total",
            "geoloc_index_size",
            "geoloc_queue_depth",
            "process_resident_memory_bytes",
            "geoloc_http_request_seconds_bucket",
        ):
            assert name in text
        spec = s.client.get("/openapi.json").json()
        for path in (
            "/locate",
            "/references",
            "/references/{ref_id}",
            "/references/{ref_id}/image",
            "/jobs/{job_id}",
            "/health",
            "/ready",
            "/metrics",
        ):
            assert path in spec["paths"]
        assert {"400", "413", "415", "422"} <= set(spec["paths"]["/locate"]["post"]["responses"])
        assert "404" in spec["paths"]["/references/{ref_id}"]["delete"]["responses"]
    finally:
        s.stop()
