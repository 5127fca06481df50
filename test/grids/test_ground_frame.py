"""The ground frame of one scan: its tilt and height recovered from the ground it sees.

Scenes are synthetic: a noisy ground disc with boxes standing on it, a wall and a canopy
(a roof with no ground visible under it, a tempting wrong plane), given in the level frame
with the ground at z = 0 and seen from a sensor at a known height and roll / pitch.
"""

import math

import numpy as np
import pytest

from vbrl_ros.grids.ground_frame import (
    CELL_M,
    FALLBACK_HEIGHT_M,
    HYPOTHESES,
    INLIER_M,
    MAX_HELD_TILT_DEG,
    MAX_RANGE_M,
    MAX_TILT_DEG,
    MIN_INLIERS,
    MIN_RANGE_M,
    GroundFrame,
    fit_ground,
    gravity_rotation,
    ground_frame,
    lowest_points,
)


def rx(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mount(roll: float, pitch: float) -> np.ndarray:
    """Sensor axes in the level, heading-aligned frame: Ry(pitch) Rx(roll)."""
    return ry(pitch) @ rx(roll)


def level_scene(seed: int = 0) -> np.ndarray:
    """(N, 3) points in the level frame, ground at z = 0 (2 cm noise)."""
    rng = np.random.default_rng(seed)
    n = 30_000
    r = np.sqrt(rng.uniform(0.5**2, 35.0**2, n))
    a = rng.uniform(0.0, 2.0 * np.pi, n)
    ground = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(0.0, 0.02, n)])
    parts = []
    for (cx, cy), (sx, sy, h) in (((8, 3), (4, 2, 1.5)), ((-6, -9), (3, 5, 2.5)),
                                  ((15, -12), (6, 6, 8.0)), ((-18, 6), (2, 2, 1.0))):
        u = rng.uniform(-0.5, 0.5, (2000, 3)) * [sx, sy, h]
        face = rng.integers(0, 5, len(u))  # four sides and the top
        u[face == 0, 0], u[face == 1, 0] = -sx / 2, sx / 2
        u[face == 2, 1], u[face == 3, 1] = -sy / 2, sy / 2
        u[face == 4, 2] = h / 2
        parts.append(u + [cx, cy, h / 2])
        ground = ground[~((np.abs(ground[:, 0] - cx) < sx / 2) & (np.abs(ground[:, 1] - cy) < sy / 2))]
    m = 4000  # a wall along y = 20
    parts.append(np.column_stack([rng.uniform(-25, 25, m), 20.0 + rng.normal(0, 0.02, m), rng.uniform(0, 6, m)]))
    m = 3000  # a canopy at 3 m with no ground in sight under it
    canopy = np.column_stack([rng.uniform(-12, -4, m), rng.uniform(10, 16, m), 3.0 + rng.normal(0, 0.02, m)])
    ground = ground[~((ground[:, 0] > -12) & (ground[:, 0] < -4) & (ground[:, 1] > 10) & (ground[:, 1] < 16))]
    return np.concatenate([ground, *parts, canopy])


def seen_from(level: np.ndarray, height: float, rotation: np.ndarray) -> np.ndarray:
    """The level-frame points in the frame of a sensor at ``height`` with axes ``rotation``."""
    return (level - [0.0, 0.0, height]) @ rotation


def heading_deg(rotation: np.ndarray) -> float:
    """Heading of the sensor's x axis in the frame ``rotation`` maps into."""
    return math.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a @ b.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


SCENE = level_scene()
#: (height m, roll deg, pitch deg): level, single-axis and combined tilts, low and high mounts,
#: and hand-held sensors held steeper than the plane search's MAX_TILT_DEG (found by refitting).
MOUNTS = ((1.8, 0.0, 0.0), (0.5, 0.0, 15.0), (2.4, 20.0, 0.0), (1.2, 10.0, 10.0),
          (1.8, -14.0, 14.0), (0.8, 25.0, -10.0), (1.5, 0.0, 35.0), (1.2, -28.0, 28.0), (1.0, 40.0, 0.0))


