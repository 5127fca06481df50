"""``vbrl simulate``: render simulated LiDAR sessions to bags or KITTI-style folders.

One output per (scenario, run seed) pair, all on the same town and route, so
the outputs are sessions of the same places under different conditions.
Next to each output a ``<name>.sim.json`` records everything needed to
re-create it bit for bit.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, replace
from pathlib import Path

from vbrl_ros.datasets.mount_tilt import mount_rotation
from vbrl_ros.simulator.keyframes import KeyframeFilter
from vbrl_ros.simulator.lidar import LidarConfig, level_cover, tilt_angle
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import SimulatedRun, simulate_run
from vbrl_ros.simulator.scenarios import FOLIAGE_DENSITY, SCENARIO_PRESETS, WEATHER, Scenario
from vbrl_ros.simulator.town import TownConfig, generate_town
from vbrl_ros.tools.options import DefaultsHelpFormatter

FORMATS = ("mcap", "sqlite3", "ros1", "kitti")


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``simulate`` subcommand; its ``func`` is :func:`run`."""
    presets = ", ".join(SCENARIO_PRESETS)
    parser = subparsers.add_parser(
        "simulate",
        help="render simulated LiDAR sessions of a procedural town (bags or KITTI-style folders)",
        description=(
            "Ray-cast a spinning LiDAR along a looping route through a procedurally generated town "
            "and write one output per scenario and run seed: OUT/<scenario> (ROS 2 bag directory, "
            "mcap or sqlite3), OUT/<scenario>.bag (ROS 1) or OUT/<scenario>/ (KITTI-style: "
            "velodyne/NNNNNN.bin, poses.txt, times.txt). With several seeds the name gets a "
            "_seed<N> suffix. Bags hold sensor_msgs/PointCloud2 (x, y, z, intensity; sensor "
            "frame) plus nav_msgs/Odometry and geometry_msgs/PoseStamped ground truth."
        ),
        epilog=(f"scenario presets: {presets}; or any <season>_<weather> with season in "
                f"{', '.join(FOLIAGE_DENSITY)} and weather in {', '.join(WEATHER)}. "
                "Same town seed, run seed and scenario give bit-identical scans."),
        formatter_class=DefaultsHelpFormatter,
    )
    parser.add_argument("output", type=Path, help="output directory (created if missing)")
    parser.add_argument("--format", choices=FORMATS, default="mcap", help="output format")
    parser.add_argument("--scenario", nargs="+", default=["summer_clear"], metavar="NAME",
                        help="scenario(s); one output each")
    parser.add_argument("--seed", nargs="+", type=int, default=[1], metavar="N",
                        help="run seed(s): traffic, parked cars, noise; one output per scenario and seed")
    parser.add_argument("--list-scenarios", action=ListScenarios, help="print the presets and exit")

    town = parser.add_argument_group("town")
    town.add_argument("--town-seed", type=int, default=0, help="seed of the town layout")
    town.add_argument("--blocks", nargs=2, type=int, default=[5, 5], metavar=("NX", "NY"),
                      help="town size in blocks")
    town.add_argument("--block-size", nargs=2, type=float, default=[70.0, 110.0], metavar=("MIN", "MAX"),
                      help="range of block sizes between street centre lines (m)")

    route = parser.add_argument_group("route")
    route.add_argument("--loops", type=int, default=4, help="number of loops around the home intersection")
    sampling = route.add_mutually_exclusive_group()
    sampling.add_argument("--spacing", type=float, default=None,
                          help="one scan every SPACING metres of path (default 1.0 unless --rate is given)")
    sampling.add_argument("--rate", type=float, default=None, help="scan rate in Hz while driving at --speed")
    route.add_argument("--speed", type=float, default=8.0, help="cruise speed (m/s); slower in corners")
    route.add_argument("--sample-offset", type=float, default=0.0,
                       help="shift of the scan positions along the path (m); give sessions different offsets "
                            "so they do not scan from the same spots")
    route.add_argument("--scans", type=int, default=None, help="stop after this many scans (default: whole route)")
    route.add_argument("--lane-offset", type=float, default=1.0, metavar="M",
                       help="lane centre to the right of the street's centre line (m); streets driven both ways "
                            "are revisited 2*M apart")
    route.add_argument("--lane-wander", type=float, default=0.0, metavar="M",
                       help="amplitude (m, at most 3) of a smooth lateral wander about the lane, correlated over "
                            "~30 m of path and drawn from the run seed: sessions with different --seed drive "
                            "different lines; keep --lane-offset + --lane-wander under ~2.5 (parked cars)")

    lidar = parser.add_argument_group("lidar")
    lidar.add_argument("--beams", type=int, default=64, help="number of beams (rows)")
    lidar.add_argument("--columns", type=int, default=1800, help="horizontal resolution (columns per turn)")
    lidar.add_argument("--vertical-fov", nargs=2, type=float, default=None, metavar=("LOW", "HIGH"),
                       help="beam elevation range in degrees (default per beam count: 16: -15..15, "
                            "32: -30..10, 64: -25..15, 128: -22.5..22.5)")
    lidar.add_argument("--max-range", type=float, default=100.0, help="maximum range (m)")
    lidar.add_argument("--range-noise", type=float, default=0.02, help="range noise std (m), before weather")
    lidar.add_argument("--blocked-azimuth", nargs=2, type=float, default=None, metavar=("FROM", "TO"),
                       help="wedge the sensor cannot see (a mast, the robot's body): sensor-frame azimuth in "
                            "degrees (0 forward, 90 left), swept counter-clockwise from FROM to TO; e.g. "
                            "150 -150 hides the 60 degrees behind")

    mount = parser.add_argument_group("sensor mount (the poses written include it)")
    mount.add_argument("--sensor-height", type=float, default=1.8, metavar="M",
                       help="height of the LiDAR origin above the ground (m): ~0.5 on a small robot, "
                            "1.8 on a car roof, 2.4 on a mast")
    mount.add_argument("--tilt", nargs=2, type=float, default=[0.0, 0.0], metavar=("ROLL", "PITCH"),
                       help="fixed tilt of the sensor on its mount in degrees, each in [-45, 45]: positive roll "
                            "lifts the left side, positive pitch tips the front down (e.g. 0 20 for a "
                            "hand-held sensor pointed at the ground); a tilted sensor is rendered as a level "
                            "one with a widened field of view, cropped to its own")
    mount.add_argument("--sway", type=float, default=0.0, metavar="DEG",
                       help="the sensor's roll and pitch sway about its mount (standard deviation in degrees, at "
                            "most 10), smooth over ~5 m of path and drawn from the run seed: a two-wheeled robot "
                            "pitching as it brakes, a rover on rough ground, a hand-held sensor")

    keyframes = parser.add_argument_group("keyframe clouds (as SLAM front-ends publish them)")
    keyframes.add_argument("--thin-voxel", type=float, default=None, metavar="V",
                           help="keep one point per V-metre voxel of the sensor frame (the return nearest the "
                                "voxel's centroid)")
    keyframes.add_argument("--no-ground", action="store_true",
                           help="remove every return from the ground surface (the simulator's exact labels), "
                                "before thinning")

    ros = parser.add_argument_group("bag topics (ROS formats)")
    ros.add_argument("--cloud-topic", default="/points", help="PointCloud2 topic")
    ros.add_argument("--odom-topic", default="/odom", help="Odometry topic (ground-truth pose)")
    ros.add_argument("--frame-id", default="lidar", help="frame of the clouds")
    # --quiet as in every other command; --no-progress, its first name, still works
    parser.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)
    return parser


