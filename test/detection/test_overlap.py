"""Overlap and constraint: what tells a real loop closure from a plausible-looking one."""

from __future__ import annotations

import numpy as np

from vbrl_ros.detection.overlap import MIN_CONSTRAINT, agreement


def no_ground(points: np.ndarray) -> np.ndarray:
    return np.zeros(len(points), dtype=bool)


def room(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """Points on the four walls of a 20 x 12 m room, 3 m high, one point per ~0.5 m^2."""
    side = rng.integers(0, 4, n)
    t = rng.uniform(-1, 1, n)
    x = np.where(side < 2, 10 * t, np.where(side == 2, -10.0, 10.0))
    y = np.where(side < 2, np.where(side == 0, -6.0, 6.0), 6 * t)
    return np.c_[x, y, rng.uniform(0, 3, n)]


def test_the_same_surfaces_overlap_and_are_constrained():
    rng = np.random.default_rng(0)
    a, b = room(rng), room(rng)  # two samplings of the same room
    found = agreement(a, b, np.eye(4), 1.0, no_ground)
    assert found.overlap > 0.9 and found.constraint > 0.3


def test_a_misalignment_lowers_the_overlap():
    rng = np.random.default_rng(1)
    a, b = room(rng), room(rng)
    moved = np.eye(4)
    moved[:3, 3] = [0.8, 0.6, 0.0]
    assert agreement(a, b, moved, 1.0, no_ground).overlap < 0.3


def test_the_smaller_share_counts_so_a_fragment_does_not_overlap_a_whole_room():
    rng = np.random.default_rng(2)
    whole = room(rng)
    fragment = whole[whole[:, 0] > 9.5]  # one wall only
    assert agreement(fragment, whole, np.eye(4), 1.0, no_ground).overlap < 0.3
    assert agreement(whole, fragment, np.eye(4), 1.0, no_ground).overlap < 0.3


def test_two_parallel_walls_leave_their_axis_unconstrained():
    rng = np.random.default_rng(3)
    n = 3000
    corridor = np.c_[rng.uniform(-30, 30, n), np.where(rng.random(n) < 0.5, -2.0, 2.0), rng.uniform(0, 3, n)]
    found = agreement(corridor, corridor + rng.normal(0, 0.05, corridor.shape), np.eye(4), 1.0, no_ground)
    assert found.overlap > 0.5 and found.constraint < MIN_CONSTRAINT / 2


def test_ground_is_left_out_and_too_little_structure_scores_zero():
    rng = np.random.default_rng(4)
    floor = np.c_[rng.uniform(-20, 20, (3000, 2)), np.zeros(3000)]

    def is_floor(points: np.ndarray) -> np.ndarray:
        return np.abs(points[:, 2]) < 0.1

    found = agreement(floor, floor.copy(), np.eye(4), 1.0, is_floor)
    assert found.overlap == 0.0 and found.constraint == 0.0
