"""The ground frame makes a scan's descriptor independent of how the sensor is mounted.

The same places of a simulated town are ray-cast from sensors at 0.8, 1.8 and 2.4 m
tilted by 0, 10 and 20 degrees (in roll, pitch or both), and hand-held at 1.2-1.5 m tilted
by 35 degrees, each with its own noise, and
described with the ground-frame height descriptor. A sensor with a wide vertical field
of view (-45..45 degrees, like hand-held units) is used on purpose: tilting a
-30..10 degree car sensor by 20 degrees makes it blind above -10 degrees on one side,
and no frame can describe what was not seen.
"""

import math

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer

sim = pytest.importorskip("vbrl_ros.simulator")

LIDAR = sim.LidarConfig(beams=32, columns=512, vertical_fov_deg=(-45.0, 45.0))
REFERENCE = (1.8, 0.0, 0.0)  # (height m, roll deg, pitch deg)
MOUNTS = (
    (0.8, 0.0, 0.0), (0.8, 0.0, 10.0), (0.8, 20.0, 0.0),
    (1.8, 0.0, 0.0), (1.8, 10.0, 0.0), (1.8, 14.142, -14.142),
    (2.4, 0.0, 0.0), (2.4, -7.071, -7.071), (2.4, 0.0, -20.0),
    (1.5, 0.0, 35.0), (1.2, -35.0, 0.0),  # held steeper than the plane search reaches
)
PLACES = (30, 150)  # scan indices on a 1 m-spaced route
FAR = 20  # the other place: 20 scans (20 m of path) further
#: Same place on any mount: at most this fraction of the distance to a place 20 m away.
RATIO = 0.35


def _featurizer(frame: str, z_edges: tuple[float, float]) -> Featurizer:
    grid = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=z_edges, frame=frame)
    return Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(modalities=("height",), min_points=1,
                                                                   normalise=True)))


GROUND = _featurizer("ground", (0.0, 20.0))
# Without levelling: the same band, placed for the reference mount (1.8 m, level).
SENSOR = _featurizer("sensor", (-1.8, 18.2))


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """L1 distance normalised to [0, 1]."""
    return float(np.abs(a - b).sum() / (np.abs(a).sum() + np.abs(b).sum()))


def _tilt_deg(roll: float, pitch: float) -> float:
    return math.degrees(math.acos(math.cos(math.radians(roll)) * math.cos(math.radians(pitch))))


@pytest.fixture(scope="module")
def scans():
    """(reference, mounted): {index: Scan} of the reference mount at the places and the far
    places (run seed 1), {(place, mount): Scan} of every mount (run seed 2: other noise)."""
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)

    def run(mount, seed):
        height, roll, pitch = mount
        route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0, sensor_height_m=height,
                                                     sensor_roll_deg=roll, sensor_pitch_deg=pitch))
        return sim.simulate_run(town, route, LIDAR, "static", seed=seed)

    level = run(REFERENCE, 1)
    for place in PLACES:
        assert np.linalg.norm(level.poses[place, :3, 3] - level.poses[place + FAR, :3, 3]) > 18.0
    reference = {i: level.scan(i) for place in PLACES for i in (place, place + FAR)}
    mounted = {}
    for mount in MOUNTS:
        session = run(mount, 2)
        mounted.update({(place, mount): session.scan(place) for place in PLACES})
    return reference, mounted


def _ratios(featurizer: Featurizer, scans) -> dict[tuple, float]:
    """Per (place, mount): distance to the reference mount's scan of the place / to the far place."""
    reference, mounted = scans
    ratios = {}
    for place in PLACES:
        here = featurizer.describe(reference[place].points)
        far = _distance(here, featurizer.describe(reference[place + FAR].points))
        for mount in MOUNTS:
            ratios[place, mount] = _distance(here, featurizer.describe(mounted[place, mount].points)) / far
    return ratios


def test_ground_frame_recovers_the_mount_height_and_tilt(scans):
    for (place, mount), scan in scans[1].items():
        frame = GROUND.frame(scan.points)
        assert frame.found
        assert abs(frame.height - mount[0]) < 0.1, (place, mount, frame.height)
        up_in_sensor = scan.pose[2, :3]  # the world's z axis in the sensor frame
        fitted_up = frame.rotation[2]
        error = math.degrees(math.acos(min(1.0, float(up_in_sensor @ fitted_up))))
        assert error < 1.5, (place, mount, error)


def test_same_place_gives_the_same_descriptor_on_every_mount(scans):
    ratios = _ratios(GROUND, scans)
    worst = max(ratios, key=ratios.get)
    assert ratios[worst] < RATIO, (worst, ratios[worst])
    assert np.mean(list(ratios.values())) < RATIO / 2


def test_without_levelling_a_tilted_sensor_sees_another_place(scans):
    """The same criterion in the sensor's frame: every mount tilted by 20 degrees or more fails it."""
    ratios = _ratios(SENSOR, scans)
    tilted = {key: ratio for key, ratio in ratios.items() if _tilt_deg(*key[1][1:]) > 19.0}
    assert len(tilted) == 5 * len(PLACES)
    assert min(tilted.values()) > RATIO, tilted
    # Level at the reference height the two frames agree: the failure is the tilt.
    assert max(ratios[place, REFERENCE] for place in PLACES) < RATIO / 5
