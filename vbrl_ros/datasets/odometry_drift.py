"""Poses as drifting odometry would give them, to measure what the node would do without a map.

A recording's poses are usually a SLAM solution: consistent across every pass. The node's
odometry drifts: its heading wanders a little with every metre, and the position error grows
with it. ``vbrl eval --simulate-drift`` gives everything that reads odometry (a keyframe's
trail, sequences matched by place, the submaps verified, the odometry gate) such poses, while
the ground truth keeps the recorded ones.
"""

from __future__ import annotations

import math

import numpy as np

#: How much drifting odometry over- or underestimates each step (a wheel or scan-matching scale
#: error): 1 %.
SCALE_ERROR = 0.01
#: Heading drift (degrees per square root of 100 m driven) beyond which no odometry is worth using.
MAX_DRIFT_DEG = 45.0


def checked_drift(value: float, what: str) -> float:
    """``value`` as degrees per square root of 100 m; ValueError naming ``what`` unless in range."""
    drift = float(value)
    if not (math.isfinite(drift) and 0.0 <= drift <= MAX_DRIFT_DEG):
        raise ValueError(f"{what} must be in [0, {MAX_DRIFT_DEG:g}] degrees per sqrt(100 m), got {value!r}")
    return drift


def drifted_poses(poses: np.ndarray, heading_deg: float, seed: int = 0) -> np.ndarray:
    """T_world_lidar (n, 4, 4) re-integrated from each step's motion, as odometry integrates it:
    every step turned by a random heading error (a random walk of ``heading_deg`` degrees per
    square root of 100 m driven) and stretched by :data:`SCALE_ERROR`. The first pose is kept;
    seeded, so a run is repeatable."""
    poses = np.asarray(poses, np.float64)
    out = poses.copy()
    if len(poses) < 2 or heading_deg == 0.0:
        return out
    rng = np.random.default_rng(seed)
    steps = np.linalg.inv(poses[:-1]) @ poses[1:]  # each motion in the sensor's frame before it
    driven = np.linalg.norm(steps[:, :3, 3], axis=1)
    errors = np.radians(heading_deg) * np.sqrt(driven / 100.0) * rng.normal(size=len(steps))
    for k, (step, error) in enumerate(zip(steps, errors)):
        # the heading error turns about gravity (world z), however the sensor is held
        turn = np.array([[math.cos(error), -math.sin(error), 0.0], [math.sin(error), math.cos(error), 0.0],
                         [0.0, 0.0, 1.0]])
        rotation = turn @ out[k, :3, :3]
        out[k + 1, :3, :3] = rotation @ step[:3, :3]
        out[k + 1, :3, 3] = out[k, :3, 3] + rotation @ step[:3, 3] * (1.0 + SCALE_ERROR)
    return out
