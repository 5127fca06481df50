"""A verified closure handed to the stored keyframe nearest the query along its match's path:
the rows along a path, the choice and its composed transform on known poses, and the detector
doing it on simulated scans, within what the query may close a loop with."""

import math
from dataclasses import replace

import numpy as np
import pytest

from vbrl_ros.detection.candidate_verification import verify_candidates
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.nearest_keyframe import REACH_M, nearest_along_path, retargeted, rows_along_path
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.model.builtin import load_default_model

sim = pytest.importorskip("vbrl_ros.simulator")


def pose(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = x, y, 1.0
    return T


# -- rows along a path ----------------------------------------------------------------------------


def test_rows_along_a_path_stay_in_the_session_and_within_reach():
    sessions = np.array([0, 0, 0, 0, 0, 0, 1, 1])
    paths = np.array([0.0, 1.0, 2.0, 4.0, 7.5, 9.0, 0.0, 1.0])
    assert rows_along_path(2, sessions, paths, reach_m=2.0).tolist() == [0, 1, 2, 3]
    assert rows_along_path(4, sessions, paths, reach_m=2.0).tolist() == [4, 5]  # 3 is 3.5 m back
    assert rows_along_path(5, sessions, paths, reach_m=20.0).tolist() == [0, 1, 2, 3, 4, 5]  # 6: next session
    assert rows_along_path(6, sessions, paths, reach_m=20.0).tolist() == [6, 7]


def test_a_keyframe_without_a_path_keeps_to_itself_and_bridges_nothing():
    sessions = np.zeros(5, np.int64)
    paths = np.array([0.0, 1.0, np.nan, 3.0, 4.0])
    assert rows_along_path(2, sessions, paths).tolist() == [2]
    assert rows_along_path(1, sessions, paths).tolist() == [0, 1]  # a gap in the path ends the stretch


# -- the nearest keyframe and its transform -------------------------------------------------------


def test_the_closure_moves_to_the_keyframe_nearest_the_registered_query_with_the_true_transform():
    """Keyframes every metre along a bend; the query stands 0.2 m from the one at 3 m, turned 150
    degrees; a right registration to the keyframe at 6 m is handed to the one at 3 m."""
    poses = np.stack([pose(x, 0.1 * x * x, 10.0 * x) for x in range(10)])
    rows = np.arange(10)
    query = pose(3.0, 0.9 + 0.2, 150.0)
    T_query_match = np.linalg.inv(query) @ poses[6]  # what a right registration to keyframe 6 finds
    row, T = nearest_along_path(T_query_match, poses[6], rows, poses, 6)
    assert row == 3
    np.testing.assert_allclose(T, np.linalg.inv(query) @ poses[3], atol=1e-12)
    # a point of keyframe 3's cloud lands where the query sees it
    point = np.array([2.0, -1.0, 0.5, 1.0])
    np.testing.assert_allclose(T @ point, np.linalg.inv(query) @ poses[3] @ point, atol=1e-12)


def test_the_registered_keyframe_stays_when_nearest_tied_or_its_pose_unknown():
    poses = np.stack([pose(float(x)) for x in range(5)])
    rows = np.arange(5)
    query = pose(2.0)
    T = np.linalg.inv(query) @ poses[2]
    assert nearest_along_path(T, poses[2], rows, poses, 2)[0] == 2
    between = pose(2.5)  # as near keyframe 2 as keyframe 3: the one registered stays
    assert nearest_along_path(np.linalg.inv(between) @ poses[3], poses[3], rows, poses, 3)[0] == 3
    unknown = np.full((4, 4), np.nan)
    row, same = nearest_along_path(T, unknown, rows, poses, 2)
    assert row == 2 and same is T
    lost = poses.copy()
    lost[0] = np.nan  # a neighbour without a pose is never the nearest
    assert nearest_along_path(np.linalg.inv(pose(0.1)) @ poses[2], poses[2], rows, lost, 2)[0] == 1


def test_retargeted_composes_the_registration_with_odometry():
    a, b, q = pose(1.0, 2.0, 30.0), pose(4.0, -1.0, -60.0), pose(2.0, 0.0, 95.0)
    np.testing.assert_allclose(retargeted(np.linalg.inv(q) @ a, a, b), np.linalg.inv(q) @ b, atol=1e-12)


# -- the detector ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def street():
    """A first drive's keyframes 2 m apart along a straight street and a second drive's scan 0.5 m
    beyond the middle one: (first run, keyframe scans, the query scan)."""
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    lidar = sim.LidarConfig(beams=32, columns=512, vertical_fov_deg=(-30.0, 20.0))
    first = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0)), lidar, seed=1)
    second = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0, sample_offset_m=0.5)),
                              lidar, seed=2)
    heading = np.degrees(np.arctan2(first.poses[:, 1, 0], first.poses[:, 0, 0]))
    middle = next(i for i in range(4, len(first) - 4) if np.ptp(heading[i - 4:i + 5]) < 1.0)
    return first, range(middle - 4, middle + 5), second.scan(middle)


def closure_from(street, forced: int, **settings):
    """The closure of the query when verification is handed only the keyframe at row ``forced``
    (rows: the keyframes in order, stamps 0, 1, ...; the query at stamp 9)."""
    first, scans, query = street
    model = load_default_model()
    detector = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()),
                                   DetectorSettings(top_k=20, translation_search=0.0, **settings))
    for stamp, i in enumerate(scans):
        scan = first.scan(i)
        detector.retrieve(scan.points, float(stamp), scan.pose)
    retrieval = detector.retrieve(query.points, 9.0, query.pose)
    k = [c.index for c in retrieval.candidates].index(forced)
    only = replace(retrieval, candidates=[retrieval.candidates[k]], candidate_clouds=[retrieval.candidate_clouds[k]],
                   candidate_frames=[retrieval.candidate_frames[k]])
    result = detector.verified(only, lambda r: verify_candidates(r, detector.settings))
    assert len(result.closures) == 1, result.rejections
    assert result.handed_on == int(result.closures[0].match_id != forced)
    stored = {row: first.scan(i).pose for row, i in enumerate(scans)}
    return result.closures[0], stored, query.pose


def test_the_detector_publishes_the_closure_to_the_nearest_keyframe_with_its_true_pose(street):
    """Registered to the keyframe 3.5 m along (row 6), the closure goes to the one 0.5 m away
    (row 4), with the ground-truth transform between the two sensors."""
    closure, stored, query = closure_from(street, forced=6, exclude_recent_s=0.0)
    assert closure.match_id == 4
    truth = np.linalg.inv(query) @ stored[4]
    assert np.linalg.norm(closure.T_query_match[:3, 3] - truth[:3, 3]) < 0.3
    assert closure.match_stamp == 4.0 and closure.fitness >= DetectorSettings().min_fitness


def test_the_nearest_keyframe_is_one_the_query_may_close_a_loop_with(street):
    """Keyframes of the last 5.5 s (rows 4-8) are the query's recent past: registered to row 2,
    4.5 m back, the closure goes to row 3, the nearest older one, not to row 4."""
    closure, stored, query = closure_from(street, forced=2, exclude_recent_s=5.5)
    assert closure.match_id == 3
    truth = np.linalg.inv(query) @ stored[3]
    assert np.linalg.norm(closure.T_query_match[:3, 3] - truth[:3, 3]) < 0.3
    assert REACH_M >= 4.0  # rows 2 to 4 lie within reach of each other