class ListScenarios(argparse.Action):
    """--list-scenarios prints the presets and exits while parsing, as --help does, so the
    output directory can stay a required argument (and say so in the usage)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        for name, scenario in SCENARIO_PRESETS.items():
            print(f"{name:14s} season={scenario.season:7s} weather={scenario.weather:6s} "
                  f"cars/km={scenario.moving_cars_per_km:g} pedestrians/km={scenario.pedestrians_per_km:g} "
                  f"parked_turnover={scenario.parked_turnover:g}")
        parser.exit()


def _output_path(folder: Path, name: str, fmt: str) -> Path:
    # ROS 2 bags are directories (a ".mcap" suffix would make readers take it for a file).
    return folder / (f"{name}.bag" if fmt == "ros1" else name)


def write_run(run: SimulatedRun, path: Path, fmt: str, *, progress: bool = True, cloud_topic: str = "/points",
              odom_topic: str = "/odom", frame_id: str = "lidar") -> Path:
    """Render ``run`` into ``path`` as a bag (mcap / sqlite3 / ros1) or a KITTI-style folder."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    clouds = run.point_clouds(progress=progress, description=path.name)
    if fmt == "kitti":
        from ..datasets.kitti_style import write_kitti_style

        return Path(write_kitti_style(path, clouds, run.poses, run.stamps))
    from ..io.bag_writer import write_scan_bag

    return Path(write_scan_bag(path, clouds, run.stamps, run.poses, storage="sqlite3" if fmt == "sqlite3" else "mcap",
                               cloud_topic=cloud_topic, odom_topic=odom_topic, frame_id=frame_id,
                               ros1=fmt == "ros1", progress=False))


