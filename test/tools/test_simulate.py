"""``vbrl simulate``: options, outputs per scenario, refusal to overwrite, degradations."""

import argparse
import json
from dataclasses import replace

import numpy as np
import pytest

from vbrl_ros.simulator.keyframes import KeyframeFilter
from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town
from vbrl_ros.tools import simulate as cli

TINY = ["--blocks", "2", "2", "--beams", "16", "--columns", "360", "--scans", "4", "--spacing", "3",
        "--quiet"]
KITTI_LOW = [*TINY, "--format", "kitti", "--sensor-height", "0.8"]
DEGRADED = ["--blocked-azimuth", "150", "-150", "--thin-voxel", "0.5", "--no-ground", "--lane-offset", "0.8",
            "--lane-wander", "1.5"]


def _parser():
    parser = argparse.ArgumentParser(prog="vbrl")
    cli.register(parser.add_subparsers(dest="command", required=True))
    return parser


def _run(argv):
    args = _parser().parse_args(["simulate", *argv])
    return args.func(args)


def test_help_documents_every_option(capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(["simulate", "--help"])
    text = capsys.readouterr().out
    for option in ("--format", "--scenario", "--seed", "--town-seed", "--blocks", "--loops", "--spacing", "--rate",
                   "--scans", "--sample-offset", "--beams", "--columns", "--vertical-fov", "winter_snow", "kitti",
                   "sqlite3", "ros1", "--blocked-azimuth FROM TO", "--thin-voxel V", "--no-ground", "--lane-offset M",
                   "--lane-wander M", "--quiet, --no-progress"):
        assert option in text


@pytest.mark.parametrize("flag", ["--quiet", "--no-progress"])
def test_quiet_as_in_every_command_and_its_first_name_still_works(flag):
    assert _parser().parse_args(["simulate", "out", flag]).quiet
    assert not _parser().parse_args(["simulate", "out"]).quiet


def test_kitti_output_per_scenario_matches_the_library(tmp_path):
    assert _run([str(tmp_path), "--format", "kitti", "--scenario", "summer_clear", "winter_snow", *TINY]) == 0
    for name in ("summer_clear", "winter_snow"):
        folder = tmp_path / name
        bins = sorted((folder / "velodyne").glob("*.bin"))
        assert len(bins) == 4
        poses = np.loadtxt(folder / "poses.txt")
        assert poses.shape == (4, 12)
        meta = json.loads((tmp_path / f"{name}.sim.json").read_text())
        assert meta["scenario"]["name"] == name and meta["scans"] == 4
    # The first scan on disk is exactly what the library renders for the same settings.
    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)
    route = make_route(town, RouteConfig(spacing_m=3.0, max_scans=4))
    expected = simulate_run(town, route, LidarConfig(beams=16, columns=360), "winter_snow", 1).scan(0).points
    on_disk = np.fromfile(tmp_path / "winter_snow" / "velodyne" / bins[0].name, dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(on_disk, expected)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "winter_snow" / "poses.txt")[0],
                               route.poses[0, :3].reshape(-1), atol=1e-6)


def test_bag_output_and_several_seeds(tmp_path):
    assert _run([str(tmp_path), "--seed", "3", "4", *TINY]) == 0
    for name in ("summer_clear_seed3", "summer_clear_seed4"):
        metadata = (tmp_path / name / "metadata.yaml").read_text()
        assert "/points" in metadata and "/odom" in metadata
        assert list((tmp_path / name).glob("*.mcap"))


def test_refuses_to_overwrite_and_rejects_bad_values(tmp_path):
    (tmp_path / "summer_clear").mkdir()
    with pytest.raises(FileExistsError):
        _run([str(tmp_path), "--format", "kitti", *TINY])
    with pytest.raises(ValueError, match="unknown scenario"):
        _run([str(tmp_path / "x"), "--scenario", "tropical_clear", *TINY])
    with pytest.raises(ValueError, match="beams"):
        _run([str(tmp_path / "x"), "--beams", "0"])
    with pytest.raises(SystemExit):  # argparse: --spacing and --rate exclude each other
        _parser().parse_args(["simulate", str(tmp_path), "--spacing", "1", "--rate", "10"])


def test_list_scenarios_needs_no_output(capsys):
    with pytest.raises(SystemExit) as exit_info:
        _parser().parse_args(["simulate", "--list-scenarios"])
    assert exit_info.value.code == 0
    assert "autumn_fog" in capsys.readouterr().out


