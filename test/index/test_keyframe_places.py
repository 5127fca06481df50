"""Keyframe places: positions by keyframe id, and whether any stored keyframe lies near a point."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vbrl_ros.index.keyframe_places import KeyframePlaces


def test_positions_are_read_by_id_and_unknown_ids_are_nan():
    places = KeyframePlaces(2.5)
    for keyframe_id, x in ((3, 0.0), (7, 10.0), (8, 20.0)):
        places.add(keyframe_id, np.array([x, 1.0, 0.0]))
    places.add(9, None)  # no odometry for this one
    got = places.positions(np.array([8, 3, 5, 9, 100]))
    np.testing.assert_array_equal(got[:2], [[20.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.isnan(got[2:]).all()
    assert len(places) == 4


def test_near_points_are_found_across_cell_borders_and_far_ones_are_not():
    places = KeyframePlaces(2.5)
    places.add(0, np.array([2.4, 2.4, 0.0]))  # at the corner of a cell
    points = np.array([[2.6, 2.6, 0.0],   # next cell, 0.3 m away
                       [4.6, 2.4, 0.0],   # 2.2 m away, two cells over
                       [5.1, 2.4, 0.0],   # 2.7 m away
                       [2.4, 2.4, 3.0],   # right above, 3 m up
                       [np.nan, 0.0, 0.0]])
    np.testing.assert_array_equal(places.any_within(points, 2.5), [True, True, False, False, False])


def test_a_keyframe_without_a_position_is_near_nothing():
    places = KeyframePlaces(2.5)
    places.add(0, np.full(3, np.nan))
    assert not places.any_within(np.zeros((1, 3)), 2.5).any()


def test_ids_must_grow_and_radius_fit_the_cells():
    places = KeyframePlaces(2.5)
    places.add(4, np.zeros(3))
    with pytest.raises(ValueError, match="does not follow"):
        places.add(4, np.zeros(3))
    with pytest.raises(ValueError, match="exceeds"):
        places.any_within(np.zeros((1, 3)), 3.0)
    with pytest.raises(ValueError, match="cell size"):
        KeyframePlaces(0.0)


def test_clear_forgets_every_place():
    places = KeyframePlaces(1.0)
    places.add(0, np.zeros(3))
    places.clear()
    assert len(places) == 0 and not places.any_within(np.zeros((1, 3)), 1.0).any()
    places.add(0, np.zeros(3))  # ids start over


def test_answers_agree_with_a_kd_tree_as_the_grid_grows():
    # a 1.5 m-step walk folded into a square: cells revisited, the table rehashed several times
    rng = np.random.default_rng(0)
    steps = rng.normal(size=(3000, 2))
    walk = np.zeros((3000, 3))
    walk[:, :2] = np.cumsum(1.5 * steps / np.linalg.norm(steps, axis=1)[:, None], axis=0) % 200.0
    places = KeyframePlaces(2.5)
    points = rng.uniform(0.0, 200.0, (500, 3))
    points[:, 2] = rng.uniform(-3.0, 3.0, 500)
    for n, position in enumerate(walk):
        places.add(n, position)
        if n in (10, 700, 2999):
            want = cKDTree(walk[: n + 1]).query(points, distance_upper_bound=2.0)[0] <= 2.0
            np.testing.assert_array_equal(places.any_within(points, 2.0), want)
    np.testing.assert_array_equal(places.positions(np.arange(3000)), walk)


def test_all_at_once_answers_as_one_at_a_time():
    rng = np.random.default_rng(1)
    positions = rng.uniform(0.0, 60.0, (500, 3))
    positions[::7] = np.nan  # keyframes without a pose
    ids = np.arange(500) * 3 + 10
    one_by_one = KeyframePlaces(2.5)
    for keyframe_id, position in zip(ids, positions):
        one_by_one.add(keyframe_id, position)
    at_once = KeyframePlaces.of(2.5, ids, positions)
    points = rng.uniform(0.0, 60.0, (400, 3))
    np.testing.assert_array_equal(at_once.any_within(points, 2.5), one_by_one.any_within(points, 2.5))
    np.testing.assert_array_equal(at_once.positions(ids), one_by_one.positions(ids))
    at_once.add(ids[-1] + 1, np.array([1.0, 1.0, 1.0]))  # and it goes on growing
    assert at_once.any_within(np.array([[1.0, 1.0, 1.5]]), 2.5).all()
    with pytest.raises(ValueError, match="increasing ids"):
        KeyframePlaces.of(2.5, np.array([3, 3]), np.zeros((2, 3)))
