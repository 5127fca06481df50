"""The detector's frames: registrations between levelled grid frames published between sensors.

``to_sensor_frames`` is checked on a scene of known transforms (points and the covariance's
adjoint); the built-in model, which levels every scan on its own ground, then closes loops
between differently mounted sensors and across lanes with the simulator's ground truth.
"""

import math

import numpy as np
import pytest
from scipy.linalg import expm, logm

from vbrl_ros.detection.candidate_verification import to_sensor_frames
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.registration import Verification
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.model.builtin import load_default_model

sim = pytest.importorskip("vbrl_ros.simulator")


def rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll), degrees."""
    r, p, y = (math.radians(a) for a in (roll, pitch, yaw))
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def transform(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def hat(xi: np.ndarray) -> np.ndarray:
    """4x4 twist of xi = [translation, rotation]."""
    rho, phi = xi[:3], xi[3:]
    out = np.zeros((4, 4))
    out[:3, :3] = [[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]
    out[:3, 3] = rho
    return out


def vee(twist: np.ndarray) -> np.ndarray:
    return np.array([twist[0, 3], twist[1, 3], twist[2, 3], twist[2, 1], twist[0, 2], twist[1, 0]])


def verification(T: np.ndarray, covariance: np.ndarray) -> Verification:
    return Verification(T_query_match=T, fitness=0.9, rmse=0.1, covariance=covariance, converged=True)


def random_covariance(seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(6, 6))
    return a @ a.T * 1e-3


# -- to_sensor_frames on known transforms ------------------------------------------------------


def test_sensor_frame_transform_maps_match_sensor_points_onto_query_sensor_points():
    """Two sensors with known world poses and mounts see the same world points; the levelled
    registration between their grid frames becomes the transform between the sensors."""
    world = np.random.default_rng(0).uniform(-20.0, 20.0, (200, 3))
    W_match = transform(rotation(4.0, -9.0, 30.0), (10.0, -4.0, 2.4))
    W_query = transform(rotation(-12.0, 5.0, -150.0), (11.5, -1.0, 0.9))
    F_match = transform(rotation(4.0, -9.0, 0.0), (0.0, 0.0, 2.4))  # sensor -> levelled
    F_query = transform(rotation(-12.0, 5.0, 0.0), (0.0, 0.0, 0.9))
    in_match = apply(np.linalg.inv(W_match), world)
    in_query = apply(np.linalg.inv(W_query), world)
    # what registration of the two levelled clouds finds
    T_grid = F_query @ np.linalg.inv(W_query) @ W_match @ np.linalg.inv(F_match)
    np.testing.assert_allclose(apply(T_grid, apply(F_match, in_match)), apply(F_query, in_query), atol=1e-9)
    # both levelled on the world's ground (z = 0): the registration is a yaw and a horizontal move
    assert abs(T_grid[2, 3]) < 1e-12 and np.allclose(T_grid[2, :3], [0, 0, 1], atol=1e-12)
    T, _ = to_sensor_frames(verification(T_grid, random_covariance(1)), F_query, F_match)
    np.testing.assert_allclose(apply(T, in_match), in_query, atol=1e-9)
    np.testing.assert_allclose(T, np.linalg.inv(W_query) @ W_match, atol=1e-12)


def test_identity_frames_leave_the_registration_as_it_is():
    T_grid = transform(rotation(1.0, 2.0, 175.0), (0.3, 2.1, -0.2))
    covariance = random_covariance(2)
    T, cov = to_sensor_frames(verification(T_grid, covariance), np.eye(4), np.eye(4))
    np.testing.assert_allclose(T, T_grid, atol=1e-15)
    np.testing.assert_allclose(cov, covariance, atol=1e-15)


def test_a_pure_rotation_frame_rotates_the_covariance_blocks():
    """Query frame a rotation R: translation and rotation blocks (and their cross terms) are
    carried by R^T, the inverse frame's rotation."""
    R = rotation(10.0, -20.0, 0.0)
    covariance = random_covariance(3)
    _, cov = to_sensor_frames(verification(np.eye(4), covariance), transform(R), np.eye(4))
    block = np.kron(np.eye(2), R.T)
    np.testing.assert_allclose(cov, block @ covariance @ block.T, atol=1e-12)
    assert not np.allclose(cov, covariance)


def test_the_covariance_follows_the_adjoint_of_the_query_frame():
    """A left perturbation exp(xi) of the levelled registration is exp(J xi) of the sensor one;
    J measured by finite differences, the covariance is J C J^T (and the match frame plays no part)."""
    F_query = transform(rotation(-12.0, 5.0, 0.0), (0.0, 0.0, 1.7))
    F_match = transform(rotation(3.0, 8.0, 0.0), (0.0, 0.0, 0.6))
    T_grid = transform(rotation(0.5, -0.3, 160.0), (1.0, 2.8, 0.05))
    T_sensor = np.linalg.inv(F_query) @ T_grid @ F_match
    eps = 1e-6
    J = np.empty((6, 6))
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = eps
        perturbed = np.linalg.inv(F_query) @ expm(hat(xi)) @ T_grid @ F_match
        J[:, i] = vee(np.real(logm(perturbed @ np.linalg.inv(T_sensor)))) / eps
    covariance = random_covariance(4)
    T, cov = to_sensor_frames(verification(T_grid, covariance), F_query, F_match)
    np.testing.assert_allclose(T, T_sensor, atol=1e-12)
    np.testing.assert_allclose(cov, J @ covariance @ J.T, atol=1e-6 * np.abs(cov).max())
    assert np.abs(J[:3, 3:]).max() > 0.5  # the frame's height couples rotation into translation
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)


