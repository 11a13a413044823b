"""A library's runs of photos read as walks (app/library/joint.py): on suggestions shaped as the scan
journals them (what the run places, what it never changes, which photos form a run, the geotagged photos as
one more term of the model), and on real photos: a scan of a held-out penn walk without GPS ends as the
sequence use case answers the same photos."""

from __future__ import annotations

import shutil
import subprocess
from datetime import datetime, timedelta, timezone

from app.domain import LocateOptions
from app.engine.calibration import Calibration
from app.engine.geo import haversine_m
from app.engine.sequence import Motion
from app.library.joint import ANCHOR_P, RUN_GAP_S, joint_suggestions, rested
from app.library.scan import ScanOptions, scan_library
from app.library.timeprior import Anchor
from app.storage.library import ACCEPTED, LOCATED, LibraryJournal
from app.usecases.sequence import SEQUENCE, sequence_answers
from app.usecases.sequence_inputs import sequence_times
from app.usecases.service import GeolocService
from tests.conftest import PENN
from tests.library.conftest import exiftool_ready
from tests.walks import CONFIG

T0 = datetime(2024, 9, 23, 16, 0, tzinfo=timezone(timedelta(hours=-4)))
CAMERA = "samsung SM-A315F"
#: Three places along a walk, about 60 m apart, and a look-alike 2 km away.
WALK = [(39.95200, -75.19300), (39.95250, -75.19290), (39.95300, -75.19280)]
ELSEWHERE = (39.97000, -75.19300)
#: The disc rule of a calibrated collection: evidence from 0.75 up gets a 35 m disc at 9 in 10; below it none.
CALIBRATION = Calibration(
    source="collection",
    disc={
        "rate": 0.9,
        "edges": [0.75],
        "radius_m": [None, 35.0],
        "n": [50, 50],
        "limit_m": 80.0,
        "max_radius_m": 100.0,
    },
)


def suggestion(n: int, p_right: float, p_wrong: float, seconds: float, camera: str | None = CAMERA, **kw) -> dict:
    """A located photo that its own answer leaves unplaced: the right place and a look-alike as candidates."""
    lat, lon = kw.pop("at", WALK[n % len(WALK)])
    return {
        "file": f"/lib/img_{n:03d}.jpg",
        "taken": (T0 + timedelta(seconds=seconds)).isoformat(),
        "camera": camera,
        "placed": False,
        "confident": False,
        "lat": None,
        "lon": None,
        "radius_m": None,
        "p": None,
        "basis": None,
        "reason_code": "ambiguous",
        "reason": "no disc holds for evidence this weak",
        "calibrated_candidates": [[lat, lon, p_right], [*ELSEWHERE, p_wrong]],
        **kw,
    }


def test_a_run_places_photos_each_too_weak_alone():
    results = [suggestion(n, 0.6, 0.3, 60 * n) for n in range(3)]
    changed = joint_suggestions(results, [], CALIBRATION)
    assert set(changed) == {r["file"] for r in results}
    for n, r in enumerate(results):
        new = changed[r["file"]]
        assert new["basis"] == SEQUENCE and new["placed"] and new["confident"]
        assert new["p"] >= 0.75 and new["radius_m"] >= 35.0 and new["reason"] is None
        assert haversine_m(new["lat"], new["lon"], *WALK[n]) < 1.0
        assert new["alone"]["reason_code"] == "ambiguous" and new["alone"]["placed"] is False
        assert new["calibrated_candidates"] == r["calibrated_candidates"]  # the evidence stays for the next run


def test_only_photos_close_in_time_of_one_camera_form_a_run():
    apart = [suggestion(n, 0.6, 0.3, (RUN_GAP_S + 1) * n) for n in range(3)]
    assert joint_suggestions(apart, [], CALIBRATION) == {}  # three runs of one photo: the photos alone
    cameras = [suggestion(n, 0.6, 0.3, 60 * n, camera=f"camera {n}") for n in range(3)]
    assert joint_suggestions(cameras, [], CALIBRATION) == {}
    untimed = [suggestion(n, 0.6, 0.3, 60 * n, taken=None) for n in range(3)]
    assert joint_suggestions(untimed, [], CALIBRATION) == {}
    nameless = [suggestion(n, 0.6, 0.3, 60 * n, camera=None) for n in range(3)]  # could be anyone's
    assert joint_suggestions(nameless, [], CALIBRATION) == {}


