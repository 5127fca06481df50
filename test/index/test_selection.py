"""The compiled row selections against their numpy twins, ties included."""

import numpy as np

from vbrl_ros.index import selection as rs


def test_smallest_per_row_are_the_stable_argsort_positions_ascending():
    rng = np.random.default_rng(8)
    values = rng.integers(0, 6, (200, 24)).astype(np.float32)  # many ties: lower position wins
    for m in (1, 4, 24):
        out = np.empty((200, m), np.int64)
        picked = np.empty((200, m), np.float32)
        rs.smallest_per_row(values, out, picked)
        expected = np.sort(np.argsort(values, axis=1, kind="stable")[:, :m], axis=1)
        np.testing.assert_array_equal(out, expected)
        np.testing.assert_array_equal(picked, np.take_along_axis(values, expected, 1))
    np.testing.assert_array_equal(rs.row_minima(values), values.min(axis=1))


def test_lowest_rows_are_the_rows_with_the_smallest_minimum_lower_first_on_ties():
    rng = np.random.default_rng(9)
    values = rng.integers(0, 20, (500, 7)).astype(np.float32)
    for count in (1, 77, 499, 500, 600):
        expected = np.sort(np.argsort(values.min(axis=1), kind="stable")[:count])
        np.testing.assert_array_equal(rs.lowest_rows(values, count), expected)


def test_smallest_and_gathered_pick_along_rows():
    values = np.array([[3.0, 1.0, 2.0], [0.0, 5.0, 0.0]], np.float32)
    positions, picked = rs.smallest(values, 2)
    np.testing.assert_array_equal(positions, [[1, 2], [0, 2]])
    np.testing.assert_array_equal(picked, [[1.0, 2.0], [0.0, 0.0]])
    labels = np.array([[10, 11, 12], [20, 21, 22]])
    np.testing.assert_array_equal(rs.gathered(labels, positions), [[11, 12], [20, 22]])
