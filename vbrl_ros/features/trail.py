"""A keyframe described with the keyframes of the last few metres merged in by odometry: its trail.

A hand-held Livox (2–3k points a scan) or a robot's voxel-thinned keyframe holds too little of
its place for one descriptor to pin it down. The keyframes of the last ``trail_m`` metres of
odometry are merged into the keyframe's own frame before it is described (odometry is good to
centimetres over a few metres), so it is described from a denser cloud of the same place. Of
1.5, 3 and 5 m, 3 m helped the hand-held recordings most (``vbrl eval --trail``,
docs/results/trail.md): a longer trail reaches where a revisit from another direction came from.

Only the keyframe's own blind wedges count: merged-in keyframes would fill part of the wedge a
mast hides, and the descriptor would then no longer hide its mirror image
(:mod:`.blind_wedges`), so merged points in the keyframe's blind wedges and their mirror images
are dropped. A forward-looking scan's last few metres lie behind it, outside what it sees, and
add what a revisit from ahead never saw; with ``forward_reach_m`` it is described with the
earlier keyframes of a longer trail that looked at where it stands instead
(:mod:`.forward_trail`). A dense scan (``TRAIL_POINTS``) that sees around is described alone:
it holds its place already, and merged it lost revisits in snow and fog; with
``fill_blind_wedges`` it still fills a blind wedge from the forward trail for its all-round cloud.
The trail fills a keyframe's cloud up to that count, so one just below it takes a few earlier
points, and its descriptor does not jump between two scans on either side of the count.

No trail holds a keyframe the keyframe may close a loop with, nor one a candidate's submap holds:
those ``max_age`` or more before it (half the node's ``exclude_recent_s``, as far as a submap
reaches; in evaluation, half P1's exclusion in scans) are not merged, or a short loop would be
closed by odometry carrying the earlier scan into the description (and into the verification
cloud of a forward-looking keyframe).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from vbrl_ros.features.blind_wedges import BINS, azimuth_bins, blind_runs, empty_bins, sees_around
from vbrl_ros.features.field_of_view import field_top
from vbrl_ros.features.forward_trail import ForwardTrail, within_reach

#: At most this many earlier keyframes are kept, however short their spacing.
MAX_TRAIL_KEYFRAMES = 40
#: Earlier keyframes are merged, nearest first, to fill the cloud up to this many points; a keyframe
#: as dense is described alone, in the time one scan takes. A spinning scan of 32 beams (24-32k
#: points of 32 x 1024 rays in the simulator, snow to clear) merged with a whole earlier scan
#: gained little in clear weather and lost revisits in snow and fog, whose flakes from the
#: earlier scan stand beside the keyframe's own and are no longer lone returns the clutter test
#: drops (simulated 32-beam car in snow: Recall@1 .991 alone, .924 trailed; docs/results/trail.md).
#: Filling up rather than merging whole scans keeps the descriptor from jumping at this count.
TRAIL_POINTS = 25_000
#: Within this horizontal range an earlier keyframe's point is kept only where another keyframe
#: confirms it (:func:`confirmed`): where rain, snow and fog return (the clutter test's 12 m).
CONFIRM_RANGE_M = 12.0
CONFIRM_VOXEL_M = 0.5
_Z_CELLS = 128  # heights beyond +-64 voxels share the top and bottom ones


class TrailClouds(NamedTuple):
    """What :meth:`Trail.clouds` returns for a keyframe."""

    described: np.ndarray  # the cloud it is described by
    all_round: np.ndarray | None  # the cloud it is also described by all round, or None
    # whether ``described`` sees all round by itself (blind_wedges.sees_all_round), where the trail
    # knows it from the keyframe's own points; None: not known here
    sees_all_round: bool | None = None


@dataclass(frozen=True)
class _Earlier:
    points: np.ndarray  # (n, 3) float32 in its own sensor frame
    pose: np.ndarray  # T_world_lidar
    travelled: float  # metres of odometry driven up to it
    stamp: float  # when it was taken (Trail.max_age's unit)


class Trail:
    """The earlier keyframes of one session within ``reach_m`` metres of travel, and of a
    forward-looking sensor those within ``forward_reach_m`` (0: described alone).

    :meth:`cloud` returns the cloud a keyframe is described by and then adds the keyframe to the
    trail. A keyframe without a usable pose, or from another session, starts the trail anew.
    """

    def __init__(self, reach_m: float, forward_reach_m: float = 0.0, max_age: float = math.inf,
                 fill_blind_wedges: bool = False) -> None:
        for name, value in (("trail reach", reach_m), ("forward trail reach", forward_reach_m)):
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number of metres >= 0, got {value!r}")
        if not max_age >= 0.0:
            raise ValueError(f"trail max_age must be >= 0, got {max_age!r}")
        self.reach_m = float(reach_m)
        self.max_age = float(max_age)
        self.fill_blind_wedges = bool(fill_blind_wedges) and forward_reach_m > 0.0
        self._earlier: deque[_Earlier] = deque()
        self._forward = ForwardTrail(forward_reach_m, max_age)
        self._session: str | None = None
        self._travelled = 0.0
        self._last_position: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._earlier)

    def clear(self) -> None:
        self._earlier.clear()
        self._forward.clear()
        self._travelled = 0.0
        self._last_position = None

    def cloud(self, points: np.ndarray, pose: np.ndarray | None, session: str = "",
              stamp: float = math.nan, ahead: Sequence[np.ndarray] = ()) -> np.ndarray:
        """``points`` (N, >=3) merged with the trail in their own frame, (M, 3); ``points`` itself
        when there is nothing to merge. ``pose``: T_world_lidar, None when unknown. ``stamp``: when
        it was taken; keyframes ``max_age`` or more before it are not merged (NaN: no limit).
        ``ahead``: as :meth:`clouds`'."""
        return self.clouds(points, pose, session, stamp, ahead)[0]

    def clouds(self, points: np.ndarray, pose: np.ndarray | None, session: str = "",
               stamp: float = math.nan, ahead: Sequence[np.ndarray] = ()) -> TrailClouds:
        """(:meth:`cloud`, the cloud it is described by all round or None, whether the first sees all
        round by itself or None): with ``fill_blind_wedges``, a keyframe with a blind wedge that the
        keyframes of its forward trail saw into (:func:`filling`) is also described all round
        (:mod:`vbrl_ros.index.all_round`). ``ahead``: the points of the keyframes after it, in its
        frame (:class:`~vbrl_ros.features.trail_ahead.TrailAhead`), merged as its trail's are."""
        if self.reach_m == 0.0 and self._forward.reach_m == 0.0:
            return TrailClouds(points, None)
        known = pose is not None and bool(np.all(np.isfinite(pose)))
        # a forward-looking keyframe has its own trail, whatever its density
        forward_trail_on = known and self._forward.reach_m > 0.0 and len(points) > 0
        empty = empty_bins(np.asarray(points)[:, :2].astype(np.float32)) if forward_trail_on else None
        forward = empty is not None and not sees_around(empty)
        # a dense keyframe is described alone and not kept: a trail of them would hold ~1 MB each
        usable = known and (forward or len(points) < TRAIL_POINTS)
        # but it may fill its blind wedge, and joins the forward trail thinned; the near trail starts anew
        dense_fill = known and self.fill_blind_wedges and not forward and len(points) >= TRAIL_POINTS
        if not (usable or dense_fill) or session != self._session:
            self.clear()
            self._session = session
            if not (usable or dense_fill):
                return TrailClouds(points, None)
        if dense_fill:
            self._earlier.clear()
        pose = np.array(pose, np.float64)  # kept: a copy, the caller may move its own along
        if self._last_position is not None:
            self._travelled += float(np.linalg.norm(pose[:3, 3] - self._last_position))
        self._last_position = pose[:3, 3].copy()
        self._forget_beyond_reach(pose, stamp)
        xyz = np.array(np.asarray(points)[:, :3], dtype=np.float32)  # a copy: the caller may reuse its buffer
        all_round, whole = None, None
        if forward:
            merged = self._forward_merged(xyz, pose, stamp)
        else:
            empty = empty_bins(xyz[:, :2]) if empty is None else empty
            parts, blind = self._near_parts(xyz, pose, empty)
            # a keyframe that does not see all round has no trail, and none ahead
            both = [*parts, *ahead] if sees_around(empty) else parts
            merged = None if len(both) == 1 else merged_confirmed(both, blind | np.roll(blind, BINS // 2))
            if self.fill_blind_wedges and blind.any():
                all_round = self._all_round(parts, blind, pose, stamp)
            # merging keeps every own point and adds where no blind bin is: no bin empties, none fills one
            whole = sees_around(empty) and not blind.any()
        if forward or self.fill_blind_wedges:
            self._forward.add(xyz, pose, self._travelled, stamp)
        if len(xyz) < TRAIL_POINTS:
            self._earlier.append(_Earlier(xyz, pose, self._travelled, stamp))
        while len(self._earlier) > MAX_TRAIL_KEYFRAMES:
            self._earlier.popleft()
        return TrailClouds(points if merged is None else merged, all_round, whole)

    def _all_round(self, parts: list[np.ndarray], blind: np.ndarray, pose: np.ndarray,
                   stamp: float) -> np.ndarray | None:
        """The keyframe (``parts[0]``) with its near trail and, in its ``blind`` bins, what its
        forward trail saw there; None when it saw nothing there. A run still empty (an open lot,
        a street with no end in range) is hidden with its mirror image when described, as any is."""
        forward = self._forward.merged(pose, self._travelled, stamp)
        keep = filling(forward.points, blind, parts[0])
        if not keep.any():
            return None
        points = np.concatenate([*parts, forward.points[keep]])
        keyframe_of = np.concatenate([keyframe_of_parts(parts), forward.keyframe_of[keep] + (len(parts) - 1)])
        return confirmed_cloud(points, keyframe_of)

    def _forward_merged(self, xyz: np.ndarray, pose: np.ndarray, stamp: float) -> np.ndarray | None:
        merged = self._forward.merged(pose, self._travelled, stamp, own=xyz)
        return None if not merged.keyframes else confirmed_cloud(merged.points, merged.keyframe_of)

    def _forget_beyond_reach(self, pose: np.ndarray, stamp: float) -> None:
        """Keep the earlier keyframes within reach both along the path and in a straight line (an
        odometry reset jumps without travelling), and younger than ``max_age``."""
        self._earlier = deque(e for e in self._earlier
                              if within_reach(e, self._travelled, pose, stamp, self.reach_m, self.max_age))

    def _near_parts(self, xyz: np.ndarray, pose: np.ndarray, empty: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """([the keyframe's points, the trail's points of each earlier keyframe...], its blind
        bins): the earlier keyframes nearest first, filling the cloud up to ``TRAIL_POINTS``."""
        blind = blind_runs(empty)
        if self.reach_m == 0.0 or not self._earlier or not len(xyz) or not sees_around(empty):
            return [xyz], blind
        to_keyframe = np.linalg.inv(pose)
        parts, total = [xyz], len(xyz)
        for earlier in reversed(self._earlier):  # nearest first
            step = top_up_step(len(earlier.points), total)
            if not step:
                break
            parts.append(placed(earlier.points[::step], to_keyframe, earlier.pose))
            total += len(parts[-1])
        return parts, blind


def top_up_step(count: int, total: int) -> int:
    """The step a trail takes a keyframe's ``count`` points by into a cloud of ``total`` points:
    1, but the last only tops the cloud up to ``TRAIL_POINTS`` (every k-th point), so a keyframe
    just below that count takes a few earlier points, not a whole scan and its flakes; 0: the
    cloud is full."""
    room = TRAIL_POINTS - total
    return 0 if room <= 0 else max(1, -(-count // room))  # an empty one: step 1


def placed(points: np.ndarray, to_keyframe: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Another keyframe's ``points`` (its frame; its ``pose`` T_world_lidar) in the keyframe's
    frame (``to_keyframe``: T_lidar_world), float32."""
    T = to_keyframe @ pose
    return (points @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def filling(points: np.ndarray, blind: np.ndarray, own: np.ndarray) -> np.ndarray:
    """(n,) bool: which of earlier keyframes' ``points`` (the keyframe's frame) lie in its
    ``blind`` azimuth bins and below the top of the field of view that saw its ``own`` points:
    what it would have seen there (a point above its top beam would stand in the height map where
    no keyframe of its own could put one)."""
    top = field_top(own)
    if not math.isfinite(top) or not len(points):
        return np.zeros(len(points), bool)
    horizontal = np.hypot(points[:, 0], points[:, 1])
    return blind[azimuth_bins(points[:, :2])] & (points[:, 2] <= math.tan(top) * horizontal)


def merged_confirmed(parts: list[np.ndarray], hidden: np.ndarray | None = None) -> np.ndarray:
    """The keyframe's points (``parts[0]``) with its trail's (the rest), each earlier point near
    the sensor only where another keyframe confirms it (:func:`confirmed`), and none in the
    azimuth bins ``hidden`` (the keyframe's blind wedges and their mirror images)."""
    return confirmed_cloud(np.concatenate(parts), keyframe_of_parts(parts), hidden)


def keyframe_of_parts(parts: list[np.ndarray]) -> np.ndarray:
    """(n,) int64: the part each point of ``parts``, concatenated, came from."""
    return np.repeat(np.arange(len(parts)), [len(p) for p in parts])


def confirmed_cloud(merged: np.ndarray, keyframe_of: np.ndarray, hidden: np.ndarray | None = None) -> np.ndarray:
    """:func:`merged_confirmed` of points already merged, ``keyframe_of`` each one's keyframe."""
    keep = confirmed(merged, keyframe_of)
    if hidden is not None and hidden.any():
        keep &= ~hidden[azimuth_bins(merged[:, :2])]
    # compress: a boolean index of an (n, 3) array takes ~4x as long
    return merged if keep.all() else np.compress(keep, merged, axis=0)


def confirmed(points: np.ndarray, keyframe_of: np.ndarray) -> np.ndarray:
    """(n,) bool: which of the merged ``points`` to keep — the keyframe's own (``keyframe_of`` 0)
    and beyond ``CONFIRM_RANGE_M``, all; an earlier keyframe's nearer point only where another
    keyframe has a point in the same ``CONFIRM_VOXEL_M`` voxel. ``keyframe_of``: each point's
    keyframe, each keyframe's points together (as merged).

    Rain, snow and fog return from different places in every scan, structure from the same: an
    earlier scan's flake stands beside the keyframe's structure, where the clutter test no longer
    sees it alone, but nothing else confirms it (simulated 16-beam car in snow: Recall@1 .949
    trailed, .978 confirmed; docs/results/trail.md)."""
    side = 2 * math.ceil(CONFIRM_RANGE_M / CONFIRM_VOXEL_M) + 1
    return _confirmed(np.asarray(points, np.float32), np.asarray(keyframe_of, np.int64),
                      CONFIRM_RANGE_M ** 2, CONFIRM_VOXEL_M, side, _Z_CELLS)


@njit(cache=True, nogil=True)
def _confirmed(points, keyframe_of, range_sq, voxel, side, z_cells):
    """:func:`confirmed` in two passes over the points: a keyframe counts once in each voxel
    (its points come together, so the last keyframe seen there tells), then who is confirmed."""
    n = points.shape[0]
    keep = np.ones(n, np.bool_)
    cells = np.full(n, -1, np.int64)
    seen_by = np.zeros(side * side * z_cells, np.int16)
    last = np.full(side * side * z_cells, -1, np.int32)
    half_z = z_cells // 2
    for i in range(n):
        x, y = points[i, 0], points[i, 1]
        if not x * x + y * y < range_sq:  # beyond, or not finite
            continue
        z = np.floor(points[i, 2] / voxel)
        if not z >= -half_z:  # below, or NaN
            z = -half_z
        elif z > half_z - 1:
            z = half_z - 1
        c = ((int(np.floor(x / voxel)) + side // 2) * side + int(np.floor(y / voxel)) + side // 2) * z_cells \
            + int(z) + half_z
        cells[i] = c
        if last[c] != keyframe_of[i]:
            last[c] = keyframe_of[i]
            seen_by[c] += 1
    for i in range(n):
        if cells[i] >= 0 and keyframe_of[i] != 0:
            keep[i] = seen_by[cells[i]] >= 2
    return keep
