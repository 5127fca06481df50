"""Same-session candidates odometry places too far away are rejected before registration."""

import math
from dataclasses import replace

import numpy as np

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.odometry_gate import (
    SLACK_M,
    SPARE_FACTOR,
    kept_with_spares,
    odometry_heading,
    path_lengths,
    too_far_by_odometry,
)
from vbrl_ros.detection.settings import DetectorSettings, SettingsError
from vbrl_ros.model.builtin import load_default_model


def test_the_path_is_driven_per_session_and_bridges_an_unknown_pose():
    positions = np.array([[0, 0, 0], [3, 4, 0], [np.nan] * 3, [3, 8, 0], [100, 0, 0], [100, 10, 0]], float)
    sessions = np.array([0, 0, 0, 0, 1, 1])
    paths = path_lengths(positions, sessions)
    assert paths[:2].tolist() == [0.0, 5.0] and math.isnan(paths[2])
    assert paths[3] == 9.0  # from the last known pose, in a straight line
    assert paths[4:].tolist() == [0.0, 10.0]  # another session starts its own


def test_the_gate_allows_drift_in_proportion_to_the_path():
    allowed = 5.0 + SLACK_M + 0.1 * 200.0  # max_closure_distance, slack and a tenth of 200 m
    assert not too_far_by_odometry(allowed - 0.1, 200.0, 5.0, 0.1)
    assert too_far_by_odometry(allowed + 0.1, 200.0, 5.0, 0.1)
    assert not too_far_by_odometry(1e4, 200.0, 5.0, 0.0)  # 0: off
    assert not too_far_by_odometry(math.nan, 200.0, 5.0, 0.1)  # no pose: no opinion
    assert not too_far_by_odometry(1e4, math.nan, 5.0, 0.1)


def test_a_bad_drift_setting_is_named():
    for bad in (-0.1, 1.5, math.nan):
        try:
            DetectorSettings(odometry_drift=bad)
        except SettingsError as error:
            assert "'odometry_drift' must be a share of the path in [0, 1] (0: off)" in str(error)
        else:
            raise AssertionError(bad)


def place(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-30, 30, (20_000, 3)).astype(np.float32)
    points[:, 2] = np.abs(points[:, 2]) % 5 - 2
    return points


def pose(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = x, y
    return T


def drive(odometry_drift: float, back_at: tuple[float, float]):
    """One place, three others 50 m apart along a loop, then the first place again where odometry
    says ``back_at``; the result of that last keyframe."""
    model = load_default_model()
    settings = DetectorSettings(exclude_recent_s=0.0, top_k=1, odometry_drift=odometry_drift, submap_keyframes=0)
    detector = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()), settings)
    for k, (seed, at) in enumerate([(0, (0.0, 0.0)), (1, (50.0, 0.0)), (2, (100.0, 0.0)), (3, (50.0, 5.0))]):
        detector.process_keyframe(place(seed), float(k), pose(*at))
    return detector.process_keyframe(place(0), 4.0, pose(*back_at))


def test_a_lookalike_odometry_places_hundreds_of_metres_away_is_not_registered():
    # 193 m driven: 5 + 5 + 19 m allowed; the same cloud where odometry says 300 m away
    far = drive(0.1, (300.0, 0.0))
    # top 1 and its spares: every keyframe retrieved is ruled out, none registered
    assert far.closures == [] and far.rejections == {"odometry": SPARE_FACTOR}
    assert [c.match_id for c in drive(0.0, (300.0, 0.0)).closures] == [0]  # the gate off: registered


def test_a_true_revisit_after_odometry_drifted_is_still_closed():
    back = drive(0.1, (8.0, 0.0))  # odometry 8 m off after 193 m: a drift of 4 %
    assert [c.match_id for c in back.closures] == [0] and back.rejections == {}


def test_spares_keep_top_k_that_odometry_allows_and_count_the_ruled_out_before_them():
    assert kept_with_spares([False, False, False, False], 3) == 3
    assert kept_with_spares([True, False, True, False, False, False], 3) == 5
    assert kept_with_spares([True, True], 3) == 2  # fewer allowed than top_k: all of them
    assert kept_with_spares([], 3) == 0


