"""A sensor tilted on its mount: hand-held and pointed at the ground, or pitched on a robot.

The simulator renders scans so (``vbrl simulate --tilt``); ``vbrl eval --mount-tilt`` turns
recorded scans and their poses as if the sensor had been held that way, to measure what such a
mounting would get at the same places (the points seen are the same, only their frame turns).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: Limit on a mount's roll and pitch each (degrees); both at the limit tilt the sensor by 60
#: degrees, what the simulator's ``render_scan`` renders at most.
MAX_MOUNT_TILT_DEG = 45.0


def mount_rotation(roll_deg: float, pitch_deg: float) -> np.ndarray:
    """Ry(pitch) Rx(roll): the tilted sensor's axes in the level, heading-aligned frame. Positive
    roll lifts the sensor's left side, positive pitch tips its front down."""
    roll, pitch = math.radians(roll_deg), math.radians(pitch_deg)
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    return np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])


def checked_tilt(tilt: Sequence[float], what: str) -> tuple[float, float]:
    """``tilt`` as (roll, pitch) degrees; ValueError naming ``what`` unless both are finite and
    within ``MAX_MOUNT_TILT_DEG`` of level."""
    try:
        values = tuple(float(v) for v in tilt)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) and abs(v) <= MAX_MOUNT_TILT_DEG for v in values):
        raise ValueError(f"{what} must be (roll, pitch) in [-{MAX_MOUNT_TILT_DEG:g}, {MAX_MOUNT_TILT_DEG:g}] "
                         f"degrees, got {tilt!r}")
    return values  # type: ignore[return-value]


def tilted_points(points: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """``points`` (N, 3+) of a sensor, in the frame of the same sensor turned by ``mount``
    (:func:`mount_rotation`); columns beyond x, y, z are kept."""
    out = np.array(points, copy=True)
    out[:, :3] = points[:, :3] @ mount.astype(points.dtype)
    return out


def tilted_poses(poses: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """T_world_lidar (n, 4, 4) of the sensor turned by ``mount``: the same positions, the
    orientations turned with it."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = out[:, :3, :3] @ mount
    return out
