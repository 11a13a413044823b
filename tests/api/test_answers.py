"""Knowing when it does not know, on a real server and real photos: a refit of a 21-photo
collection calibrates the confidence rule and p_within_25m on that collection, and with --calibrate-rerank a
second rule for verified answers (an uncalibrated pipeline gives none; a second refit once 6 are deleted
finds it too small and drops them again), a query whose place was removed gets no confident estimate, a San
Francisco street gets none against Penn, and a plain blue image gets no candidates and no probabilities,
with its own reason code. Every answer carries the collection's extent."""

import csv
import time

import cv2
import numpy as np
import pytest

from app.engine.geo import haversine_m
from app.manifests import Row, write_manifest
from tests.api.conftest import CONFIG, Server
from tests.conftest import PENN, SHARED
from tests.test_cli import geoloc

#: The query's own photo is not a reference; img_00008, 00009 and 00011 stand within 5 m of it.
QUERY = PENN / "photos" / "img_00010.jpg"
SF = SHARED / "data" / "sf-streetview-toy" / "queries" / "q4.jpg"
CODES = {None, "no_match", "ambiguous", "no_features", "no_references"}


@pytest.fixture(scope="module")
def collection(tmp_path_factory, fitted_models):
    """A data dir of the Penn photos among the first 23 rows of its index, without the query's (about 21),
    ingested by `geoloc ingest`."""
    with (PENN / "index.csv").open(newline="") as f:
        index = list(csv.DictReader(f))
    rows = [
        Row((PENN / r["photo"]).resolve(), float(r["lat"]), float(r["lon"]), "db", r["photo_id"])
        for r in index[:23]
        if r["photo"] and r["photo"] != "photos/img_00010.jpg"
    ]
    d = tmp_path_factory.mktemp("answers")
    write_manifest(d / "m.csv", rows)
    data = d / "data"
    common = ["--data-dir", str(data), "--models-dir", str(fitted_models)]
    out = geoloc("ingest", "--manifest", str(d / "m.csv"), "--split", "db", "--config", CONFIG, *common)
    assert 20 <= len(rows) <= 22 and f"ingested {len(rows)} new references" in out.stdout, out.stdout
    return data, rows, common, fitted_models


def _locate(server, path=None, data=None, rerank=False):
    data = data if data is not None else path.read_bytes()
    form = {"top_k": 10, **({"rerank": "true"} if rerank else {})}
    r = server.client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))], data=form)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["reason_code"] in CODES and (out["reason_code"] is None) == (out["estimate"] is not None)
    return out


def _refit(server, common, generation, *extra):
    out = geoloc("refit", "--calibration-sample", "600", *extra, *common)
    assert f"generation {generation}" in out.stdout, out.stdout
    _wait(server, generation)
    return out.stdout


