"""Sensor mount: height and tilt reach the poses, and a tilted scan stays on the world's geometry."""

import argparse
import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vbrl_ros.datasets.mount_tilt import mount_rotation
from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.lidar import LidarConfig, level_cover, render_scan, tilt_angle
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town
from vbrl_ros.tools import simulate as cli

LIDAR = LidarConfig(beams=32, columns=512)
ROLL, PITCH = -12.0, 20.0


@pytest.fixture(scope="module")
def town():
    return generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)


def _roll_pitch_deg(pose: np.ndarray) -> tuple[float, float]:
    """Roll and pitch of T_world_lidar = Rz(yaw) Ry(pitch) Rx(roll)."""
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    tilt = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose[:3, :3]
    return math.degrees(math.atan2(tilt[2, 1], tilt[2, 2])), math.degrees(-math.asin(tilt[2, 0]))


def test_poses_carry_the_mount_height_and_tilt(town):
    level = make_route(town, RouteConfig(loops=1, spacing_m=5.0))
    mounted = make_route(town, RouteConfig(loops=1, spacing_m=5.0, sensor_height_m=0.8,
                                           sensor_roll_deg=ROLL, sensor_pitch_deg=PITCH))
    np.testing.assert_array_equal(mounted.positions[:, :2], level.positions[:, :2])
    np.testing.assert_allclose(mounted.positions[:, 2], 0.8)
    np.testing.assert_allclose(mounted.yaw, level.yaw, atol=1e-12)  # the heading still follows the path
    rotations = mounted.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)
    for pose in mounted.poses:
        np.testing.assert_allclose(_roll_pitch_deg(pose), (ROLL, PITCH), atol=1e-9)
    # Positive pitch tips the front (x axis) down; positive roll would lift the left side (y axis).
    np.testing.assert_allclose(rotations[:, 2, 0], -math.sin(math.radians(PITCH)))
    assert np.all(rotations[:, 2, 1] < 0)  # negative roll: the left side goes down
    assert math.degrees(tilt_angle(rotations[0])) == pytest.approx(
        math.degrees(math.acos(math.cos(math.radians(ROLL)) * math.cos(math.radians(PITCH)))))
    # Untilted poses are exactly yaw-only (the renderer's level path; scans stay bit-identical).
    assert np.all(level.poses[:, 2, :3] == [0.0, 0.0, 1.0]) and np.all(level.poses[:, :2, 2] == 0.0)


def test_tilted_points_are_a_level_render_of_the_same_place(town):
    """Noise-free, every point of a tilted scan is a point of the widened level render, moved
    into the tilted frame; with range noise, the world points agree with it within the noise."""
    route = make_route(town, RouteConfig(loops=1, spacing_m=5.0, sensor_roll_deg=ROLL, sensor_pitch_deg=PITCH))
    index = 7
    exact = LidarConfig(beams=32, columns=512, range_noise_std_m=0.0, intensity_noise_std=0.0)
    run = simulate_run(town, route, exact, "static", seed=0)
    scan, scene, pose = run.scan(index), run.scene_at(index), route.poses[index]
    cover = level_cover(exact, tilt_angle(pose[:3, :3]))
    assert cover.beams == 32 + 2 * math.ceil(math.degrees(tilt_angle(pose[:3, :3])) / (40.0 / 31))
    level_pose = pose.copy()
    yaw = route.yaw[index]
    level_pose[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    # The scan's own generator: the foliage is hit or passed at random.
    rng = np.random.default_rng([0, run.scenario.seed_salt, 2, index])
    level_points, level_labels, _ = render_scan(scene, level_pose, cover, rng)
    level_world = level_points[:, :3] @ level_pose[:3, :3].T + level_pose[:3, 3]
    tree = cKDTree(level_world)
    gap, nearest = tree.query(scan.points_world())
    assert len(scan.points) > 0.8 * len(simulate_run(town, make_route(town, RouteConfig(loops=1, spacing_m=5.0)),
                                                     exact, "static", seed=0).scan(index).points)
    assert gap.max() < 1e-3
    np.testing.assert_array_equal(scan.labels, level_labels[nearest])

    # In its own frame the scan fills the sensor's field of view and no more.
    xyz = scan.points[:, :3].astype(np.float64)
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    step = 40.0 / 31
    assert elevation.min() >= -30.0 - step / 2 - 1e-3 and elevation.max() <= 10.0 + step / 2 + 1e-3
    np.testing.assert_array_equal(scan.rings, np.rint((elevation + 30.0) / step).astype(np.uint16))
    assert scan.rings.min() == 0 and scan.rings.max() == 31

    # Same seed: the same rays pass through the (porous) tree crowns, then the noise is drawn.
    noisy = simulate_run(town, route, LIDAR, "static", seed=0).scan(index)
    gap, _ = tree.query(noisy.points_world())
    assert gap.max() < 5 * LIDAR.range_noise_std_m  # at most the noise along the ray
    ground = noisy.points_world()[noisy.labels == Material.GROUND]
    assert len(ground) > 1000 and np.abs(ground[:, 2]).max() < 5 * LIDAR.range_noise_std_m


def test_mount_fields_are_validated():
    for name in ("sensor_roll_deg", "sensor_pitch_deg"):
        for bad in (45.5, -60.0, math.nan, "10"):
            with pytest.raises(ValueError, match=name):
                RouteConfig(**{name: bad})
    with pytest.raises(ValueError, match="sensor_height_m"):
        RouteConfig(sensor_height_m=0.0)
    # Both at the limit is the renderer's limit: 60 degrees of tilt.
    assert math.degrees(tilt_angle(mount_rotation(45.0, 45.0))) == pytest.approx(60.0)


def _cli(argv):
    parser = argparse.ArgumentParser(prog="vbrl")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["simulate", *argv])
    return args.func(args)


