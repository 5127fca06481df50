"""Which scans of a source are keyframes, and reading their points in order."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from vbrl_ros.datasets.base import ScanSource


def select_by_distance(poses: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of keyframes at least ``spacing`` metres of travel apart along the poses.

    The first scan with a known pose is always a keyframe; scans with unknown
    (NaN) poses are skipped. Travel is summed along the path, not measured as
    a straight line, so standing still never makes keyframes and a tight
    loop still does.
    """
    if spacing <= 0:
        raise ValueError(f"keyframe spacing must be positive, got {spacing}")
    positions = np.asarray(poses)[:, :3, 3]
    known = np.flatnonzero(np.isfinite(positions).all(axis=1))
    if len(known) == 0:
        return known
    steps = np.linalg.norm(np.diff(positions[known], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    selected = [0]
    next_at = spacing
    # Python loop over scans (not points): cheap, and a keyframe resets the
    # reference, which a vectorised floor(travelled / spacing) would not.
    for k in range(1, len(known)):
        if travelled[k] >= next_at:
            selected.append(k)
            next_at = travelled[k] + spacing
    return known[np.asarray(selected)]


def select_every(count: int, every: int) -> np.ndarray:
    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    return np.arange(0, count, every)


def select_keyframes(
    source: ScanSource, *, distance: float | None = None, every: int | None = None
) -> np.ndarray:
    """Keyframe indices of a source: by travelled distance (needs poses) or every N scans."""
    if distance is not None and every is not None:
        raise ValueError("choose either a keyframe distance or every N scans, not both")
    if distance is not None:
        if source.poses is None:
            raise ValueError(
                f"{source.name} has no poses, so keyframes cannot be spaced by distance; "
                "use --poses kiss-icp to estimate them, or --every N"
            )
        return select_by_distance(source.poses, distance)
    return select_every(len(source), every or 1)


def source_points(source: ScanSource, indices: Sequence[int]) -> Iterator[np.ndarray]:
    """The points of the selected scans, read in order (sequential reads are cheap in bags)."""
    wanted = set(int(i) for i in indices)
    if len(wanted) == len(source):
        for scan in source:
            yield scan.points
        return
    for i in sorted(wanted):
        yield source[i].points


def keyframe_poses(source: ScanSource, indices: Sequence[int]) -> np.ndarray | None:
    """(n, 4, 4) T_world_lidar of the selected scans, in order; None when the source has no poses."""
    return None if source.poses is None else source.poses[np.sort(np.asarray(indices, dtype=np.int64))]