@pytest.mark.parametrize("height, roll, pitch", MOUNTS)
def test_recovers_the_tilt_and_height_of_the_mount(height, roll, pitch):
    """Levelling brings the scan back to the level scene: tilt within 1 degree, height within
    5 cm, every point within 5 cm of where it is in the level frame."""
    true = mount(roll, pitch)
    points = seen_from(SCENE, height, true)
    frame = ground_frame(points)
    assert frame.found
    assert abs(frame.height - height) < 0.05, frame.height
    up_error = math.degrees(math.acos(min(1.0, float(frame.rotation[2] @ true[2]))))
    assert up_error < 1.0, up_error
    np.testing.assert_allclose(frame.rotation @ frame.rotation.T, np.eye(3), atol=1e-12)
    assert np.abs(frame.apply(points) - SCENE).max() < 0.05


@pytest.mark.parametrize("height, roll, pitch", MOUNTS)
def test_levelling_keeps_the_heading(height, roll, pitch):
    """The levelled frame turns the sensor about no vertical axis: its x axis keeps pointing
    the same way in the horizontal plane, so the fitted frame is the mount's own roll and pitch
    (the same frame odometry's gravity gives), even for combined roll and pitch."""
    true = mount(roll, pitch)
    frame = ground_frame(seen_from(SCENE, height, true))
    assert abs(heading_deg(frame.rotation)) < 0.05
    assert angle_deg(frame.rotation, true) < 0.5
    by_gravity = ground_frame(seen_from(SCENE, height, true), gravity_rotation(rz(70.0) @ true))
    assert angle_deg(frame.rotation, by_gravity.rotation) < 0.5


def test_a_yawed_scene_gives_the_same_tilt_seen_in_the_sensor():
    """Turning the world about the vertical changes nothing the sensor sees of its own tilt:
    the levelled scan is the level scene turned by the same yaw."""
    true = mount(10.0, -8.0)
    turned = SCENE @ rz(35.0).T
    points = seen_from(turned, 1.5, true)
    frame = ground_frame(points)
    assert abs(frame.height - 1.5) < 0.05 and angle_deg(frame.rotation, true) < 0.5
    assert np.abs(frame.apply(points) - turned).max() < 0.05


def test_the_frame_is_deterministic_and_independent_of_point_order():
    """On rough ground (8 cm bumps: other plane samples give other frames) a scan always gives
    the same frame, bit for bit, in whatever order its points come."""
    rough = SCENE.copy()
    rough[:, 2] += np.random.default_rng(7).normal(0.0, 0.08, len(rough)) * (rough[:, 2] < 0.2)
    points = seen_from(rough, 1.2, mount(10.0, 10.0))
    first, again = ground_frame(points), ground_frame(points)
    shuffled = ground_frame(points[np.random.default_rng(3).permutation(len(points))])
    for other in (again, shuffled):
        np.testing.assert_array_equal(other.rotation, first.rotation)
        assert other.height == first.height and other.found == first.found


@pytest.mark.parametrize("yaw, pitch, roll", [(0.0, 0.0, 0.0), (90.0, 0.0, 0.0), (-170.0, 12.0, -7.0),
                                              (33.0, -25.0, 18.0), (179.0, 5.0, 30.0)])
def test_gravity_rotation_removes_exactly_the_yaw(yaw, pitch, roll):
    """gravity_rotation(Rz(yaw) Ry(pitch) Rx(roll)) is Ry(pitch) Rx(roll); a 4x4 pose works too."""
    rotation = rz(yaw) @ ry(pitch) @ rx(roll)
    np.testing.assert_allclose(gravity_rotation(rotation), ry(pitch) @ rx(roll), atol=1e-12)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, (5.0, -3.0, 1.8)
    np.testing.assert_allclose(gravity_rotation(pose), ry(pitch) @ rx(roll), atol=1e-12)


