"""What a sensor could have seen: the farthest range per direction, and the band of elevations
it scans, to a margin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbrl_ros.datasets.mount_tilt import mount_rotation
from vbrl_ros.detection.candidate_verification import Retrieval, verify_candidates
from vbrl_ros.detection.database import Candidate
from vbrl_ros.detection.detector import verification_cloud
from vbrl_ros.detection.registration import QueryVerifier
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.visibility import AZIMUTH_BINS, FieldOfView, Horizon
from vbrl_ros.evaluation.verified import Candidates, KeyframeClouds
from vbrl_ros.evaluation.verified import verify_candidates as verify_every_candidate
from vbrl_ros.grids.ground_frame import ground_frame


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


def test_without_the_sensor_pose_height_does_not_matter_and_ground_counts_as_seen():
    seen = Horizon(ring(15.0, np.linspace(0, 359, 400), z=-1.8), margin=1.0)  # ground 15 m all round
    assert seen.sees(ring(12.0, np.array([45.0, 200.0]), z=8.0)).all()


def test_an_empty_cloud_saw_nothing():
    assert not Horizon(np.empty((0, 3)), margin=1.0).sees(ring(1.0, np.array([0.0, 90.0]))).any()


def beams(low_deg: float, high_deg: float, count: int = 16, radius: float = 20.0) -> np.ndarray:
    """Sensor-frame points of ``count`` beams from ``low_deg`` to ``high_deg`` all round, ``radius`` away."""
    elevation = np.radians(np.linspace(low_deg, high_deg, count))[:, None]
    azimuth = np.radians(np.arange(0.0, 360.0, 1.0))[None, :]
    return radius * np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation) * np.ones_like(azimuth)], axis=-1).reshape(-1, 3)


def levelled(points: np.ndarray, roll_deg: float, pitch_deg: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """(points in the levelled frame, the 4x4 sensor -> levelled) of a sensor so tilted, ``height`` up."""
    sensor = np.eye(4)
    sensor[:3, :3], sensor[2, 3] = mount_rotation(roll_deg, pitch_deg), height
    return points @ sensor[:3, :3].T + sensor[:3, 3], sensor


def at(azimuth_deg: float, elevation_deg: float, reach: float, height: float) -> np.ndarray:
    """A levelled-frame point ``reach`` m away horizontally, seen at ``elevation_deg`` from a sensor
    ``height`` up."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([[reach * math.cos(a), reach * math.sin(a), height + reach * math.tan(e)]])


def test_a_tilted_sensor_saw_only_its_band_of_elevations():
    cloud, sensor = levelled(beams(-15.0, 15.0), 0.0, 10.0, 0.8)
    up = sensor[:3, 2]  # the sensor's axis leans towards the side it looks down on
    low_side = math.degrees(math.atan2(up[1], up[0]))
    horizon = Horizon(cloud, margin=0.5, sensor=sensor)
    assert horizon.sees(at(low_side, 0.0, 10.0, 0.8)).all()
    assert not horizon.sees(at(low_side, 12.0, 10.0, 0.8)).any()  # above what it scanned that way...
    assert horizon.sees(at(low_side + 180.0, 12.0, 10.0, 0.8)).all()  # ... and within it the other way
    assert not horizon.sees(at(low_side + 180.0, -12.0, 10.0, 0.8)).any()  # below the band that way
    assert horizon.sees(at(low_side, 5.0, 10.0, 0.8) + [0.0, 0.0, 0.4]).all()  # a point within the margin
    assert Horizon(cloud, margin=0.5).sees(at(low_side, 12.0, 10.0, 0.8)).all()  # no pose: no band
    plan = np.vstack([at(low_side, 12.0, 10.0, 0.8), at(low_side + 180.0, -12.0, 10.0, 0.8)])[:, :2]
    assert horizon.sees(plan).all()  # a plan view's cells by their range alone


