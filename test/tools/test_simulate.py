"""``vbrl simulate``: options, outputs per scenario, refusal to overwrite."""

import argparse
import json

import numpy as np
import pytest

from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town
from vbrl_ros.tools import simulate as cli

TINY = ["--blocks", "2", "2", "--beams", "16", "--columns", "360", "--scans", "4", "--spacing", "3",
        "--no-progress"]


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
                   "--scans", "--sample-offset", "--beams", "--columns", "--vertical-fov", "winter_snow", "kitti", "sqlite3", "ros1"):
        assert option in text


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
