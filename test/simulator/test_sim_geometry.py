"""Ray-primitive intersection against analytic ranges and surface equations."""

import math

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import (Boxes, Cylinders, Ellipsoids, Material, PrimitiveKind, intersect_boxes,
                                         intersect_cylinders, intersect_ellipsoids, intersect_ground)
from vbrl_ros.simulator.scene import Scene


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _scene(boxes=None, cylinders=None, ellipsoids=None):
    return Scene(boxes or Boxes.empty(), cylinders or Cylinders.empty(), ellipsoids or Ellipsoids.empty())


def test_axis_aligned_box_range_and_normal():
    t, normal = intersect_boxes(np.zeros(3), _unit([[1, 0, 0]]), np.array([[10.0, 0, 0]]),
                                np.array([[1.0, 2.0, 3.0]]), np.array([0.0]))
    assert t[0] == pytest.approx(9.0)
    np.testing.assert_allclose(normal[0], [-1, 0, 0], atol=1e-12)


def test_rotated_box_range_matches_face_plane():
    # Box yawed 30 deg; the ray along +x enters through the local -x face.
    yaw = math.radians(30)
    t, normal = intersect_boxes(np.zeros(3), _unit([[1, 0, 0]]), np.array([[10.0, 0, 0]]),
                                np.array([[1.0, 4.0, 3.0]]), np.array([yaw]))
    assert t[0] == pytest.approx(10.0 - 1.0 / math.cos(yaw))
    np.testing.assert_allclose(normal[0], [-math.cos(yaw), -math.sin(yaw), 0], atol=1e-12)


def test_box_diagonal_ray_and_misses():
    origin = np.array([0.0, 0.0, 0.0])
    dirs = _unit([[1, 1, 0], [1, -1, 0], [-1, 0, 0], [0, 0, 1]])
    centres = np.repeat([[5.0, 5.0, 0.0]], 4, axis=0)
    t, _ = intersect_boxes(origin, dirs, centres, np.ones((4, 3)), np.zeros(4))
    assert t[0] == pytest.approx(4.0 * math.sqrt(2))  # corner (4, 4, 0)
    assert np.all(np.isinf(t[1:]))


def test_ray_from_inside_a_box_sees_nothing_of_it():
    t, _ = intersect_boxes(np.zeros(3), _unit([[1, 0, 0]]), np.zeros((1, 3)), np.ones((1, 3)), np.zeros(1))
    assert np.isinf(t[0])


def test_cylinder_side_and_cap():
    centre, radius = np.array([[10.0, 0.0]]), np.array([0.5])
    t_side, n_side = intersect_cylinders(np.array([0.0, 0.0, 1.0]), _unit([[1, 0, 0]]), centre, radius,
                                         np.array([0.0]), np.array([3.0]))
    assert t_side[0] == pytest.approx(9.5)
    np.testing.assert_allclose(n_side[0], [-1, 0, 0], atol=1e-12)
    # Looking straight down onto the top cap from 2 m above it.
    t_cap, n_cap = intersect_cylinders(np.array([10.0, 0.2, 5.0]), _unit([[0, 0, -1]]), centre, radius,
                                       np.array([0.0]), np.array([3.0]))
    assert t_cap[0] == pytest.approx(2.0)
    np.testing.assert_allclose(n_cap[0], [0, 0, 1])
    # Passing above the top misses.
    t_miss, _ = intersect_cylinders(np.array([0.0, 0.0, 3.5]), _unit([[1, 0, 0]]), centre, radius,
                                    np.array([0.0]), np.array([3.0]))
    assert np.isinf(t_miss[0])


def test_sphere_and_ellipsoid_ranges():
    t, normal = intersect_ellipsoids(np.zeros(3), _unit([[0, 1, 0]]), np.array([[0.0, 10.0, 0.0]]),
                                     np.array([[2.0, 2.0, 2.0]]))
    assert t[0] == pytest.approx(8.0)
    np.testing.assert_allclose(normal[0], [0, -1, 0], atol=1e-12)
    # Ellipsoid with semi-axes (1, 1, 2) centred 10 m ahead, ray 1 m below centre:
    # (y - 10)^2 + (1/2)^2 = 1 -> y = 10 - sqrt(3)/2.
    t, _ = intersect_ellipsoids(np.array([0.0, 0.0, 1.0]), _unit([[0, 1, 0]]), np.array([[0.0, 10.0, 2.0]]),
                                np.array([[1.0, 1.0, 2.0]]))
    assert t[0] == pytest.approx(10.0 - math.sqrt(3) / 2)


def test_ground_plane_range():
    dirs = _unit([[1, 0, -1], [1, 0, 0.1]])
    t = intersect_ground(np.array([0.0, 0.0, 1.8]), dirs)
    assert t[0] == pytest.approx(1.8 * math.sqrt(2))
    assert np.isinf(t[1])


