"""Overlap and constraint: what tells a real loop closure from a plausible-looking one."""

from __future__ import annotations

import numpy as np

from vbrl_ros.detection.overlap import (
    MIN_CONSTRAINT,
    MIN_FACING_AREA_M2,
    SURFACE_CREDIT,
    agreement,
    covisible_overlap,
    is_constrained,
)
from vbrl_ros.detection.prepared_cloud import PreparedCloud


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


def test_what_a_narrow_sensor_saw_overlaps_the_whole_room_where_it_looked():
    # one wall, as a forward-looking sensor at the origin sees it: the rest of the room lay
    # outside its field of view and counts neither for nor against the overlap
    rng = np.random.default_rng(2)
    whole = room(rng)
    seen_ahead = whole[whole[:, 0] > 9.5]
    assert agreement(seen_ahead, whole, np.eye(4), 1.0, no_ground).overlap > 0.8
    assert agreement(whole, seen_ahead, np.eye(4), 1.0, no_ground).overlap > 0.8


def test_structure_one_sensor_saw_and_the_other_should_have_seen_lowers_the_overlap():
    rng = np.random.default_rng(2)
    empty, furnished = room(rng), room(rng)
    # a row of cabinets 3 m from the sensor: in view of both, present in one room only
    cabinets = np.c_[rng.uniform(-8, 8, 3000), np.full(3000, 3.0), rng.uniform(0, 2, 3000)]
    furnished = np.concatenate([furnished, cabinets])
    assert agreement(empty, room(rng), np.eye(4), 1.0, no_ground).overlap > 0.9
    # the walls are 4000 of the furnished room's 7000 points: its share can be no more than 0.57
    assert agreement(empty, furnished, np.eye(4), 1.0, no_ground).overlap < 0.6
    assert agreement(furnished, empty, np.eye(4), 1.0, no_ground).overlap < 0.6


def test_a_sensor_blind_behind_still_overlaps_the_same_place_seen_from_the_other_side():
    # a reversed revisit of a robot whose mast hides the 90 degrees behind it: each scan misses
    # what the other saw ahead, and only what both could see is compared
    rng = np.random.default_rng(5)
    whole = room(rng, 8000)
    azimuth = np.degrees(np.arctan2(whole[:, 1], whole[:, 0]))
    facing_east, facing_west = whole[np.abs(azimuth) < 135], whole[np.abs(azimuth) > 45]
    assert agreement(facing_east, facing_west, np.eye(4), 1.0, no_ground).overlap > 0.8


def test_two_parallel_walls_leave_their_axis_unconstrained():
    rng = np.random.default_rng(3)
    n = 3000
    corridor = np.c_[rng.uniform(-30, 30, n), np.where(rng.random(n) < 0.5, -2.0, 2.0), rng.uniform(0, 3, n)]
    found = agreement(corridor, corridor + rng.normal(0, 0.05, corridor.shape), np.eye(4), 1.0, no_ground)
    assert found.overlap > 0.5 and found.constraint < MIN_CONSTRAINT / 2
    assert found.facing_area < MIN_FACING_AREA_M2 / 4 and not is_constrained(found.constraint, found.facing_area)


def street_ahead(rng: np.random.Generator, wall_width: float, points_per_m2: float) -> np.ndarray:
    """What a forward-looking sensor sees down a street: two 200 m facades 12 m apart and,
    40 m ahead, a wall ``wall_width`` wide facing it; all 3 m high."""
    n_facade, n_wall = int(2 * 200 * 3 * points_per_m2), int(wall_width * 3 * points_per_m2)
    facades = np.c_[rng.uniform(0, 200, n_facade), np.where(rng.random(n_facade) < 0.5, -6.0, 6.0),
                    rng.uniform(0, 3, n_facade)]
    wall = np.c_[np.full(n_wall, 40.0), rng.uniform(-wall_width / 2, wall_width / 2, n_wall), rng.uniform(0, 3, n_wall)]
    return np.concatenate([facades, wall])


def test_a_wall_ahead_fixes_a_street_seen_forwards_however_many_facade_points_there_are():
    # thousands of facade points beside the sensor, 72 m^2 of wall ahead: a small ratio, yet
    # the position along the street is fixed
    rng = np.random.default_rng(6)
    found = agreement(street_ahead(rng, 24.0, 4.0), street_ahead(rng, 24.0, 4.0), np.eye(4), 1.0, no_ground)
    assert found.constraint < MIN_CONSTRAINT
    assert found.facing_area > MIN_FACING_AREA_M2 and is_constrained(found.constraint, found.facing_area)


