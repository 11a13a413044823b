"""A sequence's capture times: given by the caller (ISO 8601, one per photo), else the photos' own EXIF
DateTimeOriginal, else none (the photos' order alone, under a step bound).

Why refuse rather than guess: times that cannot be parsed, or that go backwards in a sequence the caller
ordered, mean the order or the clock is wrong, and a motion model fed a wrong order forbids the true path.
A clear 4xx says which photo is out of place."""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path

from PIL import Image

from app.engine.imageio import read_exif_gps
from app.errors import InvalidRequest
from app.text import iso_captured_at


class TimesOutOfOrder(InvalidRequest):
    """Capture times that go backwards in a sequence given in order."""


def parse_time(text: str, n: int) -> datetime:
    """One given time (``n``: the photo's position, for the message); a date alone is refused (a walk's
    photos are minutes apart, not days)."""
    try:
        iso = iso_captured_at(text.strip())
    except ValueError as e:
        raise InvalidRequest(f"taken_at of image {n}: {e}") from None
    if len(iso) == 10:
        raise InvalidRequest(f"taken_at of image {n}: {iso!r} is a date without a time of day")
    return datetime.fromisoformat(iso)


def exif_time(data: bytes) -> datetime | None:
    """A photo's EXIF DateTimeOriginal (with its offset when the photo states one); None when absent,
    malformed or unreadable (the photo itself is judged when it is decoded)."""
    try:
        with Image.open(io.BytesIO(data)) as img:
            _, text = read_exif_gps(img)
    except Exception:  # not an image: said when it is decoded, with the image's own error
        return None
    if not text:
        return None
    try:
        iso = iso_captured_at(text)
    except ValueError:
        return None
    return datetime.fromisoformat(iso)


def seconds(times: Sequence[datetime | None]) -> list[float | None]:
    """Seconds since the first photo, or all None when any photo has no time. A sequence is read as one
    clock: a time without a zone (a camera writes the offset on some photos only) takes the zone of the
    sequence's first time that has one."""
    if not times or any(t is None for t in times):
        return [None] * len(times)
    zone = next((t.tzinfo for t in times if t.tzinfo is not None), None)
    times = [t if t.tzinfo is not None or zone is None else t.replace(tzinfo=zone) for t in times]
    first = times[0]
    return [(t - first).total_seconds() for t in times]


def check_order(secs: Sequence[float | None], source: str) -> None:
    """Refuse times that go backwards (equal times are a burst, allowed)."""
    for n in range(1, len(secs)):
        a, b = secs[n - 1], secs[n]
        if a is not None and b is not None and b < a:
            raise TimesOutOfOrder(
                f"the {source} times go backwards: image {n} was taken {a - b:.0f} s before image {n - 1}; give "
                "the images in the order they were taken, or send order=taken"
            )


def sequence_times(
    images: Sequence[Callable[[], bytes]], given: Sequence[str] | None, in_order: bool = True
) -> tuple[list[float | None], str]:
    """Each photo's time in seconds (all None: order only) and where the times come from (``given``,
    ``exif`` or ``order``). ``given``: one ISO 8601 time per photo, or None/empty for the EXIF times, read
    from each photo in turn (``images``: functions that read its bytes; one photo held at a time).
    ``in_order``: the caller says the photos are in the order taken, so times that go backwards are refused;
    else the caller orders them by these times (``taken_order``)."""
    if given:
        if len(given) != len(images):
            raise InvalidRequest(f"taken_at: give one per image or none ({len(given)} for {len(images)} images)")
        secs = seconds([parse_time(t, n) for n, t in enumerate(given)])
        if in_order:
            check_order(secs, "given")
        return secs, "given"
    secs = seconds([exif_time(read()) for read in images])
    if secs and secs[0] is not None:
        if in_order:
            check_order(secs, "EXIF")
        return secs, "exif"
    return secs, "order"


def taken_order(secs: Sequence[float | None]) -> tuple[list[int], list[float | None]]:
    """The photos' positions in the order they were taken, and their times from the first taken; photos
    without times keep the order they came in. Equal times (a burst) keep it too."""
    if not secs or secs[0] is None:
        return list(range(len(secs))), list(secs)
    order = sorted(range(len(secs)), key=lambda n: secs[n])
    first = secs[order[0]]
    return order, [secs[n] - first for n in order]


# -- files, folders, videos (the CLI) ----------------------------------------------------------------------
#: Image files a folder sequence reads (others are left out: a folder of a walk holds sidecars too).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff")
#: A video frame is scaled down to at most this many pixels before it is located (a 4K frame says no more
#: about a place than the pipeline's decode size, and would hold 25 MB while the frames are gathered).
VIDEO_FRAME_PIXELS = 2_000_000


class UnreadableVideo(InvalidRequest):
    """A video OpenCV cannot open or read a frame from."""


def folder_photos(folder: Path) -> list[Path]:
    """A folder's images by name: the sequence use case orders them by their EXIF times where every one has
    one (``taken_order``), else keeps this order."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def video_frames(
    path: Path, every_s: float, max_frames: int, max_pixels: int = VIDEO_FRAME_PIXELS
) -> tuple[list[bytes], list[float]]:
    """One frame every ``every_s`` seconds of a video, as JPEG bytes, and each frame's time in seconds;
    at most ``max_frames`` (a longer video is refused: sample it more sparsely), each at most ``max_pixels``.
    ``UnreadableVideo`` when OpenCV cannot open it or reads no frame."""
    import cv2

    if every_s <= 0:
        raise InvalidRequest(f"--every must be a positive number of seconds, not {every_s}")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise UnreadableVideo(f"{path.name}: OpenCV cannot open it as a video")
        fps = cap.get(cv2.CAP_PROP_FPS)
        if not fps or fps <= 0 or fps != fps:
            raise UnreadableVideo(f"{path.name}: the video states no frame rate")
        frames: list[bytes] = []
        times: list[float] = []
        n = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            t = n / fps
            n += 1
            if t + 1e-9 < len(frames) * every_s:
                continue
            if len(frames) == max_frames:
                raise InvalidRequest(
                    f"{path.name}: more than {max_frames} frames at one every {every_s:g} s; give a larger --every"
                )
            h, w = frame.shape[:2]
            if h * w > max_pixels:
                scale = (max_pixels / (h * w)) ** 0.5
                frame = cv2.resize(
                    frame, (max(1, int(w * scale)), max(1, int(h * scale))), interpolation=cv2.INTER_AREA
                )
            ok, jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 92])
            if not ok:
                raise UnreadableVideo(f"{path.name}: frame {n - 1} cannot be encoded")
            frames.append(jpeg.tobytes())
            times.append(t)
    finally:
        cap.release()
    if not frames:
        raise UnreadableVideo(f"{path.name}: OpenCV reads no frame from it (not a video, or a codec it lacks)")
    return frames, times
