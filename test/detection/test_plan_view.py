"""The plan view that compares a heading search's overlays: occupied cells and their neighbours."""

from __future__ import annotations

import numpy as np

from vbrl_ros.detection.plan_view import PlanView


def test_cells_beside_an_occupied_one_are_near_and_two_cells_away_are_not():
    plan = PlanView(np.array([[0.2, 0.3, 5.0], [0.4, 0.1, 1.0], [10.7, -3.2, 0.0]]), 0.5)
    np.testing.assert_allclose(plan.centres, [[0.25, 0.25], [10.75, -3.25]])  # one per occupied cell
    near = plan.near(np.array([[0.25, 0.25], [0.7, -0.2], [-0.2, 0.7], [1.1, 0.25], [0.25, -0.6],
                               [10.3, -3.6], [-50.0, 80.0]]))
    np.testing.assert_array_equal(near, [True, True, True, False, False, True, False])


def test_an_empty_structure_is_near_nothing():
    plan = PlanView(np.empty((0, 3)), 0.5)
    assert plan.centres.shape == (0, 2)
    assert not plan.near(np.zeros((3, 2))).any()