def test_simulate_options_write_the_mount_into_poses_and_sidecar(tmp_path, capsys):
    tiny = ["--blocks", "2", "2", "--beams", "16", "--columns", "360", "--scans", "3", "--spacing", "3",
            "--quiet", "--format", "kitti"]
    assert _cli([str(tmp_path), *tiny, "--sensor-height", "0.9", "--tilt", "5", "-15"]) == 0
    assert "sensor 0.9 m up, tilted 15.8 deg" in capsys.readouterr().out
    expected = make_route(generate_town(TownConfig(blocks_x=2, blocks_y=2), 0),
                          RouteConfig(spacing_m=3.0, max_scans=3, sensor_height_m=0.9, sensor_roll_deg=5.0,
                                      sensor_pitch_deg=-15.0))
    poses = np.loadtxt(tmp_path / "summer_clear" / "poses.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(poses, expected.poses[:, :3], atol=1e-6)
    for pose in poses:
        np.testing.assert_allclose(_roll_pitch_deg(np.vstack([pose, [0, 0, 0, 1]])), (5.0, -15.0), atol=1e-4)
    route = json.loads((tmp_path / "summer_clear.sim.json").read_text())["route"]
    assert (route["sensor_height_m"], route["sensor_roll_deg"], route["sensor_pitch_deg"]) == (0.9, 5.0, -15.0)

    with pytest.raises(SystemExit):
        _cli(["--help"])
    help_text = capsys.readouterr().out
    assert "--sensor-height" in help_text and "--tilt ROLL PITCH" in help_text
    with pytest.raises(ValueError, match="sensor_roll_deg"):
        _cli([str(tmp_path / "a"), *tiny, "--tilt", "50", "0"])
    with pytest.raises(ValueError, match="beam level render"):  # before anything is written
        _cli([str(tmp_path / "b"), *tiny, "--beams", "500", "--tilt", "0", "30"])
    assert not (tmp_path / "b").exists()


def test_a_swaying_sensor_tilts_smoothly_about_its_mount_seed_by_seed(town):
    def sway(seed: int, **mount) -> np.ndarray:
        route = make_route(town, RouteConfig(loops=2, spacing_m=0.5, sensor_sway_deg=3.0, sensor_sway_seed=seed,
                                             **mount))
        return np.array([_roll_pitch_deg(pose) for pose in route.poses]), route

    angles, route = sway(1)
    level = make_route(town, RouteConfig(loops=2, spacing_m=0.5))
    np.testing.assert_array_equal(route.positions, level.positions)  # only the orientation sways
    np.testing.assert_allclose(route.yaw, level.yaw, atol=1e-12)
    assert np.abs(angles).max() <= 9.0 + 1e-9  # clipped at three standard deviations
    assert angles.std(axis=0) == pytest.approx([3.0, 3.0], rel=0.35)  # a few correlation lengths: not exact
    assert np.abs(np.diff(angles, axis=0)).max() < 1.5  # smooth: half a metre apart, within a degree or so
    assert abs(np.corrcoef(angles[:, 0], angles[:, 1])[0, 1]) < 0.3  # roll and pitch sway apart
    other, _ = sway(2)
    assert np.abs(other - angles).mean() > 1.0
    np.testing.assert_array_equal(sway(1)[0], angles)
    mounted, _ = sway(1, sensor_roll_deg=5.0, sensor_pitch_deg=-10.0)  # about the mount's tilt
    np.testing.assert_allclose(mounted - angles, np.broadcast_to([5.0, -10.0], angles.shape), atol=0.05)


def test_sway_is_validated_and_reaches_the_cli(tmp_path, capsys):
    for bad in (-1.0, 10.5, math.nan, "2"):
        with pytest.raises(ValueError, match="sensor_sway_deg"):
            RouteConfig(sensor_sway_deg=bad)
    with pytest.raises(ValueError, match="sensor_sway_deg"):  # the mount's 40 plus three times 2 is beyond 45
        RouteConfig(sensor_pitch_deg=40.0, sensor_sway_deg=2.0)
    with pytest.raises(ValueError, match="sensor_sway_seed"):
        RouteConfig(sensor_sway_seed=-1)
    tiny = ["--blocks", "2", "2", "--beams", "16", "--columns", "360", "--scans", "3", "--spacing", "3",
            "--quiet", "--format", "kitti"]
    assert _cli([str(tmp_path), *tiny, "--sway", "2", "--seed", "4"]) == 0
    assert "tilted 0.0 deg, swaying 2 deg" in capsys.readouterr().out
    route = json.loads((tmp_path / "summer_clear.sim.json").read_text())["route"]
    assert (route["sensor_sway_deg"], route["sensor_sway_seed"]) == (2.0, 4)  # drawn from the run seed
    poses = np.loadtxt(tmp_path / "summer_clear" / "poses.txt").reshape(-1, 3, 4)
    assert max(abs(a) for pose in poses for a in _roll_pitch_deg(np.vstack([pose, [0, 0, 0, 1]]))) > 0.1
