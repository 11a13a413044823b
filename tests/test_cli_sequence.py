"""`geoloc locate --sequence` (files, a folder) and `--video` (a video the test makes from penn photos)."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from tests.test_cli import geoloc
from tests.walks import CONFIG


def _where(walk_collection):
    models, data, _ = walk_collection
    return ["--data-dir", str(data), "--models-dir", str(models), "--config", CONFIG]


def test_files_in_order(walk_collection):
    walk = walk_collection[2][:4]
    args = ["--top-k", "2", "--max-speed-mps", "1.5", "--max-step-m", "80"]
    out = json.loads(geoloc("locate", "--sequence", *map(str, walk), *args, *_where(walk_collection)).stdout)
    assert out["photos"] == [str(p) for p in walk]
    assert out["times_from"] == "exif"
    assert len(out["answers"]) == len(out["path"]) == 4
    assert all(a["rests_on"] in ("pixels", "sequence") and len(a["candidates"]) <= 2 for a in out["answers"])


def test_files_in_any_order_with_order_taken(walk_collection):
    """--order taken: files given against their time order are located in it, each answer naming its file;
    without it the same files are refused, and a bad value is said."""
    walk = walk_collection[2][:4]
    given = [walk[2], walk[0], walk[3], walk[1]]
    args = ["locate", "--sequence", *map(str, given)]
    out = json.loads(geoloc(*args, "--order", "taken", *_where(walk_collection)).stdout)
    assert out["photos"] == [str(p) for p in walk]
    assert out["images"] == [1, 3, 0, 2]
    assert out["times_from"] == "exif" and len(out["answers"]) == 4
    refused = geoloc(*args, *_where(walk_collection), check=False)
    assert refused.returncode != 0 and "go backwards" in refused.stdout + refused.stderr
    bad = geoloc(*args, "--order", "by name", *_where(walk_collection), check=False)
    assert bad.returncode != 0 and "--order must be sent or taken" in bad.stdout + bad.stderr


def test_a_folder_is_read_in_exif_time_order(tmp_path, walk_collection):
    walk = walk_collection[2][:4]
    folder = tmp_path / "walk"
    folder.mkdir()
    for n, p in enumerate(walk):  # names in the reverse of the time order
        shutil.copyfile(p, folder / f"{9 - n}.jpg")
    (folder / "notes.txt").write_text("not a photo")
    p = geoloc("locate", "--sequence", str(folder), "--brief", *_where(walk_collection))
    lines = p.stdout.strip().splitlines()
    assert [line.split(" ")[0].rsplit("/", 1)[-1] for line in lines] == ["9.jpg", "8.jpg", "7.jpg", "6.jpg"]
    assert all("(pixels)" in line or "(sequence)" in line for line in lines)


def _video(path, photos, fps=2, seconds_each=1):
    size = (320, 240)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for p in photos:
        frame = cv2.resize(cv2.imread(str(p)), size)
        for _ in range(fps * seconds_each):
            writer.write(frame)
    writer.release()


def test_a_video_every_second(tmp_path, walk_collection):
    video = tmp_path / "walk.avi"
    _video(video, walk_collection[2][:3])
    out = json.loads(geoloc("locate", "--video", str(video), "--every", "1", *_where(walk_collection)).stdout)
    assert out["times_from"] == "video"
    assert out["photos"] == ["frame at 0.0 s", "frame at 1.0 s", "frame at 2.0 s"]
    assert len(out["answers"]) == 3


def test_the_video_bound_in_frames(tmp_path):
    from app.usecases.sequence_inputs import video_frames

    video = tmp_path / "long.avi"
    size = (64, 48)
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    for n in range(100):
        writer.write(np.full((48, 64, 3), n, np.uint8))
    writer.release()
    frames, times = video_frames(video, 1.0, 20)
    assert len(frames) == 10 and times[1] == pytest.approx(1.0)
    with pytest.raises(Exception, match="more than 5 frames"):
        video_frames(video, 1.0, 5)
    frames, _ = video_frames(video, 5.0, 20, max_pixels=800)
    img = cv2.imdecode(np.frombuffer(frames[0], np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[0] * img.shape[1] <= 800


@pytest.mark.parametrize(
    "args, words",
    [
        (["--video", "{bad}", "--every", "1"], "OpenCV"),
        (["--video", "{bad}", "--every", "0"], "--every"),
        (["--sequence", "{photo}"], "at least 2 images"),
        (["--sequence", "{photo}", "{missing}"], "no such photo"),
    ],
)
def test_bad_sequences_fail_with_exit_2(tmp_path, args, words):
    bad = tmp_path / "not-a-video.mp4"
    bad.write_text("hello")
    photo = tmp_path / "a.jpg"
    photo.write_bytes(b"x")
    names = {"bad": bad, "photo": photo, "missing": tmp_path / "missing.jpg"}
    p = geoloc("locate", *[a.format(**names) for a in args], "--models-dir", str(tmp_path), check=False)
    assert p.returncode == 2, p.stdout + p.stderr
    assert words in p.stderr + p.stdout
