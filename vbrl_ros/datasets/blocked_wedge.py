"""A wedge of azimuth a sensor cannot see: a robot's mast, the operator behind a hand-held sensor.

The simulator renders scans with it (``vbrl simulate --blocked-azimuth``); ``vbrl eval
--blocked-azimuth`` hides it from recorded scans that have none, to measure what a sensor
mounted that way would get at the same places.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def checked_wedge(wedge: Sequence[float], what: str) -> tuple[float, float]:
    """``wedge`` as (start, end) degrees, swept counter-clockwise; ValueError naming ``what`` unless
    both lie in [-180, 180] and span some but not all of the circle."""
    try:
        values = tuple(float(v) for v in wedge)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 2 or not all(-180.0 <= v <= 180.0 for v in values) or wedge_width(values) == 0:
        raise ValueError(f"{what} must be (start, end) in [-180, 180] degrees spanning less than a full turn, "
                         f"got {wedge!r}")
    return values  # type: ignore[return-value]


def wedge_width(wedge: tuple[float, float]) -> float:
    """Degrees swept counter-clockwise from ``wedge[0]`` to ``wedge[1]``, in [0, 360)."""
    return (wedge[1] - wedge[0]) % 360.0


def outside_wedge(xyz: np.ndarray, wedge: tuple[float, float] | None) -> np.ndarray:
    """(N,) bool: the sensor-frame points ``xyz`` lie outside ``wedge`` (all of them for None)."""
    if wedge is None:
        return np.ones(len(xyz), dtype=bool)
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    return (azimuth - wedge[0]) % 360.0 > wedge_width(wedge)