def test_with_a_gravity_rotation_only_the_height_is_fitted():
    """The given rotation is kept as it is (even when it is 2 degrees off the ground's), and
    the height is still the sensor's above the ground."""
    true = mount(8.0, -12.0)
    points = seen_from(SCENE, 2.1, true)
    given = ry(2.0) @ true
    frame = ground_frame(points, given)
    assert frame.found
    np.testing.assert_array_equal(frame.rotation, given)
    assert abs(frame.height - 2.1) < 0.05
    exact = ground_frame(points, true)
    np.testing.assert_array_equal(exact.rotation, true)
    assert abs(exact.height - 2.1) < 0.05


@pytest.mark.parametrize("slope_deg", [2.0, 4.0])
def test_on_a_slope_the_gravity_frame_height_is_the_ground_straight_below(slope_deg):
    """Levelled by gravity on a sloping street, z = 0 is the ground under the sensor: the
    height is the vertical distance to it, not the perpendicular one (an exact, noiseless plane)."""
    xy = np.random.default_rng(1).uniform(-30.0, 30.0, (20_000, 2))
    ground = np.column_stack([xy, xy[:, 0] * math.tan(math.radians(slope_deg))])
    frame = ground_frame(ground - [0.0, 0.0, 1.8], np.eye(3))
    assert frame.found and frame.height == pytest.approx(1.8, abs=1e-6)
    levelled = ground_frame(ground - [0.0, 0.0, 1.8])  # on its own ground: perpendicular
    assert levelled.height == pytest.approx(1.8 * math.cos(math.radians(slope_deg)), abs=1e-6)


def test_without_ground_the_scan_keeps_its_tilt_and_a_bounded_height():
    """No plane below the sensor (points only above it, too few points, none at all): not
    found, the rotation given (or none), a height within FALLBACK_HEIGHT_M."""
    rng = np.random.default_rng(4)
    ceiling = rng.uniform(-15.0, 15.0, (5000, 3)) * [1.0, 1.0, 0.0] + [0.0, 0.0, 2.5]
    low, high = FALLBACK_HEIGHT_M
    for points, gravity in ((ceiling, None), (ceiling, mount(5.0, 0.0)),
                            (np.array([[3.0, 1.0, -1.2], [-4.0, 2.0, -1.2], [2.0, -5.0, -1.2]]), None),
                            (np.empty((0, 3)), None)):
        frame = ground_frame(points, gravity)
        assert not frame.found
        assert low <= frame.height <= high
        np.testing.assert_array_equal(frame.rotation, np.eye(3) if gravity is None else gravity)
    assert ground_frame(ceiling).height == low  # the lowest points are above: clipped
    assert ground_frame(np.empty((0, 3))).height == high
    few = ground_frame(np.array([[3.0, 1.0, -1.2], [-4.0, 2.0, -1.2], [2.0, -5.0, -1.2]]))
    assert few.height == pytest.approx(1.2)  # the lowest points stand in for the ground



@pytest.mark.parametrize("roll", [55.0, 70.0, 90.0])
def test_no_frame_tilts_a_scan_beyond_the_held_limit(roll):
    """A wall stands 90 degrees from the ground; a sensor is never levelled by more than
    MAX_HELD_TILT_DEG, so a wall seen by a sensor held below that limit can never be taken for the
    ground. Beyond the limit the scene's ground is out of reach: whatever the frame, it tilts the
    scan by at most the limit."""
    frame = ground_frame(seen_from(SCENE, 1.5, mount(roll, 0.0)))
    assert angle_deg(frame.rotation, np.eye(3)) <= MAX_HELD_TILT_DEG + 1e-9