def test_the_output_is_required_and_shown_so(capsys):
    with pytest.raises(SystemExit) as exit_info:
        _parser().parse_args(["simulate", "--format", "kitti"])
    assert exit_info.value.code == 2
    assert "required: output" in capsys.readouterr().err
    usage = _parser()._subparsers._group_actions[0].choices["simulate"].format_usage()
    assert " output" in usage and "[output]" not in usage


# -- degradations: blocked wedge, thinned ground-free keyframes, lane offset and wander --


def _kitti(folder):
    bins = sorted((folder / "velodyne").glob("*.bin"))
    clouds = [np.fromfile(path, dtype="<f4").reshape(-1, 4) for path in bins]
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    return clouds, poses


def test_degraded_outputs_are_what_the_library_renders(tmp_path):
    assert _run([str(tmp_path), *KITTI_LOW, *DEGRADED, "--seed", "3", "4"]) == 0
    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)
    config = RouteConfig(spacing_m=3.0, max_scans=4, sensor_height_m=0.8, lane_offset_m=0.8, lane_wander_m=1.5)
    lidar = LidarConfig(beams=16, columns=360, blocked_azimuth_deg=(150.0, -150.0))
    keyframes = KeyframeFilter(thin_voxel_m=0.5, remove_ground=True)
    poses = {}
    for seed in (3, 4):
        clouds, poses[seed] = _kitti(tmp_path / f"summer_clear_seed{seed}")
        route = make_route(town, replace(config, lane_wander_seed=seed))  # the wander is the run seed's
        np.testing.assert_allclose(poses[seed], route.poses[:, :3], atol=1e-6)
        expected = simulate_run(town, route, lidar, "summer_clear", seed, keyframes)
        for index, cloud in enumerate(clouds):
            np.testing.assert_array_equal(cloud, expected.scan(index).points)
            azimuth = np.degrees(np.arctan2(cloud[:, 1], cloud[:, 0]))
            assert not np.any(np.abs(azimuth) >= 150.0)  # nothing in the 60 degrees behind
            voxels = np.floor(cloud[:, :3] / 0.5).astype(np.int64)
            assert len(np.unique(voxels, axis=0)) == len(voxels)
            world_z = cloud[:, :3].astype(np.float64) @ poses[seed][index][:, :3].T[:, 2] + poses[seed][index][2, 3]
            assert np.mean(np.abs(world_z) < 0.05) < 0.05  # the ground (z = 0) is gone
        sidecar = json.loads((tmp_path / f"summer_clear_seed{seed}.sim.json").read_text())
        assert sidecar["lidar"]["blocked_azimuth_deg"] == [150.0, -150.0]
        assert sidecar["keyframes"] == {"thin_voxel_m": 0.5, "remove_ground": True}
        assert (sidecar["route"]["lane_offset_m"], sidecar["route"]["lane_wander_m"]) == (0.8, 1.5)
        assert sidecar["route"]["lane_wander_seed"] == seed
    lateral = np.linalg.norm(poses[3][:, :2, 3] - poses[4][:, :2, 3], axis=1)
    assert 0.05 < lateral.max() < 3.0  # two sessions, two lines


def test_defaults_write_the_plain_scans_and_record_the_options_off(tmp_path):
    assert _run([str(tmp_path), *KITTI_LOW]) == 0
    clouds, _ = _kitti(tmp_path / "summer_clear")
    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)
    route = make_route(town, RouteConfig(spacing_m=3.0, max_scans=4, sensor_height_m=0.8))
    np.testing.assert_array_equal(clouds[2], simulate_run(town, route, LidarConfig(beams=16, columns=360),
                                                          "summer_clear", 1).scan(2).points)
    sidecar = json.loads((tmp_path / "summer_clear.sim.json").read_text())
    assert sidecar["keyframes"] == {"thin_voxel_m": None, "remove_ground": False}
    assert sidecar["lidar"]["blocked_azimuth_deg"] is None
    assert (sidecar["route"]["lane_wander_m"], sidecar["route"]["lane_wander_seed"]) == (0.0, 0)


@pytest.mark.parametrize(("option", "field"), [(["--blocked-azimuth", "10", "10"], "blocked_azimuth_deg"),
                                               (["--thin-voxel", "0"], "thin_voxel_m"),
                                               (["--lane-wander", "4"], "lane_wander_m"),
                                               (["--lane-offset", "-1"], "lane_offset_m")])
def test_bad_values_fail_before_anything_is_written(tmp_path, option, field):
    with pytest.raises(ValueError, match=field):
        _run([str(tmp_path / "out"), *KITTI_LOW, *option])
    assert not (tmp_path / "out").exists()