def test_the_band_is_read_from_the_cloud_and_a_stray_return_does_not_widen_it():
    cloud, sensor = levelled(beams(-15.0, 15.0), 5.0, 0.0, 1.5)
    field = FieldOfView.of(np.vstack([cloud, [[5.0, 0.0, 30.0]]]), sensor)
    assert math.degrees(math.atan(field.tan_top)) == pytest.approx(15.0, abs=0.1)
    assert math.degrees(math.atan(field.tan_bottom)) == pytest.approx(-15.0, abs=0.1)
    assert FieldOfView.of(cloud[:50], sensor) is None  # too few returns to tell


@pytest.fixture(scope="module")
def tilted_robot():
    """A 16-beam sensor (+-15 degrees) 0.8 m up, pitched 10 degrees down, through a simulated town:
    (route, render) where render(pose) is the keyframe's verification cloud and its frame."""
    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0, sensor_height_m=0.8, sensor_pitch_deg=10.0))
    lidar = sim.LidarConfig(beams=16, columns=720, vertical_fov_deg=(-15.0, 15.0))
    scene, rng = town.reference_scene(), np.random.default_rng(0)

    def render(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points = sim.render_scan(scene, pose, lidar, rng)[0][:, :3].astype(np.float64)
        frame = ground_frame(points).matrix
        return verification_cloud(points, frame, 1.0), frame

    return route, render


def driven_back(pose: np.ndarray) -> np.ndarray:
    """``pose`` turned half a turn about the vertical and 2 m over to its left: the other lane."""
    back = pose.copy()
    back[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ pose[:3, :3]
    left = pose[:3, 1] * (1.0, 1.0, 0.0)
    back[:3, 3] += 2.0 * left / np.linalg.norm(left)
    return back


def test_a_tilted_sensor_driven_back_on_the_other_lane_registers_over_the_threshold(tilted_robot):
    # measured: the right registrations overlapped .11-.30 without the band (two of five under the
    # node's 0.2), .23-.43 with it; other places .01-.04 either way
    route, render = tilted_robot
    without, with_band = [], []
    for place in (20, 60, 100, 140, 180):
        pose = route.poses[place]
        (query, query_frame), (first, first_frame) = render(driven_back(pose)), render(pose)
        elsewhere, elsewhere_frame = render(route.poses[place + 40])
        without.append(QueryVerifier(query).verify(first))
        banded = QueryVerifier(query, sensor=query_frame)
        with_band.append(banded.verify(first, sensor=first_frame))
        assert banded.verify(elsewhere, sensor=elsewhere_frame).fitness < 0.1
        assert np.linalg.norm(with_band[-1].T_query_match[:2, 3]) == pytest.approx(2.0, abs=0.3)
    assert all(b.fitness > a.fitness + 0.05 for a, b in zip(without, with_band))
    assert all(b.rejection(0.2) is None for b in with_band)
    assert sum(a.rejection(0.2) is None for a in without) <= 3


def test_the_node_and_the_evaluation_pass_each_keyframe_frame_to_the_verification(tilted_robot):
    # the two places whose right registrations fall under 0.2 without the band
    route, render = tilted_robot
    settings = DetectorSettings()
    for place in (100, 140):
        (query, query_frame), (first, first_frame) = render(driven_back(route.poses[place])), render(route.poses[place])
        result = verify_candidates(Retrieval(
            keyframe_id=1, stamp=100.0, session="back", candidates=[Candidate(0, 0, 1.0, 0.0, "first")],
            candidates_scored=1, frame=query_frame, cloud=query, candidate_clouds=[first],
            candidate_frames=[first_frame]), settings)
        assert len(result.closures) == 1 and result.closures[0].fitness >= settings.min_fitness
        evaluated = verify_every_candidate(
            KeyframeClouds([query], [query_frame]), KeyframeClouds([first], [first_frame]),
            Candidates(np.array([[0]]), np.array([[1.0]])), settings, workers=1, progress=False)
        assert evaluated.fitness[0, 0] == pytest.approx(result.closures[0].fitness)
        assert evaluated.accepted_at(settings.min_fitness)[0, 0]
