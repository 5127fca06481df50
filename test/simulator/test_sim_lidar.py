"""Spinning LiDAR: beam layout, culling == brute force, sensor frame, output format."""

import math

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import Boxes, Cylinders, Ellipsoids, Material, PrimitiveKind
from vbrl_ros.simulator.scene import Scene
from vbrl_ros.simulator.lidar import LidarConfig, candidate_pairs, render_scan
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town


@pytest.fixture(scope="module")
def town_and_route():
    town = generate_town(TownConfig(blocks_x=3, blocks_y=3), 11)
    return town, make_route(town, RouteConfig(loops=2, spacing_m=5.0))


def _pose(x, y, yaw, z=1.8):
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    pose[:3, 3] = [x, y, z]
    return pose


def test_beam_layout():
    lidar = LidarConfig(beams=64, columns=1800)
    assert lidar.vertical_fov_deg == (-25.0, 15.0)
    elevations = np.degrees(lidar.elevations())
    assert elevations[0] == pytest.approx(-25.0) and elevations[-1] == pytest.approx(15.0)
    dirs = lidar.directions()
    assert dirs.shape == (64 * 1800, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert LidarConfig(beams=16).vertical_fov_deg == (-15.0, 15.0)


def test_culled_pairs_give_exactly_the_brute_force_hits(town_and_route):
    town, route = town_and_route
    scene = town.reference_scene()
    lidar = LidarConfig(beams=8, columns=100, vertical_fov_deg=(-25.0, 15.0))
    for index in (0, len(route) // 2):
        pose = route.poses[index]
        yaw = math.atan2(pose[1, 0], pose[0, 0])
        dirs = lidar.directions() @ pose[:3, :3].T
        brute = scene.cast(pose[:3, 3], dirs, lidar.max_range_m)
        culled = scene.cast(pose[:3, 3], dirs, lidar.max_range_m, candidate_pairs(scene, lidar, pose[:3, 3], yaw))
        np.testing.assert_array_equal(culled.range, brute.range)
        np.testing.assert_array_equal(culled.material, brute.material)
        pairs = candidate_pairs(scene, lidar, pose[:3, 3], yaw)
        n_pairs = sum(len(r) for r, _ in pairs.values())
        n_all = lidar.n_rays * (len(scene.boxes) + len(scene.cylinders) + len(scene.ellipsoids))
        assert n_pairs < 0.02 * n_all  # the culling actually culls


def test_culling_keeps_primitives_around_and_above_the_sensor():
    # Sensor under a bridge, beside a pole, under a tree crown and next to a wall:
    # the cases where the angular window must wrap or cover the full turn.
    boxes = Boxes(center=[[0.0, 0.0, 6.0], [3.0, 0.0, 1.0], [-40.0, 5.0, 3.0]],
                  half_size=[[20.0, 4.0, 0.5], [0.2, 6.0, 1.0], [1.0, 10.0, 3.0]], yaw=[0.3, 0.0, 2.0],
                  material=[Material.BUILDING, Material.WALL, Material.BUILDING])
    cylinders = Cylinders(center_xy=[[0.6, 0.0], [-1.0, -3.0]], radius=[0.3, 0.2], z_min=[0.0, 0.0],
                          z_max=[3.0, 8.0], material=[Material.POLE, Material.POLE])
    crowns = Ellipsoids(center=[[0.5, 0.5, 5.0], [-8.0, -9.0, 4.0]], radii=[[3.0, 3.0, 2.0], [2.0, 2.0, 3.0]],
                        material=[Material.FOLIAGE, Material.CONIFER])
    scene = Scene(boxes, cylinders, crowns)
    lidar = LidarConfig(beams=32, columns=400, vertical_fov_deg=(-60.0, 60.0))
    for yaw in (0.0, 3.1, -2.0):
        pose = _pose(0.0, 0.0, yaw)
        dirs = lidar.directions() @ pose[:3, :3].T
        brute = scene.cast(pose[:3, 3], dirs, lidar.max_range_m)
        culled = scene.cast(pose[:3, 3], dirs, lidar.max_range_m, candidate_pairs(scene, lidar, pose[:3, 3], yaw))
        np.testing.assert_array_equal(culled.range, brute.range)
        np.testing.assert_array_equal(culled.index, brute.index)
        assert set(np.unique(brute.material).tolist()) >= {Material.BUILDING, Material.WALL, Material.POLE,
                                                           Material.FOLIAGE}


def test_sensor_frame_axes_single_wall():
    # A wall 10 m north of the sensor; the sensor faces north (yaw +90 deg):
    # in the sensor frame the wall is straight ahead (+x), 10 m away.
    wall = Boxes(center=[[0.0, 10.5, 2.0]], half_size=[[0.5, 5.0, 2.0]], yaw=[math.pi / 2],
                 material=[Material.WALL])
    scene = Scene(wall, Cylinders.empty(), Ellipsoids.empty())
    lidar = LidarConfig(beams=16, columns=360, range_noise_std_m=0.0, intensity_noise_std=0.0)
    points, labels, rings = render_scan(scene, _pose(0.0, 0.0, math.pi / 2), lidar, np.random.default_rng(0))
    on_wall = points[labels == Material.WALL]
    assert len(on_wall) > 50
    np.testing.assert_allclose(on_wall[:, 0], 10.0, atol=1e-4)
    assert np.abs(on_wall[:, 1]).max() <= 5.0 + 1e-4
    ground = points[labels == Material.GROUND]
    np.testing.assert_allclose(ground[:, 2], -1.8, atol=1e-4)
    assert rings.max() < 16 and rings.dtype == np.uint16


def test_points_transformed_by_the_pose_land_on_world_geometry(town_and_route):
    town, route = town_and_route
    lidar = LidarConfig(beams=32, columns=900, range_noise_std_m=0.0)
    run = simulate_run(town, route, lidar, "static", seed=0)
    scan = run.scan(len(run) // 2)
    world = scan.points_world()
    scene = run.scene_at(scan.index)
    np.testing.assert_allclose(world[scan.labels == Material.GROUND, 2], 0.0, atol=1e-3)

    buildings = scene.boxes.take(scene.boxes.material == Material.BUILDING)
    pts = world[scan.labels == Material.BUILDING]
    assert len(pts) > 500
    rel = pts[:, None] - buildings.center[None]
    c, s = np.cos(buildings.yaw), np.sin(buildings.yaw)
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    # Distance outside / inside each box; a surface point is ~0 for its box.
    surface_gap = np.abs(np.max(np.abs(local) - buildings.half_size[None], axis=-1))
    assert np.max(surface_gap.min(axis=1)) < 2e-3

    trunks = scene.cylinders.take(scene.cylinders.material == Material.TRUNK)
    pts = world[scan.labels == Material.TRUNK]
    radial = np.linalg.norm(pts[:, None, :2] - trunks.center_xy[None], axis=-1) - trunks.radius[None]
    assert len(pts) > 20 and np.max(np.abs(radial).min(axis=1)) < 2e-3


def test_output_format_and_ranges(town_and_route):
    town, route = town_and_route
    lidar = LidarConfig(beams=32, columns=900, max_range_m=60.0, min_range_m=1.0)
    scan = simulate_run(town, route, lidar, "summer_clear", seed=3).scan(0)
    assert scan.points.dtype == np.float32 and scan.points.ndim == 2 and scan.points.shape[1] == 4
    assert len(scan.points) == len(scan.labels) == len(scan.rings)
    ranges = np.linalg.norm(scan.points[:, :3], axis=1)
    assert ranges.min() >= 1.0 - 1e-4 and ranges.max() <= 60.0 + 1e-4
    assert 0.0 <= scan.points[:, 3].min() and scan.points[:, 3].max() <= 1.0
    assert np.all(scan.labels != Material.NONE)
    # Rays into the sky return nothing: fewer points than rays.
    assert len(scan.points) < lidar.n_rays


def test_intensity_depends_on_material_and_incidence():
    wall = Boxes(center=[[10.5, 0.0, 3.0]], half_size=[[0.5, 30.0, 3.0]], yaw=[0.0], material=[Material.WALL])
    scene = Scene(wall, Cylinders.empty(), Ellipsoids.empty())
    lidar = LidarConfig(beams=16, columns=720, range_noise_std_m=0.0, intensity_noise_std=0.0)
    points, labels, rings = render_scan(scene, _pose(0, 0, 0), lidar, np.random.default_rng(0))
    on_wall = points[labels == Material.WALL]
    wall_rings = rings[labels == Material.WALL]
    azimuth = np.abs(np.arctan2(on_wall[:, 1], on_wall[:, 0]))
    head_on, grazing = on_wall[azimuth < 0.1, 3], on_wall[azimuth > 1.0, 3]
    assert head_on.mean() > 1.5 * grazing.mean()  # incidence cosine and range falloff
    one_ring = on_wall[wall_rings == wall_rings[0]]
    assert np.corrcoef(np.abs(one_ring[:, 1]), one_ring[:, 3])[0, 1] < -0.9
    ground = points[(labels == Material.GROUND) & (np.linalg.norm(points[:, :2], axis=1) < 9)]
    assert on_wall[azimuth < 0.1, 3].mean() > ground[:, 3].mean()  # plaster brighter than asphalt


def test_overly_tilted_or_improper_pose_is_rejected():
    scene = Scene(Boxes.empty(), Cylinders.empty(), Ellipsoids.empty())
    lidar = LidarConfig(beams=16, columns=90)
    tilted = _pose(0, 0, 0)
    tilted[:3, :3] = [[1, 0, 0], [0, math.cos(1.2), -math.sin(1.2)], [0, math.sin(1.2), math.cos(1.2)]]
    with pytest.raises(ValueError, match="tilts the sensor by 68.8"):
        render_scan(scene, tilted, lidar, np.random.default_rng(0))
    mirrored = _pose(0, 0, 0)
    mirrored[1, 1] = -1.0
    with pytest.raises(ValueError, match="rotation"):
        render_scan(scene, mirrored, lidar, np.random.default_rng(0))


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"beams": 0}, "beams"), ({"columns": 4}, "columns"), ({"vertical_fov_deg": (10.0, -10.0)}, "vertical_fov"),
     ({"max_range_m": -1.0}, "max_range_m"), ({"min_range_m": 200.0}, "min_range_m"),
     ({"range_noise_std_m": -0.1}, "range_noise_std_m")],
)
def test_bad_config_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        LidarConfig(**changes)


def test_only_ground_kind_has_no_index():
    scene = Scene(Boxes.empty(), Cylinders.empty(), Ellipsoids.empty())
    lidar = LidarConfig(beams=16, columns=90)
    dirs = lidar.directions()
    hits = scene.cast(np.array([0.0, 0.0, 1.8]), dirs, 100.0)
    assert set(np.unique(hits.kind).tolist()) == {PrimitiveKind.NONE, PrimitiveKind.GROUND}
    assert np.all(hits.index == -1)