def test_a_post_ahead_does_not_fix_a_street():
    rng = np.random.default_rng(7)
    found = agreement(street_ahead(rng, 1.0, 4.0), street_ahead(rng, 1.0, 4.0), np.eye(4), 1.0, no_ground)
    assert found.facing_area < MIN_FACING_AREA_M2 / 2 and not is_constrained(found.constraint, found.facing_area)


def test_the_facing_area_is_the_surface_not_the_sensor_density():
    # once every voxel of the wall holds points, four times as many add nothing
    rng = np.random.default_rng(8)
    sparse, dense = (agreement(street_ahead(rng, 24.0, d), street_ahead(rng, 24.0, d), np.eye(4), 1.0,
                               no_ground).facing_area for d in (4.0, 16.0))
    assert 0.75 < dense / sparse < 1.33


def test_ground_is_left_out_and_too_little_structure_scores_zero():
    rng = np.random.default_rng(4)
    floor = np.c_[rng.uniform(-20, 20, (3000, 2)), np.zeros(3000)]

    def is_floor(points: np.ndarray) -> np.ndarray:
        return np.abs(points[:, 2]) < 0.1

    found = agreement(floor, floor.copy(), np.eye(4), 1.0, is_floor)
    assert found.overlap == 0.0 and found.constraint == 0.0


def test_the_plan_view_overlap_tells_a_room_from_itself_turned():
    # what the heading search's overlays are compared by: the same room overlays fully, turned
    # by 90 degrees (its walls crossing) or moved off its walls it does not
    rng = np.random.default_rng(5)
    a, b = (PreparedCloud.of_thinned(room(rng), 1.0, np.zeros(4000, dtype=bool)) for _ in range(2))
    turned, moved = np.eye(4), np.eye(4)
    turned[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    moved[:3, 3] = [3.0, 2.0, 0.0]
    same = covisible_overlap(a, b, np.eye(4))
    assert same > 0.9
    assert covisible_overlap(a, b, turned) < 0.5 * same and covisible_overlap(a, b, moved) < 0.5 * same
    empty = PreparedCloud.of_thinned(np.empty((0, 3)), 1.0, np.zeros(0, dtype=bool))
    assert covisible_overlap(a, empty, np.eye(4)) == 0.0


def rings(heights: np.ndarray, along: float) -> np.ndarray:
    """The room's walls where horizontal rings at ``heights`` cross them, a point every 0.35 m
    along each (about as thinned as verification keeps a cloud), from ``along`` metres past a corner."""
    x, y = np.arange(-10 + along, 10, 0.35), np.arange(-6 + along, 6, 0.35)
    outline = np.concatenate([np.c_[x, np.full_like(x, -6)], np.c_[x, np.full_like(x, 6)],
                              np.c_[np.full_like(y, -10), y], np.c_[np.full_like(y, 10), y]])
    return np.concatenate([np.c_[outline, np.full(len(outline), z)] for z in heights])


def test_a_wall_sampled_by_another_sensors_rings_overlaps_at_the_surface_credit():
    # two sensors' rings 0.35 m apart in height on the same walls, their points 0.175 m apart along
    # them: no point lies within 0.3 m of the other cloud's, nearly every one on its planes
    low, high = rings(np.arange(0.0, 4.0, 0.7), 0.0), rings(np.arange(0.35, 4.0, 0.7), 0.175)
    found = agreement(low, high, np.eye(4), 1.0, no_ground)
    assert 0.5 < found.overlap <= SURFACE_CREDIT  # nothing coincides: all of it is credit
    moved = np.eye(4)
    moved[:3, 3] = [0.8, 0.6, 0.0]  # off the walls' planes: no credit
    assert agreement(low, high, moved, 1.0, no_ground).overlap < 0.2


def test_scattered_clutter_earns_no_surface_credit():
    rng = np.random.default_rng(4)
    a, b = (rng.uniform((-10, -10, 0), (10, 10, 3), (3000, 3)) for _ in range(2))
    found = agreement(a, b, np.eye(4), 1.0, no_ground)
    assert found.overlap < 0.3  # the points that happen to lie within 0.3 m, not the credit