# -- the built-in model between mounts and lanes -------------------------------------------------

LIDAR = sim.LidarConfig(beams=32, columns=512, vertical_fov_deg=(-45.0, 45.0))


@pytest.fixture(scope="module")
def model():
    return load_default_model()


@pytest.fixture(scope="module")
def town():
    return sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)


def drive(town, seed: int = 1, **route):
    """Two loops, 2 m apart scans; the second loop drives the first street the other way."""
    return sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=2.0, **route)),
                            LIDAR, "summer_clear", seed=seed)


def closure(model, match, query):
    """(closure, detector) of ``query`` after only ``match`` was seen, verified."""
    database = KeyframeDatabase(model.scorer(), model.identity())
    detector = LoopClosureDetector(model, database, DetectorSettings(verify=True, exclude_recent_s=0.0))
    assert detector.process_keyframe(match.points, 0.0, pose=match.pose).closures == []
    result = detector.process_keyframe(query.points, 1.0, pose=query.pose)
    assert len(result.closures) == 1, (result.candidates_scored, result.rejected_by_verification)
    return result.closures[0], detector


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation error vector in m, rotation error in degrees) of T against truth."""
    D = np.linalg.inv(truth) @ T
    angle = math.degrees(math.acos(float(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    return T[:3, 3] - truth[:3, 3], angle


@pytest.mark.parametrize("scan", [20, 100])
def test_a_tilted_sensor_closes_the_loop_with_the_true_relative_pose(model, town, scan):
    """The same places from a sensor rolled 8 and pitched -6 degrees, 1 m further along: the
    published T_query_match is the ground-truth sensor-to-sensor transform (tilts included)."""
    level, tilted = drive(town), drive(town, seed=2, sample_offset_m=1.0, sensor_roll_deg=8.0, sensor_pitch_deg=-6.0)
    match, query = level.scan(scan), tilted.scan(scan)
    found, detector = closure(model, match, query)
    truth = np.linalg.inv(query.pose) @ match.pose
    assert angle_between_up(truth) > 9.0  # the sensors really are tilted against each other
    translation, angle = errors(found.T_query_match, truth)
    assert np.linalg.norm(translation) < 0.3 and angle < 3.0, (translation, angle)
    assert found.match_id == 0 and found.fitness >= DetectorSettings().min_fitness
    np.testing.assert_allclose(detector.database.frame(0), detector.featurizer.frame(match.points).matrix)
    assert found.covariance.shape == (6, 6) and np.isfinite(found.covariance).all()


def angle_between_up(T: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(T[2, 2], -1.0, 1.0))))


def test_a_revisit_from_the_other_lane_closes_the_loop_with_the_true_relative_pose(model, town):
    """Driven the other way ~2 m to the side: found under translation search, turned ~180
    degrees, and verified to the ground truth."""
    run = drive(town)
    poses = run.poses
    heading = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    for first in (7, 28):
        later = np.arange(first + 50, len(run))
        opposite = later[np.cos(heading[later] - heading[first]) < -0.99]
        second = int(opposite[np.argmin(np.linalg.norm(poses[opposite, :2, 3] - poses[first, :2, 3], axis=1))])
        truth = np.linalg.inv(poses[second]) @ poses[first]
        assert 1.0 < np.linalg.norm(truth[:2, 3]) < 3.0
        found, _ = closure(model, run.scan(first), run.scan(second))
        assert abs(abs(math.degrees(math.atan2(math.sin(found.yaw), math.cos(found.yaw)))) - 180.0) < 13.0
        translation, angle = errors(found.T_query_match, truth)
        assert np.linalg.norm(translation) < 0.3 and angle < 3.0, (first, second, translation, angle)


def test_a_raised_sensor_closes_the_loop_with_the_true_heading_and_position(model, town):
    """A sensor 0.6 m higher (2.4 m) and tilted: x, y and the rotation agree with the ground truth."""
    level, raised = drive(town), drive(town, seed=2, sample_offset_m=1.0, sensor_height_m=2.4,
                                        sensor_roll_deg=8.0, sensor_pitch_deg=-6.0)
    for scan in (20, 100):
        match, query = level.scan(scan), raised.scan(scan)
        found, _ = closure(model, match, query)
        truth = np.linalg.inv(query.pose) @ match.pose
        # compare in the query's levelled axes, where "up" is the height difference
        level_q = rotation(8.0, -6.0, 0.0)
        translation, angle = errors(found.T_query_match, truth)
        horizontal = (level_q @ translation)[:2]
        assert np.linalg.norm(horizontal) < 0.3 and angle < 3.0, (scan, horizontal, angle)


@pytest.mark.xfail(strict=True, reason="scan-to-scan ICP between sensors at different heights is pulled "
                                       "~the height difference in z (beam rings on walls; the thinned "
                                       "ground does not hold it), in sensor and levelled frames alike")
def test_a_raised_sensor_closes_the_loop_with_the_true_height_difference(model, town):
    level, raised = drive(town), drive(town, seed=2, sample_offset_m=1.0, sensor_height_m=2.4,
                                        sensor_roll_deg=8.0, sensor_pitch_deg=-6.0)
    match, query = level.scan(60), raised.scan(60)
    found, _ = closure(model, match, query)
    translation, _ = errors(found.T_query_match, np.linalg.inv(query.pose) @ match.pose)
    assert np.linalg.norm(translation) < 0.3, translation
