"""Scripted motion as data: ``ActorScript`` (keyframes, still intervals, presence, posture,
gestures), the piecewise path it defines, and the people-in-a-room script of the ``hd4`` /
``hd4p`` presets.

A script says where an actor is when (keyframes through which a cubic spline runs), when it
stands exactly still (it decelerates into a keyframe and every body part stays identical until
the interval ends), when it is in the room (gaps: it left and came back), whether it sits, and
how much it gestures while not walking. Scripts live in ``SceneConfig.actor_scripts`` (and so
in gt/scene.json); ``build_scene`` turns them into ``motion.Actor`` objects.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline, PPoly

F64 = NDArray[np.float64]


Interval = tuple[float, float]
"""[start, stop) in frames."""


def _bad(name: str, value: Any, allowed: str) -> ValueError:
    return ValueError(f"{name} = {value!r} is invalid: {allowed}")


def _check_intervals(name: str, intervals: Sequence[Interval]) -> None:
    for i, iv in enumerate(intervals):
        if len(iv) != 2 or not iv[0] < iv[1]:
            raise _bad(f"{name}[{i}]", iv, "need (start, stop) with start < stop")
        if i and iv[0] <= intervals[i - 1][1]:
            raise _bad(name, intervals, "intervals must be increasing and separated")


@dataclass(frozen=True, kw_only=True)
class ActorScript:
    """The motion of one actor, as data: where it is when, when it stands still, when it is in
    the room, and how it holds itself. Frames are float frame times (``t = 0`` = first frame);
    positions are world floor coordinates, metres."""

    keys: tuple[tuple[float, float, float], ...]
    """Keyframes (frame, x, y), frames strictly increasing; the path is a cubic spline through
    them (natural ends, zero velocity where it meets a still interval). One key, or all keys at
    one place: the actor never walks."""
    still: tuple[Interval, ...] = ()
    """Intervals (start, stop) during which the actor stands exactly still: it decelerates
    into the key at frame ``start`` (there must be one), stays there (no key may lie in
    ``(start, stop]``), then walks on towards the next key (turning over ``turn_s``)."""
    present: tuple[Interval, ...] = ()
    """Intervals [enter, leave) of frames during which the actor is in the room, increasing and
    separated (gaps = it left and came back; put a key at a wall or door where it leaves and
    re-enters); () = from the first key to the end of the sequence."""
    posture: Literal["stand", "sit"] = "stand"
    """'sit': seated on a chair (a static box of the room, placed under it; the actor must
    never walk)."""
    facing_deg: float | None = None
    """Direction an actor that never walks faces, degrees about z (0 = +x); None = towards the
    rig's target."""
    gesture: float = 0.0
    """Talking gestures while not walking: forearm lifts up to this many radians, head turns
    up to half of it; 0 = none (a still actor then does not move at all)."""
    gesture_period_frames: float = 40.0
    """Main period of the gestures, frames (a second, slower component is mixed in)."""
    turn_s: float = 0.5
    """Time to turn from the standing direction to the new walking direction after a still
    interval, seconds."""

    def __post_init__(self) -> None:
        if not self.keys:
            raise _bad("keys", self.keys, "need at least one (frame, x, y)")
        for i, k in enumerate(self.keys):
            if len(k) != 3 or not all(math.isfinite(v) for v in k):
                raise _bad(f"keys[{i}]", k, "need finite (frame, x, y)")
            if i and not k[0] > self.keys[i - 1][0]:
                raise _bad("keys", self.keys, "frames must be strictly increasing")
        frames = [k[0] for k in self.keys]
        _check_intervals("still", self.still)
        for i, (a, b) in enumerate(self.still):
            if not any(abs(f - a) < 1e-9 for f in frames):
                raise _bad(f"still[{i}]", (a, b), f"needs a key at frame {a}")
            if any(a < f <= b for f in frames):
                raise _bad(f"still[{i}]", (a, b), "no key may lie inside a still interval")
        _check_intervals("present", self.present)
        if self.posture not in ("stand", "sit"):
            raise _bad("posture", self.posture, "'stand' or 'sit'")
        if self.posture == "sit" and (self.walks or self.still):
            raise _bad("posture", self.posture, "a seated actor must never walk (one place)")
        if not 0 <= self.gesture <= 1.5:
            raise _bad("gesture", self.gesture, "[0, 1.5] radians")
        if not self.gesture_period_frames > 0:
            raise _bad("gesture_period_frames", self.gesture_period_frames, "must be > 0")
        if not self.turn_s >= 0:
            raise _bad("turn_s", self.turn_s, "must be >= 0")

    @property
    def walks(self) -> bool:
        """Whether the keys are at more than one place."""
        xy = np.asarray([k[1:] for k in self.keys], float)
        return bool(np.ptp(xy, axis=0).max() > 0) if len(xy) > 1 else False

    def presence(self, num_frames: int) -> tuple[Interval, ...]:
        """The presence intervals, with the default (first key to the end) filled in."""
        if self.present:
            return tuple((float(a), float(b)) for a, b in self.present)
        return ((float(self.keys[0][0]), float(num_frames)),)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ActorScript:
        def pairs(v: Any) -> tuple[Any, ...]:
            return tuple(tuple(float(x) for x in item) for item in v)

        d = dict(d)
        for key in ("keys", "still", "present"):
            if key in d:
                d[key] = pairs(d[key])
        return cls(**d)