def _random_scene(rng):
    n = 12
    boxes = Boxes(center=np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(1, 4, n)]),
                  half_size=rng.uniform(0.5, 3, (n, 3)), yaw=rng.uniform(-3, 3, n),
                  material=np.full(n, Material.BUILDING))
    cylinders = Cylinders(center_xy=rng.uniform(-30, 30, (n, 2)), radius=rng.uniform(0.1, 1, n),
                          z_min=np.zeros(n), z_max=rng.uniform(2, 8, n), material=np.full(n, Material.POLE))
    ellipsoids = Ellipsoids(center=np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(3, 6, n)]),
                            radii=rng.uniform(0.5, 3, (n, 3)), material=np.full(n, Material.FOLIAGE))
    return _scene(boxes, cylinders, ellipsoids)


def test_hits_lie_on_the_surface_of_the_primitive_they_report():
    rng = np.random.default_rng(7)
    scene = _random_scene(rng)
    origin = np.array([0.5, -0.3, 1.8])
    dirs = _unit(rng.normal(size=(4000, 3)))
    hits = scene.cast(origin, dirs, max_range=200.0)
    points = origin + dirs * np.where(np.isfinite(hits.range), hits.range, 0.0)[:, None]
    kinds = {int(k) for k in np.unique(hits.kind)}
    assert {PrimitiveKind.GROUND, PrimitiveKind.BOX, PrimitiveKind.CYLINDER, PrimitiveKind.ELLIPSOID} <= kinds

    ground = hits.kind == PrimitiveKind.GROUND
    np.testing.assert_allclose(points[ground, 2], 0.0, atol=1e-9)

    box = hits.kind == PrimitiveKind.BOX
    b, i = scene.boxes, hits.index[box]
    rel = points[box] - b.center[i]
    c, s = np.cos(b.yaw[i]), np.sin(b.yaw[i])
    local = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]])
    # On the surface: inside or on all slabs, and on at least one face.
    np.testing.assert_allclose(np.max(np.abs(local) / b.half_size[i], axis=1), 1.0, atol=1e-9)

    cyl = hits.kind == PrimitiveKind.CYLINDER
    cb, i = scene.cylinders, hits.index[cyl]
    radial = np.linalg.norm(points[cyl, :2] - cb.center_xy[i], axis=1)
    on_side = np.isclose(radial, cb.radius[i], atol=1e-9)
    on_cap = np.isclose(points[cyl, 2], cb.z_max[i], atol=1e-9) & (radial <= cb.radius[i] + 1e-9)
    assert np.all(on_side | on_cap)

    ell = hits.kind == PrimitiveKind.ELLIPSOID
    eb, i = scene.ellipsoids, hits.index[ell]
    level = np.sum(((points[ell] - eb.center[i]) / eb.radii[i]) ** 2, axis=1)
    np.testing.assert_allclose(level, 1.0, atol=1e-9)

    # Normals are unit and face the ray.
    hit = np.isfinite(hits.range)
    np.testing.assert_allclose(np.linalg.norm(hits.normal[hit], axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", hits.normal[hit], dirs[hit]) <= 1e-9)


def test_nearest_primitive_wins_and_max_range_clips():
    boxes = Boxes(center=[[20.0, 0, 1], [10.0, 0, 1]], half_size=np.ones((2, 3)), yaw=[0.0, 0.0],
                  material=[Material.BUILDING, Material.WALL])
    scene = _scene(boxes)
    hits = scene.cast(np.array([0.0, 0, 1]), _unit([[1, 0, 0]]))
    assert hits.range[0] == pytest.approx(9.0)
    assert hits.material[0] == Material.WALL and hits.index[0] == 1
    clipped = scene.cast(np.array([0.0, 0, 1]), _unit([[1, 0, 0]]), max_range=5.0)
    assert np.isinf(clipped.range[0]) and clipped.kind[0] == PrimitiveKind.NONE


def test_porous_primitive_lets_the_expected_share_through():
    fence = Boxes(center=[[5.0, 0, 1]], half_size=[[0.05, 10, 1]], yaw=[0.0], material=[Material.FENCE],
                  density=[0.3])
    wall = Boxes(center=[[10.0, 0, 1]], half_size=[[0.5, 20, 1]], yaw=[0.0], material=[Material.WALL])
    scene = _scene(Boxes.concat([fence, wall]))
    angles = np.linspace(-0.5, 0.5, 20000)
    dirs = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    hits = scene.cast(np.array([0.0, 0, 1]), dirs, rng=np.random.default_rng(0))
    on_fence = np.mean(hits.material == Material.FENCE)
    assert on_fence == pytest.approx(0.3, abs=0.02)
    assert np.all((hits.material == Material.FENCE) | (hits.material == Material.WALL))
    # Without a generator every primitive is solid.
    assert np.all(scene.cast(np.array([0.0, 0, 1]), dirs).material == Material.FENCE)


def test_batches_validate_their_inputs():
    with pytest.raises(ValueError, match="half_size"):
        Boxes(center=[[0.0, 0, 0]], half_size=[[1.0, -1, 1]], yaw=[0.0], material=[1])
    with pytest.raises(ValueError, match="density"):
        Ellipsoids(center=[[0.0, 0, 0]], radii=[[1.0, 1, 1]], material=[1], density=[0.0])
    with pytest.raises(ValueError, match="Cylinders"):
        Cylinders(center_xy=[[0.0, 0]], radius=[1.0], z_min=[2.0], z_max=[1.0], material=[1])