def test_matrix_and_apply_agree():
    frame = ground_frame(seen_from(SCENE, 1.2, mount(10.0, 10.0)))
    points = np.random.default_rng(5).normal(0.0, 10.0, (100, 4)).astype(np.float32)
    homogeneous = np.column_stack([points[:, :3].astype(np.float64), np.ones(len(points))])
    np.testing.assert_allclose(frame.apply(points), (homogeneous @ frame.matrix.T)[:, :3], atol=1e-9)
    assert frame.apply(points).dtype == np.float64 and frame.apply(points).shape == (100, 3)
    identity = GroundFrame.identity()
    np.testing.assert_array_equal(identity.matrix, np.eye(4))
    np.testing.assert_array_equal(identity.apply(points), points[:, :3].astype(np.float64))


def test_non_finite_points_are_ignored():
    points = seen_from(SCENE, 1.8, mount(-14.0, 14.0))
    bad = np.array([[np.nan, 1.0, -1.0], [2.0, np.inf, -1.0], [3.0, 1.0, -np.inf], [np.nan] * 3])
    dirty = np.insert(points, [0, 100, 5000, len(points)], bad, axis=0)
    clean, frame = ground_frame(points), ground_frame(dirty)
    np.testing.assert_array_equal(frame.rotation, clean.rotation)
    assert frame.height == clean.height and frame.found


def fit_by_matrix_product(low: np.ndarray) -> tuple[np.ndarray, float] | None:
    """fit_ground written with a (lowest points x hypotheses) matrix product: its reference."""
    if len(low) < MIN_INLIERS:
        return None
    tri = low[np.random.default_rng(0x5EED).integers(0, len(low), size=(HYPOTHESES, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals = normals[ok] / norms[ok, None]
    normals *= np.sign(normals[:, 2:3]) + (normals[:, 2:3] == 0)
    heights = -np.einsum("hk,hk->h", normals, tri[ok, 0])
    ok = (normals[:, 2] >= math.cos(math.radians(MAX_TILT_DEG))) & (heights > 0)
    if not ok.any():
        return None
    normals, heights = normals[ok], heights[ok]
    signed = low @ normals.T + heights
    inliers = np.abs(signed) < INLIER_M
    best = int(np.argmax(inliers.sum(0) - 3 * (signed < -3 * INLIER_M).sum(0)))
    chosen = low[inliers[:, best]]
    if len(chosen) < MIN_INLIERS:
        return None
    centre = chosen.mean(0)
    normal = np.linalg.svd(chosen - centre, full_matrices=False)[2][2]
    normal = normal if normal[2] > 0 else -normal
    return normal, float(-normal @ centre)


@pytest.mark.parametrize("height, roll, pitch", [m for m in MOUNTS if angle_deg(mount(*m[1:]), np.eye(3)) < MAX_TILT_DEG])
def test_the_compiled_fit_is_the_matrix_product_fit(height, roll, pitch):
    """Same plane, bit for bit, on rough ground (other samples would give other planes)."""
    rough = SCENE.copy()
    rough[:, 2] += np.random.default_rng(7).normal(0.0, 0.08, len(rough)) * (rough[:, 2] < 0.2)
    low = lowest_points(seen_from(rough, height, mount(roll, pitch)), CELL_M, MIN_RANGE_M, MAX_RANGE_M)
    (normal, offset), (expected_normal, expected_offset) = fit_ground(low), fit_by_matrix_product(low)
    np.testing.assert_array_equal(normal, expected_normal)
    assert offset == expected_offset


def test_float32_points_and_extra_columns_give_the_frame_of_their_float64_xyz():
    points = seen_from(SCENE, 1.2, mount(10.0, 10.0)).astype(np.float32)
    with_intensity = np.column_stack([points, np.ones(len(points), np.float32)])
    expected = ground_frame(points[:, :3].astype(np.float64))
    for given in (points, with_intensity, with_intensity[:, :3]):
        frame = ground_frame(given)
        np.testing.assert_array_equal(frame.rotation, expected.rotation)
        assert frame.height == expected.height and frame.found