def scripted_path(times: F64, points: F64, still: Sequence[Interval]) -> PPoly:
    """Piecewise-cubic path through keyframes ``(times, points)`` that stands exactly still
    over the ``still`` intervals (validated by ``ActorScript``): cubic splines through the keys
    between them (natural ends; zero velocity into and out of a still interval) and constant
    pieces over them. One key: a constant path."""
    times = np.asarray(times, float)
    points = np.asarray(points, float)
    if len(times) == 1:
        c = np.zeros((4, 1, 2))
        c[3, 0] = points[0]
        return PPoly(c, np.array([times[0], times[0] + 1.0]))
    # Nodes: the keys, plus the end of each still interval (at the position it holds).
    node_t, node_p, hold_after = list(times), list(points), [False] * len(times)
    for a, b in sorted(still):
        i = int(np.argmin(np.abs(np.asarray(node_t) - a)))
        node_t.insert(i + 1, b)
        node_p.insert(i + 1, node_p[i])
        hold_after.insert(i + 1, False)
        hold_after[i] = True
    breaks: list[float] = [node_t[0]]
    coefs: list[F64] = []
    start = 0
    zero = np.zeros(2)
    for i in range(len(node_t)):
        end_of_run = i == len(node_t) - 1 or hold_after[i]
        if end_of_run and i > start:
            bc_start = (1, zero) if start > 0 and hold_after[start - 1] else (2, zero)
            bc_end = (1, zero) if hold_after[i] else (2, zero)
            spline = CubicSpline(
                node_t[start : i + 1], node_p[start : i + 1], bc_type=(bc_start, bc_end)
            )
            coefs.append(spline.c)
            breaks += list(node_t[start + 1 : i + 1])
        if hold_after[i]:
            c = np.zeros((4, 1, 2))
            c[3, 0] = node_p[i]
            coefs.append(c)
            breaks.append(node_t[i + 1])
            start = i + 1
    return PPoly(np.concatenate(coefs, axis=1), np.asarray(breaks))


#: The people-in-a-room script at 25 fps (world metres, the rig's target at the origin; the
#: four cameras stand towards the room's corners, so the +x wall is between cam0 and cam3):
#: actor 1 walks in and stands still at frames 30-180 (6 s), then walks on; actor 2 walks out
#: through the +x wall at frame 70 and comes back at frame 130; actor 3 sits on a chair,
#: talking (hand and head gestures), throughout.
ROOM_SCRIPTS = (
    ActorScript(
        keys=(
            (0.0, -1.1, 1.0),
            (14.0, -0.62, 0.62),
            (30.0, -0.15, 0.35),
            (200.0, 0.3, 0.75),
            (222.0, 0.85, 0.7),
            (250.0, 1.0, 0.05),
        ),
        still=((30.0, 180.0),),
    ),
    ActorScript(
        keys=(
            (0.0, 0.6, -0.5),
            (25.0, 1.4, -0.9),
            (50.0, 2.4, -0.6),
            (70.0, 3.3, -0.2),
            (130.0, 3.3, 0.2),
            (152.0, 2.3, -0.2),
            (176.0, 1.3, -0.5),
            (200.0, 0.45, -0.25),
            (225.0, 0.2, 0.4),
            (250.0, 0.5, 1.1),
        ),
        present=((0.0, 70.0), (130.0, 250.0)),
    ),
    ActorScript(
        keys=((0.0, -0.55, -0.65),), posture="sit", gesture=0.5, gesture_period_frames=40.0
    ),
)
#: Lights dim to 45 % over a second from frame 185, stay there 10 frames, recover by 245.
ROOM_LIGHTS = ((185.0, 1.0), (210.0, 0.45), (220.0, 0.45), (245.0, 1.0))
