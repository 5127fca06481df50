"""Keyframes that wait to be described until the sensor has passed them: their trail ahead.

A revisit driven the other way comes along the far side of a place: its trail lies where the
first pass went on to, not where it came from, and the two trails share little (the open
campus of docs/results/trail.md lost reversed revisits as the trail grew). A keyframe whose
model has ``features.trail_ahead_m`` waits until odometry has carried the sensor that far past
it and is then described with the keyframes of those metres merged in as well, the same way as
those of its trail; both passes then hold both sides of the place. A walker's 3 m are about
two seconds of delay for its closures.

Only a keyframe that would be described with a trail waits (:class:`~vbrl_ros.features.trail.Trail`):
a dense or forward-looking scan, one without a pose and one that does not see all round are
described at once (after those before it: keyframes are described in order). A keyframe is
described with what came when the sensor is ``ahead_m`` past it, when a keyframe ``max_age``
after it comes (none later may join: the trail's own limit, so no candidate's submap holds
one), when the chain breaks (another session, a pose unknown, a dense scan), or at
:meth:`TrailAhead.flush` (the node's input fell silent or stops).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from vbrl_ros.features.blind_wedges import empty_bins, sees_around
from vbrl_ros.features.forward_trail import within_reach
from vbrl_ros.features.trail import MAX_TRAIL_KEYFRAMES, TRAIL_POINTS, placed, top_up_step

T = TypeVar("T")


@dataclass(frozen=True)
class _Waiting(Generic[T]):
    item: T  # what the caller gets back with the keyframe's trail ahead
    points: np.ndarray  # (n, 3) float32 in its own sensor frame
    pose: np.ndarray  # T_world_lidar
    travelled: float  # metres of odometry driven up to it since the chain began
    stamp: float
    waits: bool  # whether it is described with a trail ahead (else: as soon as those before it are)


class TrailAhead(Generic[T]):
    """Keyframes of one stream held until the keyframes of the next ``ahead_m`` metres have come.

    :meth:`add` takes a keyframe and returns, oldest first, ``(item, ahead)`` for every keyframe
    now due: ``ahead`` the points of the keyframes after it within reach, nearest first and
    filled up to ``TRAIL_POINTS`` as the trail is, each in that keyframe's own frame (empty for
    one that does not wait). ``ahead_m`` 0: every keyframe is due at once."""

    def __init__(self, ahead_m: float, max_age: float = math.inf) -> None:
        if not (math.isfinite(ahead_m) and ahead_m >= 0.0):
            raise ValueError(f"trail ahead must be a finite number of metres >= 0, got {ahead_m!r}")
        if not max_age >= 0.0:
            raise ValueError(f"trail ahead max_age must be >= 0, got {max_age!r}")
        self.ahead_m = float(ahead_m)
        self.max_age = float(max_age)
        self._waiting: deque[_Waiting[T]] = deque()
        self._session: str | None = None

    def __len__(self) -> int:
        """Keyframes waiting."""
        return len(self._waiting)

    def add(self, item: T, points: np.ndarray, pose: np.ndarray | None, session: str = "",
            stamp: float = math.nan) -> list[tuple[T, list[np.ndarray]]]:
        """Take a keyframe (``points`` (N, >=3) in its frame, ``pose`` T_world_lidar or None,
        ``stamp`` NaN: no age limit); the keyframes now due, oldest first."""
        known = pose is not None and bool(np.all(np.isfinite(pose)))
        chained = known and self.ahead_m > 0.0 and len(points) < TRAIL_POINTS
        due = []
        if not chained or session != self._session:  # nothing after it reaches back past it
            due = self.flush()
            self._session = session
        if not chained:
            return [*due, (item, [])]
        pose = np.array(pose, np.float64)  # kept: a copy, the caller may move its own along
        xyz = np.array(np.asarray(points)[:, :3], dtype=np.float32)  # the caller may reuse its buffer
        travelled = 0.0
        if self._waiting:
            last = self._waiting[-1]
            travelled = last.travelled + float(np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]))
        waits = len(xyz) > 0 and sees_around(empty_bins(xyz[:, :2]))
        self._waiting.append(_Waiting(item, xyz, pose, travelled, float(stamp), waits))
        newest = self._waiting[-1]
        while self._waiting and self._passed(self._waiting[0], newest):
            due.append(self._release())
        return due

    def flush(self) -> list[tuple[T, list[np.ndarray]]]:
        """Every waiting keyframe, oldest first, with what has come after it."""
        due = []
        while self._waiting:
            due.append(self._release())
        return due

    def _passed(self, keyframe: _Waiting[T], newest: _Waiting[T]) -> bool:
        """Whether no keyframe after ``newest`` can join ``keyframe``'s trail ahead: it is out of
        reach or too late, or those before it fill the cloud already (a slow sensor)."""
        return (not keyframe.waits
                or newest.travelled - keyframe.travelled > self.ahead_m
                or newest.stamp - keyframe.stamp >= self.max_age
                or len(self._waiting) > MAX_TRAIL_KEYFRAMES
                or sum(len(later.points[::step]) for later, step in self._taken(keyframe))
                + len(keyframe.points) >= TRAIL_POINTS)

    def _taken(self, keyframe: _Waiting[T]) -> Iterator[tuple[_Waiting[T], int]]:
        """The keyframes after ``keyframe`` that its trail ahead takes, nearest first, each with the
        step its points are taken by: all of them, but the last only tops the cloud up to
        ``TRAIL_POINTS``, as the trail does."""
        total, taken = len(keyframe.points), 0
        for later in self._waiting:
            step = top_up_step(len(later.points), total)
            if not step or taken == MAX_TRAIL_KEYFRAMES:
                return
            # "within reach" of the later one looking back: the trail's own test, turned round
            if later is keyframe or not within_reach(keyframe, later.travelled, later.pose, later.stamp,
                                                     self.ahead_m, self.max_age):
                continue
            yield later, step
            total += len(later.points[::step])
            taken += 1

    def _release(self) -> tuple[T, list[np.ndarray]]:
        keyframe = self._waiting.popleft()
        if not keyframe.waits:
            return keyframe.item, []
        to_keyframe = np.linalg.inv(keyframe.pose)
        return keyframe.item, [placed(later.points[::step], to_keyframe, later.pose)
                               for later, step in self._taken(keyframe)]
