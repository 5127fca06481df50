"""Off by default: a small run renders what it rendered before the blocked wedge, keyframe filters and
lane wander existed (fingerprints recorded from that renderer; bit-identical on the machine that recorded
them, compared here to within float32 summation so other CPUs' last bits do not matter)."""

import numpy as np
import pytest

from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town

# scan: (points, points per Material, column sums of x, y, z, intensity, sum of the beam indices)
RECORDED = {
    ("summer_clear", 0): (5030, [0, 1992, 1835, 34, 81, 38, 395, 312, 67, 270, 4, 2, 0, 0],
                          [-529.1355, 2847.2206, 1912.1025, 845.7665], 34103),
    ("summer_clear", 7): (5204, [0, 784, 2164, 7, 18, 49, 188, 75, 37, 1852, 29, 1, 0, 0],
                          [-2039.5169, 5400.2631, 2718.1699, 1625.9898], 36178),
    ("winter_snow", 0): (4011, [0, 0, 1449, 29, 63, 45, 23, 263, 46, 213, 2, 9, 225, 1644],
                         [662.6446, 736.7963, 567.2782, 961.4945], 25700),
    ("winter_snow", 7): (4480, [0, 0, 2209, 4, 61, 69, 9, 49, 26, 1008, 1, 10, 197, 837],
                         [965.4872, 4616.9936, 1260.9745, 1308.5436], 30525),
}
POSE_5 = [[0.9995722476436102, -0.02924588416685797, 0.0, 26.32534693379883],
          [0.02924588416685797, 0.9995722476436102, 0.0, -7.36871737502095], [0.0, 0.0, 1.0, 1.8], [0, 0, 0, 1]]
POSE_LAST = [[-0.9995722476436101, 0.029245884166859016, 0.0, 11.855425994600834],
             [-0.029245884166859016, -0.9995722476436101, 0.0, -5.7912282320142445], [0.0, 0.0, 1.0, 1.8], [0, 0, 0, 1]]


@pytest.fixture(scope="module")
def town_and_route():
    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)
    return town, make_route(town, RouteConfig(loops=2, spacing_m=3.0))


def test_the_default_route_is_unchanged(town_and_route):
    _, route = town_and_route
    assert len(route) == 234
    np.testing.assert_allclose(route.poses[5], POSE_5, rtol=0, atol=1e-9)
    np.testing.assert_allclose(route.poses[-1], POSE_LAST, rtol=0, atol=1e-9)


@pytest.mark.parametrize(("scenario", "index"), list(RECORDED))
def test_default_scans_are_unchanged(town_and_route, scenario, index):
    town, route = town_and_route
    scan = simulate_run(town, route, LidarConfig(beams=16, columns=360), scenario, 1).scan(index)
    count, per_material, sums, ring_sum = RECORDED[(scenario, index)]
    assert len(scan.points) == count
    assert np.bincount(scan.labels, minlength=14).tolist() == per_material
    assert int(scan.rings.sum()) == ring_sum
    np.testing.assert_allclose(scan.points.astype(np.float64).sum(axis=0), sums, rtol=0, atol=2e-3)
