"""A blocked azimuth wedge: no return inside it, the rest of the scan exactly as unblocked."""

import math

import numpy as np
import pytest

from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town

INDEX = 5


@pytest.fixture(scope="module")
def town():
    return generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)


def _azimuth_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 1].astype(np.float64), points[:, 0].astype(np.float64)))


def _in_wedge(azimuth: np.ndarray, start: float, end: float) -> np.ndarray:
    """Inside the counter-clockwise sweep from ``start`` to ``end``, written out per case."""
    if start <= end:
        return (azimuth >= start) & (azimuth <= end)
    return (azimuth >= start) | (azimuth <= end)  # wraps through +-180


@pytest.mark.parametrize(("wedge", "pitch"), [((150.0, -150.0), 0.0), ((-45.0, 30.0), 0.0), ((100.0, 170.0), 15.0)],
                         ids=["behind-wrapping", "front", "tilted-left-rear"])
def test_no_return_inside_the_wedge_and_the_rest_unchanged(town, wedge, pitch):
    route = make_route(town, RouteConfig(loops=1, spacing_m=5.0, sensor_height_m=0.8, sensor_pitch_deg=pitch))
    open_sensor = LidarConfig(beams=32, columns=512)
    full = simulate_run(town, route, open_sensor, "summer_clear", seed=1).scan(INDEX)
    blind = simulate_run(town, route, LidarConfig(beams=32, columns=512, blocked_azimuth_deg=wedge),
                         "summer_clear", seed=1).scan(INDEX)

    width = (wedge[1] - wedge[0]) % 360
    full_inside = _in_wedge(_azimuth_deg(full.points), *wedge)
    assert full_inside.sum() > 0.5 * len(full.points) * width / 360  # the open sensor does see there
    assert not _in_wedge(_azimuth_deg(blind.points), *wedge).any()
    # Outside the wedge, the very same returns: each ray drew its noise as before.
    np.testing.assert_array_equal(blind.points, full.points[~full_inside])
    np.testing.assert_array_equal(blind.labels, full.labels[~full_inside])
    np.testing.assert_array_equal(blind.rings, full.rings[~full_inside])
    # The cut is at the wedge's edges: just outside them the sensor still sees.
    azimuth = _azimuth_deg(blind.points)
    for edge, side in ((wedge[0], -1), (wedge[1], 1)):
        near = (azimuth - (edge + side * 3.0) + 180) % 360 - 180
        assert (np.abs(near) < 3.0).sum() > 20


def test_the_wedge_is_in_the_sensor_frame(town):
    """Whatever the heading, the same sensor-frame directions are hidden (a mast turns with the robot)."""
    route = make_route(town, RouteConfig(loops=1, spacing_m=5.0))
    run = simulate_run(town, route, LidarConfig(beams=16, columns=360, blocked_azimuth_deg=(60.0, 120.0)),
                       "static", seed=0)
    headings = []
    for index in range(0, len(route), max(1, len(route) // 8)):
        scan = run.scan(index)
        assert not _in_wedge(_azimuth_deg(scan.points), 60.0, 120.0).any()
        headings.append(route.yaw[index])
    assert np.ptp(np.unwrap(headings)) > math.pi  # the loop turned the robot around


@pytest.mark.parametrize("bad", [(10.0, 10.0), (-180.0, 180.0), (0.0, 200.0), (-181.0, 0.0), (0.0,), (0.0, math.nan)])
def test_bad_wedges_are_rejected(bad):
    with pytest.raises(ValueError, match="blocked_azimuth_deg"):
        LidarConfig(blocked_azimuth_deg=bad)


def test_the_wedge_is_normalised_and_sees_is_exact():
    lidar = LidarConfig(blocked_azimuth_deg=[170, -170])
    assert lidar.blocked_azimuth_deg == (170.0, -170.0)
    angles = np.radians([169.0, 171.0, 179.9, -179.9, -171.0, -169.0, 0.0])
    xyz = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    np.testing.assert_array_equal(lidar.sees(xyz), [True, False, False, False, False, True, True])
    assert LidarConfig().sees(xyz).all()
