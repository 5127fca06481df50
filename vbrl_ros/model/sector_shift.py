"""Yaw from a circular sector shift: the convention shared by the scorer and the index.

For S sectors of angle 2 pi / S, a compact descriptor is sector-major
(``x.reshape(S, R)``). Comparing a query q with a template t at shift k pairs
query sector (s + k) % S with template sector s. If the query scan is the
template scan rotated counter-clockwise about z by k sectors, D_k = 0: so the
best shift k means **the query scan is the template scan rotated by
yaw = k * 2 pi / S** (wrapped to (-pi, pi]), i.e. ``T_query_match`` has that
yaw — the seed for geometric verification (KISS-ICP).
"""

from __future__ import annotations

import math

import numpy as np


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped to (-pi, pi]."""
    return math.pi - np.mod(math.pi - np.asarray(angle, dtype=np.float64), 2.0 * math.pi)


def yaw_of_shift(shift: np.ndarray, sectors: int) -> np.ndarray:
    """Yaw (radians, (-pi, pi]) of integer sector shifts in [0, S)."""
    shift = np.asarray(shift, dtype=np.int64)
    signed = np.where(shift > sectors // 2, shift - sectors, shift)
    return signed.astype(np.float64) * (2.0 * math.pi / sectors)


def parabola_offset(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Vertex offset in [-0.5, 0.5] shifts of the parabola through D(k-1), D(k), D(k+1).

    0 where the three values are not convex (flat or degenerate).
    """
    left, centre, right = (np.asarray(v, dtype=np.float64) for v in (left, centre, right))
    curvature = left - 2.0 * centre + right
    safe = np.where(curvature > 0, curvature, 1.0)
    return np.where(curvature > 0, np.clip(0.5 * (left - right) / safe, -0.5, 0.5), 0.0)


def refined_yaw(shift: np.ndarray, left: np.ndarray, centre: np.ndarray, right: np.ndarray,
                sectors: int) -> np.ndarray:
    """Yaw of ``shift`` moved to the parabola vertex through the neighbouring distances."""
    offset = parabola_offset(left, centre, right)
    return wrap_angle(yaw_of_shift(shift, sectors) + offset * (2.0 * math.pi / sectors))