def revisit_after_a_lookalike(odometry_drift: float):
    """top_k 1: the query's own cloud was seen first where odometry says 300 m away; the true place,
    0.5 m from the query, holds the same cloud jittered, so the lookalike ranks first."""
    model = load_default_model()
    settings = DetectorSettings(exclude_recent_s=0.0, top_k=1, odometry_drift=odometry_drift, submap_keyframes=0,
                                sequence_length=1)
    detector = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()), settings)
    jittered = place(0) + np.random.default_rng(9).normal(0.0, 0.05, (20_000, 3)).astype(np.float32)
    for k, (cloud, at) in enumerate([(place(0), (300.0, 0.0)), (place(1), (50.0, 0.0)), (jittered, (0.0, 0.0)),
                                     (place(2), (50.0, 5.0))]):
        detector.process_keyframe(cloud, float(k), pose(*at))
    return detector.process_keyframe(place(0), 4.0, pose(0.5, 0.0))


def test_a_lookalike_ruled_out_gives_its_place_to_the_true_revisit():
    back = revisit_after_a_lookalike(0.1)
    assert [c.match_id for c in back.closures] == [2] and back.rejections == {"odometry": 1}
    # the gate off: the lookalike is the one candidate, and it registers (the same cloud)
    assert [c.match_id for c in revisit_after_a_lookalike(0.0).closures] == [0]


def turned(yaw_deg: float, x: float = 0.0, y: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    a, r = np.deg2rad(yaw_deg), np.deg2rad(roll_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    T = np.eye(4)
    T[:3, :3], T[:2, 3] = Rz @ Rx, (x, y)
    return T


def test_odometry_s_heading_is_the_yaw_between_the_levelled_frames():
    query, match = turned(100.0, 3.0, 1.0), turned(30.0)
    assert math.isclose(math.degrees(odometry_heading(query, match, np.eye(4), np.eye(4), 0.1)), -70.0, abs_tol=1e-9)
    # each sensor tipped by 10 degrees of roll on its mount: its levelled frame takes the roll out and
    # lifts it to the ground's height, and the heading between the levelled frames is the same
    tipped_query, tipped_match = query @ turned(0.0, roll_deg=10.0), match @ turned(0.0, roll_deg=10.0)
    level = turned(0.0, roll_deg=10.0)
    level[2, 3] = 1.5
    heading = odometry_heading(tipped_query, tipped_match, level, level, 0.1)
    assert math.isclose(math.degrees(heading), -70.0, abs_tol=1e-6)
    assert math.isnan(odometry_heading(np.full((4, 4), np.nan), match, np.eye(4), np.eye(4), 0.1))
    assert math.isnan(odometry_heading(query, match, np.eye(4), np.eye(4), 0.0))  # odometry_drift 0: off


def revisit_turned(odometry_drift: float, *, another_session: bool = False, verified: bool = False):
    """A place, two others, then the first place again turned by 90 degrees where odometry says it
    is (``another_session``: as a keyframe of another session); its candidates as retrieved, or
    ``verified``: the keyframe's result."""
    model = load_default_model()
    settings = DetectorSettings(exclude_recent_s=0.0, top_k=1, odometry_drift=odometry_drift, submap_keyframes=0)
    detector = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()), settings)
    for k, (seed, at) in enumerate([(0, turned(0.0)), (1, turned(0.0, 50.0)), (2, turned(0.0, 100.0))]):
        detector.process_keyframe(place(seed), float(k), at)
    if another_session:
        detector.settings = replace(settings, session="another")
    quarter = turned(90.0)
    cloud = place(0) @ quarter[:3, :3]  # the same world, seen from a sensor turned by 90 degrees
    if verified:
        return detector.process_keyframe(cloud.astype(np.float32), 3.0, quarter)
    return detector.retrieve(cloud.astype(np.float32), 3.0, quarter).candidates


def test_a_same_session_candidate_carries_the_heading_odometry_expects():
    candidates = revisit_turned(0.1)
    assert [c.index for c in candidates] == [0]
    assert math.isclose(math.degrees(candidates[0].odometry_yaw), -90.0, abs_tol=3.0)  # the frames level each
    # no opinion with the gate off, or from another session's odometry frame
    assert math.isnan(revisit_turned(0.0)[0].odometry_yaw)
    assert math.isnan(revisit_turned(0.1, another_session=True)[0].odometry_yaw)


def test_the_verification_is_told_the_heading_odometry_expects(expected_yaws):
    told = expected_yaws
    result = revisit_turned(0.1, verified=True)
    assert [c.match_id for c in result.closures] == [0]
    assert len(told) == 1 and math.isclose(math.degrees(told[0]), -90.0, abs_tol=3.0)
    told.clear()
    revisit_turned(0.0, verified=True)  # the gate off: every keyframe's candidate registered, none expected
    assert len(told) == 3 and all(math.isnan(yaw) for yaw in told)
