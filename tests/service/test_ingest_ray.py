"""`geoloc ingest SOURCE --ray local` as a user runs it: a manifest and a folder encoded on a real local Ray
instance give the same references and the same codes as the local path, all indexed."""

import shutil
import sqlite3

import numpy as np
import pytest

from tests.conftest import PENN
from tests.service.test_ingest import GPS_PHOTOS, ingest

pytestmark = [pytest.mark.ray, pytest.mark.slow]


def stored(data) -> dict[str, tuple]:
    db = sqlite3.connect(data / "references.sqlite")
    try:
        rows = db.execute("SELECT sha256, lat, lon, label, status, float_code, binary_code FROM refs").fetchall()
        adds = db.execute("SELECT COUNT(*) FROM changes WHERE op='add'").fetchone()[0]
    finally:
        db.close()
    assert adds == len(rows)  # every reference reached the index exactly once
    return {r[0]: r[1:] for r in rows}


def test_manifest_and_folder_on_ray_match_the_local_path(tmp_path, fitted_models, mini_manifest):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in GPS_PHOTOS:
        shutil.copy(PENN / "photos" / name, folder / name)
    got = {}
    for engine, extra in (("local", ()), ("ray", ("--ray", "local", "--workers", "2"))):
        data = tmp_path / engine
        ingest(mini_manifest, data, fitted_models, "--split", "query", *extra)
        out = ingest(folder, data, fitted_models, *extra).stdout
        assert f"ingested {len(GPS_PHOTOS)} new references" in out
        got[engine] = stored(data)

    local, ray = got["local"], got["ray"]
    assert len(local) == 9 + len(GPS_PHOTOS)  # 3 query captures x (photo + 2 crops), then the folder
    assert local.keys() == ray.keys()
    for sha, (lat, lon, label, status, fcode, bcode) in local.items():
        r = ray[sha]
        assert (lat, lon, label, status) == r[:4] and status == "indexed"
        assert np.allclose(np.frombuffer(fcode, np.float32), np.frombuffer(r[4], np.float32), atol=1e-5)
        bits = np.unpackbits(np.frombuffer(bcode, np.uint8) ^ np.frombuffer(r[5], np.uint8)).sum()
        assert bits <= 2  # a sign flip where a projection sits on zero, nothing more
