"""``vbrl replay BAG``: publish a bag's clouds, odometry and poses over ROS 2, paced like the recording.

The player is :class:`~vbrl_ros.ros.bag_player.BagPlayer` (its docstring says
what is published, how it is paced and with which QoS); this module is its
command line.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vbrl_ros.ros.bag_player import QOS_CHOICES, BagPlayer
from vbrl_ros.tools.cli import run_parsed


def parse_remap(text: str) -> tuple[str, str]:
    """``"/points:=/velodyne_points"`` -> ("/points", "/velodyne_points")."""
    source, sep, target = text.partition(":=")
    if not sep or not source or not target:
        raise argparse.ArgumentTypeError(f"remap must look like /from:=/to, got {text!r}")
    return source, target


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``replay`` to the ``vbrl`` command."""
    parser = subparsers.add_parser("replay", help="publish a bag's clouds, odometry and /clock over ROS 2",
                                   description="Publish a bag's clouds, odometry and poses (and /clock) "
                                   "over ROS 2, paced like the recording. Needs no ros2 bag.")
    add = parser.add_argument
    add("bag", type=Path, help="ROS 2 bag directory (mcap/sqlite3), its file, or a ROS 1 .bag")
    add("--topics", nargs="+", metavar="TOPIC", help="bag topics to publish (default: clouds, odometry, poses)")
    add("--rate", type=float, default=1.0, help="speed factor over real time (default 1)")
    add("--start-offset", type=float, default=0.0, metavar="S", help="skip the bag's first S s")
    add("--duration", type=float, metavar="S", help="play only S s of bag time")
    add("--loop", action="store_true", help="play again and again until Ctrl-C")
    add("--delay", type=float, default=0.0, metavar="S", help="wait S s before the first message (discovery)")
    add("--wait-for-subscribers", type=int, default=0, metavar="N",
        help="first wait until each published topic (not the clock) has N subscribers")
    add("--wait-topics", nargs="+", metavar="TOPIC", help="only these published topics need the N subscribers")
    add("--wait-timeout", type=float, default=30.0, metavar="S", help="fail (exit 2) after S s of waiting")
    add("--remap", type=parse_remap, action="append", default=[], metavar="FROM:=TO",
        help="publish bag topic (or /clock) FROM as TO, e.g. /points:=/velodyne_points; repeatable")
    add("--qos", choices=QOS_CHOICES, default="reliable",
        help="clouds reliable (default: loss-free for evaluation, sensor-data subscribers still match) or "
             "sensor data (best effort, depth 5)")
    add("--clock-hz", type=float, default=40.0, help="clock ticks per wall second between messages (0: none)")
    add("--no-clock", action="store_true", help="do not publish /clock")
    add("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


class Interrupts:
    """SIGINT/SIGTERM stop the replay at the next message boundary instead of raising mid-call.

    A KeyboardInterrupt raised inside a DDS call (a publish holding rclpy's
    handle lock) can leave teardown waiting on that lock, so the first signal
    only sets ``stop`` — from a helper thread, since ``Event.set`` in a handler
    can deadlock on the lock the interrupted main thread holds. A second
    Ctrl-C interrupts at once, as usual.
    """

    def __init__(self, stop: threading.Event) -> None:
        self.stop, self.received, self._previous = stop, False, {}

    def __enter__(self) -> Interrupts:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        self.received = True
        signal.signal(signal.SIGINT, signal.default_int_handler)
        threading.Thread(target=self.stop.set, daemon=True).start()

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def run(args: argparse.Namespace) -> int:
    """Replay as the parsed ``args`` say; 0 when done, 130 when interrupted (bad input raises ReplayError)."""
    from vbrl_ros.ros.transport import use_large_data_profile

    use_large_data_profile()  # before rclpy: clouds of megabytes arrive whole, even best effort
    with BagPlayer(args.bag, topics=args.topics, rate=args.rate, start_offset=args.start_offset,
                   duration=args.duration, loop=args.loop, remaps=dict(args.remap), cloud_qos=args.qos,
                   clock=not args.no_clock, clock_hz=args.clock_hz) as player:
        print(f"replaying {player.total} messages from {args.bag} ({', '.join(player.topics)}) "
              f"at {args.rate:g}x", file=sys.stderr, flush=True)
        if (hint := mounting_hint(args.bag)) is not None:
            print(hint, file=sys.stderr, flush=True)
        # SIGTERM (e.g. a test harness or launch stopping us) takes the same orderly path as Ctrl-C.
        with Interrupts(threading.Event()) as interrupts:
            try:
                player.play(delay=args.delay, wait_for_subscribers=args.wait_for_subscribers,
                            wait_topics=args.wait_topics, wait_timeout=args.wait_timeout,
                            progress=False if args.quiet else None, stop=interrupts.stop)
            except KeyboardInterrupt:  # a second Ctrl-C
                interrupts.received = True
        if interrupts.received:
            print(f"interrupted: {player.stats.summary(args.rate)}", flush=True)
            return 130
        print(player.stats.summary(args.rate), flush=True)
    return 0


def mounting_hint(bag: str | Path) -> str | None:
    """One line telling ``vbrl_node`` where the LiDAR sits when the bag's odometry moves another frame
    than its clouds' (a robot's ``base_link``): the node has no tf to look it up."""
    from scipy.spatial.transform import Rotation

    from vbrl_ros.datasets.base import ScanSourceError
    from vbrl_ros.datasets.poses import lidar_mounting
    from vbrl_ros.datasets.rosbag import RosbagSource

    try:
        source = RosbagSource(bag)
    except ScanSourceError:  # no single cloud topic: nothing to say about its frame
        return None
    try:
        odometry = source.topics_of_type("nav_msgs/msg/Odometry")
        mounting = lidar_mounting(source, odometry[0]) if len(odometry) == 1 else None
    except Exception:  # a hint never stops a replay; what the player cannot read, it says itself
        mounting = None
    finally:
        source.close()
    if mounting is None:
        return None
    said = f"odometry on {odometry[0]} moves '{mounting.moved}', the clouds are in '{mounting.lidar}'"
    if mounting.T_moved_lidar is None:
        return f"{said}, and the bag's tf does not connect them: give vbrl_node odometry_lidar_pose"
    T = mounting.T_moved_lidar
    values = [*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_euler("xyz")]
    return (f"{said}: run vbrl_node with -p 'odometry_lidar_pose:=[{', '.join(f'{v:.6f}' for v in values)}]' "
            f"(the bag's tf)")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m vbrl_ros.tools.replay BAG ...``: the ``vbrl replay`` subcommand on its own."""
    parser = argparse.ArgumentParser(prog="vbrl")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["replay", *(sys.argv[1:] if argv is None else argv)])
    return run_parsed(args)


if __name__ == "__main__":
    sys.exit(main())