def _describe(run: SimulatedRun, town_config: TownConfig, route_config: RouteConfig) -> dict:
    return {
        "town_seed": run.town.seed, "run_seed": run.seed, "scenario": asdict(run.scenario),
        "town": asdict(town_config), "route": asdict(route_config), "lidar": asdict(run.lidar),
        "keyframes": asdict(run.keyframes), "scans": len(run), "route_length_m": run.route.length_m,
        "loops": list(run.route.loop_names),
    }


def run(args: argparse.Namespace) -> int:
    """Execute ``vbrl simulate``; returns the exit code. Bad parameters raise ValueError."""
    scenarios = [Scenario.from_name(name) for name in args.scenario]
    if len({s.name for s in scenarios}) != len(scenarios) or len(set(args.seed)) != len(args.seed):
        raise ValueError("--scenario and --seed values must not repeat (outputs would collide)")
    town_config = TownConfig(blocks_x=args.blocks[0], blocks_y=args.blocks[1], block_size_m=tuple(args.block_size))
    spacing = args.spacing if args.spacing is not None or args.rate is not None else 1.0
    route_config = RouteConfig(loops=args.loops, spacing_m=spacing, rate_hz=args.rate, speed_mps=args.speed,
                               sample_offset_m=args.sample_offset, max_scans=args.scans,
                               sensor_height_m=args.sensor_height, sensor_roll_deg=args.tilt[0],
                               sensor_pitch_deg=args.tilt[1], sensor_sway_deg=args.sway,
                               lane_offset_m=args.lane_offset,
                               lane_wander_m=args.lane_wander)
    lidar = LidarConfig(beams=args.beams, columns=args.columns,
                        vertical_fov_deg=tuple(args.vertical_fov) if args.vertical_fov else None,
                        max_range_m=args.max_range, range_noise_std_m=args.range_noise,
                        blocked_azimuth_deg=tuple(args.blocked_azimuth) if args.blocked_azimuth else None)
    keyframes = KeyframeFilter(thin_voxel_m=args.thin_voxel, remove_ground=args.no_ground)
    tilt = tilt_angle(mount_rotation(route_config.sensor_roll_deg, route_config.sensor_pitch_deg))
    # the largest tilt the sway may reach: three standard deviations on each axis
    reach = 3.0 * route_config.sensor_sway_deg
    steepest = tilt_angle(mount_rotation(abs(route_config.sensor_roll_deg) + reach,
                                         abs(route_config.sensor_pitch_deg) + reach))
    if steepest > 0:  # a tilt too large for the beam count fails here, not after the first outputs
        level_cover(lidar, steepest)
    jobs = [(scenario, seed, scenario.name if len(args.seed) == 1 else f"{scenario.name}_seed{seed}")
            for scenario in scenarios for seed in args.seed]
    paths = [_output_path(args.output, name, args.format) for _, _, name in jobs]
    existing = [str(p) for p in paths if p.exists()]
    if existing:  # refuse before spending minutes rendering the first ones
        raise FileExistsError(f"output exists already, not overwriting: {', '.join(existing)}")

    town = generate_town(town_config, args.town_seed)
    # The wander and the sway are drawn from the run seed; without them every job drives the same route.
    job_routes = [replace(route_config,
                          lane_wander_seed=seed if route_config.lane_wander_m > 0 else route_config.lane_wander_seed,
                          sensor_sway_seed=seed if route_config.sensor_sway_deg > 0 else route_config.sensor_sway_seed)
                  for _, seed, _ in jobs]
    routes = {config: make_route(town, config) for config in dict.fromkeys(job_routes)}
    route = routes[job_routes[0]]
    print(f"town {args.blocks[0]}x{args.blocks[1]} blocks (seed {args.town_seed}), route {route.length_m:.0f} m "
          f"in {len(route.loop_names)} loops, {len(route)} scans of {lidar.beams}x{lidar.columns} rays, "
          f"sensor {route_config.sensor_height_m:g} m up, tilted {math.degrees(tilt):.1f} deg"
          + (f", swaying {route_config.sensor_sway_deg:g} deg" if route_config.sensor_sway_deg > 0 else ""))
    args.output.mkdir(parents=True, exist_ok=True)
    for (scenario, seed, name), path, config in zip(jobs, paths, job_routes):
        sim = simulate_run(town, routes[config], lidar, scenario, seed, keyframes)
        started = time.perf_counter()
        written = write_run(sim, path, args.format, progress=not args.quiet, cloud_topic=args.cloud_topic,
                            odom_topic=args.odom_topic, frame_id=args.frame_id)
        sidecar = args.output / f"{name}.sim.json"
        sidecar.write_text(json.dumps(_describe(sim, town_config, config), indent=2) + "\n")
        print(f"wrote {written} ({len(sim)} scans, {time.perf_counter() - started:.1f} s)")
    return 0