def test_a_run_that_cannot_walk_between_its_places_places_nothing():
    """Places 2 km apart 10 s apart: no path joins them at walking pace."""
    results = [suggestion(0, 0.6, 0.3, 0), suggestion(1, 0.6, 0.3, 10, at=ELSEWHERE), suggestion(2, 0.6, 0.3, 20)]
    changed = joint_suggestions(results, [], CALIBRATION)
    assert results[1]["file"] not in changed


def test_a_geotagged_photo_of_the_run_is_one_more_term():
    """One weak photo beside a geotagged photo of its camera a minute earlier, at the photo's right place;
    the same anchor 2 km away, or of another camera, gives nothing."""
    photo = suggestion(0, 0.5, 0.3, 60)
    near = Anchor(*WALK[0], T0, CAMERA)
    assert joint_suggestions([photo], [], CALIBRATION) == {}
    placed = joint_suggestions([photo], [near], CALIBRATION)[photo["file"]]
    assert placed["basis"] == SEQUENCE and haversine_m(placed["lat"], placed["lon"], *WALK[0]) < 1.0
    assert ANCHOR_P < 1.0  # a GPS fix is strong evidence, not certainty
    far = Anchor(39.99, -75.10, T0, CAMERA)
    assert joint_suggestions([photo], [far], CALIBRATION) == {}
    other = Anchor(*WALK[0], T0, "Apple iPhone 13")
    assert joint_suggestions([photo], [other], CALIBRATION) == {}


def test_confident_suggestions_are_never_changed_and_a_lost_placement_reverts():
    confident = suggestion(1, 0.6, 0.3, 60, placed=True, confident=True, lat=1.0, lon=2.0, basis="pixels")
    results = [suggestion(0, 0.6, 0.3, 0), confident, suggestion(2, 0.6, 0.3, 120)]
    changed = joint_suggestions(results, [], CALIBRATION)
    assert confident["file"] not in changed
    # A photo an earlier scan placed by its run, whose run no longer holds it (its neighbours gone): back to
    # its own suggestion, exactly.
    own = suggestion(3, 0.6, 0.3, 0)
    run = [own, suggestion(4, 0.6, 0.3, 60), suggestion(5, 0.6, 0.3, 120)]
    earlier = joint_suggestions(run, [], CALIBRATION)[own["file"]]
    assert earlier["basis"] == SEQUENCE
    assert joint_suggestions([earlier], [], CALIBRATION) == {own["file"]: own}
    assert rested(earlier, None) == own
    # The runs off, or a collection no longer calibrated: every placement of theirs goes back.
    placed = joint_suggestions(run, [], CALIBRATION)
    assert len(placed) == 3
    assert joint_suggestions(list(placed.values()), [], CALIBRATION, enabled=False) == {r["file"]: r for r in run}
    uncalibrated = Calibration.conservative("too small")
    assert joint_suggestions(list(placed.values()), [], uncalibrated) == {r["file"]: r for r in run}


def test_an_uncalibrated_collection_changes_nothing():
    results = [suggestion(n, 0.6, 0.3, 60 * n) for n in range(3)]
    assert joint_suggestions(results, [], Calibration.conservative("too small")) == {}


def test_a_scanned_walk_ends_as_the_sequence_use_case_answers_it(walk_collection, tmp_path):
    """The held-out walk's photos, GPS removed, scanned as a library against the calibrated walk collection:
    each photo's journalled evidence is its single answer's calibrated candidates, and what its run makes
    of it is what ``sequence_answers`` (POST /locate/sequence's model) makes of the same photos."""
    exiftool_ready()
    models, data, walk = walk_collection
    folder = tmp_path / "library"
    folder.mkdir()
    for p in walk:
        shutil.copyfile(p, folder / p.name)
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-gps:all=", *map(str, folder.iterdir())], check=True)
    service = GeolocService.open(data, models, CONFIG)
    journal = LibraryJournal(tmp_path / "journal")
    summary = scan_library(service, folder, ScanOptions(workers=1), journal)
    results = {r.path.rsplit("/", 1)[-1]: r.result for r in journal.photos(journal.scan_id_of(folder), LOCATED)}
    journal.close()
    assert summary.located == len(walk) == len(results)

    options = LocateOptions(top_k=10, rerank=False)
    singles = [service.locate(p.read_bytes(), options) for p in walk]
    times, times_from = sequence_times([p.read_bytes for p in walk], None)
    assert times_from == "exif"
    calibration = service.answer_calibration(options)
    assert calibration.calibrated
    answered = sequence_answers(singles, times, calibration, Motion(), options).photos
    for p, alone, photo in zip(walk, singles, answered, strict=True):
        r = results[p.name]
        own = [[c.lat, c.lon, round(c.p_within_25m, 4)] for c in alone.candidates if c.p_within_25m is not None]
        assert r["calibrated_candidates"] == own and own, p.name
        assert (r["basis"] == SEQUENCE) == (photo.rests_on == SEQUENCE), (p.name, r, photo.rests_on)
        if photo.rests_on == SEQUENCE:
            e = photo.answer.estimate
            assert (r["lat"], r["lon"], r["radius_m"]) == (round(e.lat, 7), round(e.lon, 7), round(e.radius_m, 1))
    assert summary.by_sequence == sum(photo.rests_on == SEQUENCE for photo in answered)


