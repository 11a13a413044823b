"""The time prior: a photo taken minutes before or after geotagged photos of the same
camera was most likely taken near them; people walk at about 1.4 m/s.

Why this shape: the prior never overrides the pixels. It is a disc (a centre and a radius growing with the
time gap), and it does two things only:

- it confirms a confident visual answer that lies inside it (the answer then rests on pixels and time);
- it rescues an unconfident visual answer whose candidates inside the disc agree on one place (the fused
  estimate of those candidates alone, confident when at least ``MIN_SUPPORT`` of them agree): "pixels and
  time";
- with no visual candidate inside it, a tight disc (a same-camera photo within ``TIME_ONLY_S``) gives a
  position resting on time alone, stated with that disc's radius and never called confident.

Cameras are matched on EXIF Make + Model when both photos state them; a photo without a camera is compared
with every photo. A photo without DateTimeOriginal has no prior. Offsets: a time with its EXIF offset is
compared in UTC; two naive times are compared as they are (one camera's clock); an aware time is never
compared with a naive one (the clocks' zones are unknown)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from app.engine.geo import haversine_m

#: Only geotagged photos this close in time inform the prior.
WINDOW_S = 10 * 60.0
#: Walking speed: the prior's radius grows by this per second of gap.
SPEED_M_S = 1.4
#: The prior's radius is never smaller than this (GPS error of the neighbour itself).
FLOOR_M = 25.0
#: A position on time alone needs a same-camera neighbour this close in time.
TIME_ONLY_S = 60.0
#: Candidates inside the disc that must agree for the prior to rescue a visual answer.
MIN_SUPPORT = 2


@dataclass(frozen=True)
class Anchor:
    """A geotagged photo of the library: where and when, by which camera."""

    lat: float
    lon: float
    taken: datetime
    camera: str | None


@dataclass(frozen=True)
class Prior:
    lat: float
    lon: float
    radius_m: float
    gap_s: float  # the nearest anchor's time gap
    anchors: int  # anchors within the window
    same_camera: bool

    def as_dict(self) -> dict:
        return {
            "lat": round(self.lat, 7),
            "lon": round(self.lon, 7),
            "radius_m": round(self.radius_m, 1),
            "gap_s": round(self.gap_s, 1),
            "anchors": self.anchors,
            "same_camera": self.same_camera,
        }


def _gap_s(a: datetime, b: datetime) -> float | None:
    if (a.tzinfo is None) != (b.tzinfo is None):
        return None
    return abs((a - b).total_seconds())


def time_prior(taken: datetime | None, camera: str | None, anchors: Sequence[Anchor]) -> Prior | None:
    """The prior of a photo taken at ``taken`` by ``camera``, or None (no time, or no anchor in the window).

    Same-camera anchors are used when there are any in the window; else every anchor (another person of the
    same walk). The centre is the nearest anchor in time (the walk's last known point), the radius
    ``FLOOR_M + SPEED_M_S * gap``."""
    if taken is None:
        return None
    near = [(g, a) for a in anchors if (g := _gap_s(taken, a.taken)) is not None and g <= WINDOW_S]
    if not near:
        return None
    same = [(g, a) for g, a in near if camera and a.camera == camera]
    pool = same or near
    gap, best = min(pool, key=lambda p: p[0])
    return Prior(best.lat, best.lon, FLOOR_M + SPEED_M_S * gap, gap, len(pool), bool(same))


def inside(prior: Prior, lat: float, lon: float) -> bool:
    return float(haversine_m(prior.lat, prior.lon, lat, lon)) <= prior.radius_m


def time_only_radius(prior: Prior) -> float | None:
    """The radius of a position on time alone, when the prior is tight enough to state one."""
    if prior.same_camera and prior.gap_s <= TIME_ONLY_S:
        return prior.radius_m
    return None