def _wait(server, generation, timeout=120.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if server.client.get("/ready").json().get("generation") == generation:
            return
        time.sleep(0.2)
    raise TimeoutError(f"the server never switched to generation {generation}")


def test_a_refit_calibrates_on_the_collection_and_a_removed_place_is_not_confident(collection):
    data, rows, common, models = collection
    with Server(data, models, api_key="k") as s:
        s.client.headers["X-API-Key"] = "k"
        # The tests' pipeline was fitted without calibration: the conservative rule, no probabilities.
        before = _locate(s, QUERY)
        assert all(c["p_within_25m"] is None for c in before["candidates"])
        extent = before["index"]["extent"]
        assert extent["min_lat"] == pytest.approx(min(r.lat for r in rows), abs=1e-6)
        assert extent["max_lon"] == pytest.approx(max(r.lon for r in rows), abs=1e-6)

        stdout = _refit(s, common, 1, "--calibrate-rerank")
        assert f"calibration: fitted on {len(rows)} references of this collection" in stdout, stdout
        assert f"verified answers (rerank) by their own rule, {len(rows)} located with verification" in stdout
        here = _locate(s, QUERY)
        p_here = [c["p_within_25m"] for c in here["candidates"]]
        assert all(p is not None and 0 <= p <= 1 for p in p_here)
        # A verified answer is judged by the rule fitted on verified answers: its inliers count, so the same
        # references get other probabilities than in the plain answer.
        verified = _locate(s, QUERY, rerank=True)
        assert any(c["inliers"] is not None for c in verified["candidates"])  # verification ran
        plain_p = {c["reference_id"]: c["p_within_25m"] for c in here["candidates"]}
        both = [(plain_p[c["reference_id"]], c["p_within_25m"]) for c in verified["candidates"][:10]]
        both = [(a, b) for a, b in both if a is not None and b is not None]
        assert len(both) >= 5 and any(abs(a - b) > 1e-3 for a, b in both), both
        sf = _locate(s, SF)
        assert sf["estimate"] is None and sf["reason_code"] in ("no_match", "ambiguous")
        assert all(c["p_within_25m"] is not None for c in sf["candidates"])
        # The same photo searched within a region (here the whole extent: the same candidates): the same
        # decision, and a "not found" speaks of the region searched, not of the whole collection.
        box = ",".join(str(extent[k]) for k in ("min_lon", "min_lat", "max_lon", "max_lat"))
        files = [("image", ("q.jpg", SF.read_bytes(), "image/jpeg"))]
        r = s.client.post("/locate", files=files, data={"top_k": 10, "bbox": box})
        assert r.status_code == 200, r.text
        in_region = r.json()
        assert in_region["reason_code"] == sf["reason_code"] and "in this collection" not in in_region["reason"]
        assert sf["reason_code"] != "no_match" or "in the requested region" in in_region["reason"]

        # Remove every reference within 100 m of the query's place: it must not get a confident estimate.
        q = next(r for r in _penn_rows() if r["photo"] == "photos/img_00010.jpg")
        qlat, qlon = float(q["lat"]), float(q["lon"])
        refs = s.client.get("/references?limit=100").json()["items"]
        gone = [r["id"] for r in refs if haversine_m(qlat, qlon, r["lat"], r["lon"]) <= 100]
        assert 3 <= len(gone) < len(refs) - 10
        for i in gone:
            assert s.client.delete(f"/references/{i}").status_code in (200, 202, 204)
        absent = _locate(s, QUERY)
        assert absent["estimate"] is None and absent["reason_code"] in ("no_match", "ambiguous"), absent["reason"]
        assert not any(c["reference_id"] in gone for c in absent["candidates"])

        # A refit on the smaller collection recalibrates: below 16 references it is too small to calibrate,
        # says so, and the probabilities go (never another collection's figures): they changed with the
        # collection. (The conservative rule it falls back to, three candidates agreeing on one spot with 80 %
        # of the weight, is NOT enough to keep this absent place from a confident answer here: three
        # look-alikes 100-200 m away agree; see the README.)
        stdout = _refit(s, common, 2)
        left = len(refs) - len(gone)
        assert left < 16 and f"too small to calibrate ({left} references sampled" in stdout, stdout
        sf2 = _locate(s, SF)
        assert all(c["p_within_25m"] is None for c in sf2["candidates"]) and sf2["estimate"] is None
        again = _locate(s, QUERY)  # the conservative rule: no probabilities, whatever it decides
        assert all(c["p_within_25m"] is None for c in again["candidates"])
        assert again["estimate"] is not None or "too small to calibrate" in again["reason"], again


def _penn_rows():
    with (PENN / "index.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def test_a_plain_blue_image_gets_no_candidates_and_no_probabilities(collection):
    data, _, _, models = collection
    blue = np.zeros((480, 640, 3), np.uint8)
    blue[:] = (200, 120, 30)  # BGR: a clear-sky blue
    ok, jpg = cv2.imencode(".jpg", blue)
    assert ok
    with Server(data, models, api_key="k") as s:
        out = _locate(s, data=jpg.tobytes())
    assert out["reason_code"] == "no_features" and out["candidates"] == [] and out["estimate"] is None
    assert out["features"]["extracted"] < 8 and "no usable features" in out["reason"]