def _results(journal: LibraryJournal, folder) -> dict[str, dict]:
    return {r.path.rsplit("/", 1)[-1]: r.result for r in journal.photos(journal.scan_id_of(folder), LOCATED)}


def test_a_resumed_scan_reads_the_runs_as_a_fresh_one_and_a_decision_survives(walk_collection, penn_index, tmp_path):
    """The held-out walk without GPS between two geotagged photos of its phone (the captures just before and
    after it, in the collection): a scan stopped before its runs (``runs=False``, as a crash after the last
    photo leaves it) and scanned again, with nothing new to locate, ends as a fresh scan does; whatever the
    runs place is placed by the collection's rule; a reviewed photo keeps its decision; a scan without the
    time prior takes the runs' placements back. (Whether a run places a photo depends on how strongly the
    collection's calibration reads its neighbours: the synthetic tests above pin what a run places.)"""
    exiftool_ready()
    models, data, walk = walk_collection
    captures = [r for r in penn_index if r["photo"]]
    anchors = [PENN / captures[11]["photo"], PENN / captures[20]["photo"]]
    folder = tmp_path / "library"
    folder.mkdir()
    for p in walk:
        shutil.copyfile(p, folder / p.name)
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-gps:all=", *map(str, folder.iterdir())], check=True)
    for p in anchors:
        shutil.copyfile(p, folder / p.name)
    service = GeolocService.open(data, models, CONFIG)
    calibration = service.answer_calibration(LocateOptions(top_k=10, rerank=False))

    journal = LibraryJournal(tmp_path / "resumed")
    scan_library(service, folder, ScanOptions(workers=1, runs=False), journal)
    before = _results(journal, folder)
    assert len(before) == len(walk) and not any(r["basis"] == SEQUENCE for r in before.values())
    again = scan_library(service, folder, ScanOptions(workers=1), journal)
    assert again.located == 0 and again.references == 2
    after = _results(journal, folder)
    placed = sorted(n for n, r in after.items() if r["basis"] == SEQUENCE)
    for name in placed:
        r, own = after[name], before[name]
        assert r["confident"] and r["placed"] and calibration.estimate_disc(r["p"]) is not None
        assert not own["confident"] and r["alone"] == {k: own.get(k) for k in r["alone"]}
    for name in set(after) - set(placed):
        assert after[name] == before[name]

    fresh = LibraryJournal(tmp_path / "fresh")
    summary = scan_library(service, folder, ScanOptions(workers=1), fresh)
    assert _results(fresh, folder) == after and summary.by_sequence == len(placed)

    # A reviewed photo keeps its decision through later scans; without the time prior the runs' placements
    # go back to the photos' own suggestions (the reviewed one stays as reviewed).
    sid = journal.scan_id_of(folder)
    # The reviewed photo: one the runs placed, else one the user places at its best candidate.
    reviewed = placed[0] if placed else sorted(after)[0]
    at = after[reviewed]
    lat, lon = (at["lat"], at["lon"]) if at["lat"] is not None else at["calibrated_candidates"][0][:2]
    decided = next(r for r in journal.photos(sid, LOCATED) if r.path.endswith(reviewed))
    journal.decide(decided.id, ACCEPTED, lat, lon)
    scan_library(service, folder, ScanOptions(workers=1, time_prior=False), journal)
    final = _results(journal, folder)
    assert final[reviewed] == after[reviewed]
    assert all(final[n] == before[n] for n in set(before) - {reviewed})
    assert next(r for r in journal.photos(sid, LOCATED) if r.id == decided.id).decision == ACCEPTED
    journal.close()
    fresh.close()
