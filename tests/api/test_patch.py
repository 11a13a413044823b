"""Edits: a duplicate upload with other metadata says it was not applied; PATCH changes metadata, and a
second process sees the new position at its next answer."""

import json

from app.manifests import read_manifest
from tests.api.conftest import Server, wait_job

KEY = "patch-key"
H = {"X-API-Key": KEY}


def test_duplicates_say_so_and_patch_edits(tmp_path, fitted_models, mini_manifest):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"][:4]
    data = tmp_path / "data"
    with Server(data, fitted_models, api_key=KEY) as s:
        c = s.client
        files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in rows]
        meta = [{"lat": r.lat, "lon": r.lon, "label": f"ref {n}"} for n, r in enumerate(rows)]
        acc = c.post("/references", files=files, data={"metadata": json.dumps(meta)}, headers=H).json()
        wait_job(c, acc["job_id"])
        ref = acc["reference_ids"][0]
        assert acc["notes"] == []
        # The same bytes with another position: the existing id, and a note that nothing changed.
        again = c.post(
            "/references", files=files[:1], data={"lat": rows[0].lat + 0.01, "lon": rows[0].lon}, headers=H
        ).json()
        assert again["reference_ids"] == [ref] and again["duplicates"] == [True]
        assert len(again["notes"]) == 1 and f"PATCH /references/{ref}" in again["notes"][0]
        assert c.get(f"/references/{ref}").json()["lat"] == rows[0].lat
        same = c.post("/references", files=files[:1], data={"lat": rows[0].lat, "lon": rows[0].lon}, headers=H)
        assert same.json()["notes"] == []  # nothing asked that differs: nothing to say

        with Server(data, fitted_models, api_key=KEY, worker="none") as other:
            q = [("image", ("q.jpg", rows[0].image.read_bytes(), "image/jpeg"))]
            before = other.client.post("/locate", files=q, data={"top_k": 1}).json()["candidates"][0]
            assert before["reference_id"] == ref and before["lat"] == rows[0].lat
            new = {"lat": rows[0].lat + 0.001, "lon": rows[0].lon - 0.001, "label": "College Hall", "heading": 90}
            assert c.patch(f"/references/{ref}", json=new).status_code == 401
            r = c.patch(f"/references/{ref}", json=new, headers=H)
            assert r.status_code == 200, r.text
            body = r.json()
            assert (body["lat"], body["lon"], body["label"], body["heading"]) == (
                new["lat"],
                new["lon"],
                "College Hall",
                90,
            )
            after = other.client.post("/locate", files=q, data={"top_k": 1}).json()["candidates"][0]
            assert (after["lat"], after["lon"], after["label"]) == (new["lat"], new["lon"], "College Hall")
        # Only the given fields change; a heading can be cleared.
        r = c.patch(f"/references/{ref}", json={"heading": None}, headers=H).json()
        assert r["heading"] is None and r["label"] == "College Hall"
        # Errors: unknown id, bad values, unknown fields, nothing to change.
        assert c.patch("/references/999999", json={"label": "x"}, headers=H).json()["error"] == "not_found"
        for bad in ({"heading": 400}, {"lon": "east"}, {"colour": "red"}, {}, {"lat": None}):
            r = c.patch(f"/references/{ref}", json=bad, headers=H)
            assert r.status_code == 422 and r.json()["error"] == "invalid_request", (bad, r.text)
        # A position out of range is invalid_position, as in an upload (one fault, one code).
        r = c.patch(f"/references/{ref}", json={"lat": 123}, headers=H)
        assert r.status_code == 422 and r.json()["error"] == "invalid_position", r.text
        assert c.get(f"/references/{ref}").json()["lat"] == new["lat"]
