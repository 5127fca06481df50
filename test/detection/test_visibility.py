"""What a sensor could have seen: the farthest range per direction, to a margin."""

from __future__ import annotations

import numpy as np

from vbrl_ros.detection.visibility import AZIMUTH_BINS, Horizon


def ring(radius: float, azimuth_deg: np.ndarray, z: float = 0.0) -> np.ndarray:
    a = np.deg2rad(azimuth_deg)
    return np.c_[radius * np.cos(a), radius * np.sin(a), np.full(len(a), z)]


def test_a_forward_cone_sees_ahead_within_its_range_only():
    cone = Horizon(ring(20.0, np.linspace(-35, 35, 200)), margin=1.0)
    ahead = ring(10.0, np.array([0.0, 30.0, -30.0]))
    assert cone.sees(ahead).all()
    assert cone.sees(ring(20.9, np.array([0.0]))).all()  # within the margin
    assert not cone.sees(ring(22.0, np.array([0.0]))).any()  # beyond anything it saw that way
    behind = ring(5.0, np.array([180.0, 90.0, -90.0, 60.0]))
    assert not cone.sees(behind).any()


def test_a_neighbouring_bin_lends_its_range_so_sparse_far_points_leave_no_blind_gaps():
    step = 360.0 / AZIMUTH_BINS
    every_other = ring(30.0, np.arange(0, 360, 2 * step) + step / 2)  # one point in every second bin
    assert Horizon(every_other, margin=0.5).sees(ring(29.0, np.arange(0, 360, step / 3) + 0.1)).all()


def test_height_does_not_matter_and_ground_counts_as_seen():
    seen = Horizon(ring(15.0, np.linspace(0, 359, 400), z=-1.8), margin=1.0)  # ground 15 m all round
    assert seen.sees(ring(12.0, np.array([45.0, 200.0]), z=8.0)).all()


def test_an_empty_cloud_saw_nothing():
    assert not Horizon(np.empty((0, 3)), margin=1.0).sees(ring(1.0, np.array([0.0, 90.0]))).any()
