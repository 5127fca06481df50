"""Drive a real ``vbrl_node`` process with a replayed bag and score what it publishes.

Used by ``vbrl demo`` and by the end-to-end tests: simulate session bags,
start the node on an isolated ROS domain, replay a bag into it, collect its
loop closures and diagnostics, stop it with SIGINT (which saves the
database), and measure precision and recall against ground-truth positions.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vbrl_ros.io.bag_writer import write_scan_bag

CLOSURE_TOPIC = "/vbrl_node/loop_closures"
MARKER_TOPIC = "/vbrl_node/markers"
CORRECT_WITHIN_M = 5.0  # a closure is correct when the two scans were taken this close


@dataclass
class SessionBag:
    path: Path
    positions: dict[float, np.ndarray]  # stamp (rounded to 1 us) -> ground-truth position


@dataclass
class SessionResult:
    closures: list[dict]  # rows of the loop-closure message (see vbrl_ros.ros.messages)
    stats: dict[str, str]  # the node's last diagnostics values
    markers: object | None  # the last visualization_msgs/MarkerArray, if any
    node_output: str
    returncode: int


def stamp_key(stamp: float) -> float:
    return round(float(stamp), 6)


def simulate_session_bags(
    out: Path, scenarios: tuple[tuple[str, int], ...], *, town_seed: int = 5, blocks: int = 1,
    loops: int = 2, spacing_m: float = 2.0, beams: int = 32, columns: int = 900,
    progress: bool = False,
) -> dict[str, SessionBag]:
    """One mcap bag per (scenario, run seed), all on the same town and route."""
    from vbrl_ros.simulator import LidarConfig, RouteConfig, TownConfig, generate_town, make_route
    from vbrl_ros.simulator import simulate_run

    town = generate_town(TownConfig(blocks_x=blocks, blocks_y=blocks), seed=town_seed)
    bags = {}
    for k, (name, seed) in enumerate(scenarios):
        # sessions do not scan from the very same spots
        route = make_route(town, RouteConfig(loops=loops, spacing_m=spacing_m,
                                             sample_offset_m=0.5 * k * spacing_m))
        run = simulate_run(town, route, LidarConfig(beams=beams, columns=columns), name, seed=seed)
        path = out / name
        if not (path / "metadata.yaml").is_file():
            clouds = run.point_clouds(progress, f"simulating {name}")  # lazy (N, 4) arrays
            path = write_scan_bag(path, clouds, run.stamps, run.poses)
        bags[name] = SessionBag(path, {stamp_key(t): p for t, p in zip(run.stamps, run.poses[:, :3, 3])})
    return bags


def run_node_session(
    bag: Path, database: Path, env: dict[str, str], context, *, rate: float = 2.0,
    node_params: tuple[str, ...] = (), timeout: float = 600.0, progress: bool = False,
    scans: int | None = None, replay_args: tuple[str, ...] = (),
    on_node_up: Callable[[int], None] | None = None, on_idle: Callable[[], None] | None = None,
) -> SessionResult:
    """Start vbrl_node, replay ``bag`` into it, wait until it is idle, stop it with SIGINT.

    ``progress``: a bar over the ``scans`` clouds of the bag as the node reports receiving
    them, with its keyframes and closures so far; a replay takes minutes, and what the
    node has taken in is what matters, not what the player has sent. ``replay_args``: more
    ``vbrl replay`` options; ``on_node_up``: called with the node's pid once it is up, before
    the replay starts; ``on_idle``: once it has worked through the replay, before it is stopped.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64MultiArray
    from visualization_msgs.msg import MarkerArray

    from vbrl_ros.ros.messages import parse_closures
    from vbrl_ros.ros.testing import MessageCollector

    probe = rclpy.create_node("vbrl_session_probe", context=context)
    collector = MessageCollector(probe, {CLOSURE_TOPIC: Float64MultiArray, "/diagnostics": DiagnosticArray,
                                         MARKER_TOPIC: MarkerArray})
    params = ("odom_topic:=/odom", f"database_path:={database}", "diagnostics_period:=0.5", *node_params)
    node = subprocess.Popen(
        [sys.executable, "-m", "vbrl_ros.ros.node", "--ros-args", *[a for p in params for a in ("-p", p)]],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    player = None
    try:
        if not collector.wait_for({"/diagnostics": 1}, timeout=60):
            raise RuntimeError("vbrl_node did not come up")
        if on_node_up is not None:
            on_node_up(node.pid)
        player = subprocess.Popen(
            [sys.executable, "-m", "vbrl_ros.tools.replay", str(bag), "--rate", str(rate), "--quiet",
             "--wait-for-subscribers", "1", "--wait-topics", "/points", "/odom",
             # discovery is not symmetric: a best-effort cloud sent as soon as the replay's
             # writer has matched the node's reader can reach a reader not yet matched to it
             "--delay", "0.5", *replay_args],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        with SessionProgress(collector, bag.name, scans, progress) as bar:
            # keep spinning while the replay runs, so the probe's queues stay current
            if not collector.spin_until(lambda: bar.update() or player.poll() is not None, timeout=timeout):
                replay_output, _ = stop_process(player, signal.SIGINT, 30)
                raise RuntimeError(f"the replay did not end within {timeout:g} s: {replay_output[-500:]}")
            replay_output, _ = player.communicate(timeout=30)
            if player.returncode != 0:
                raise RuntimeError(f"replay failed: {replay_output}")
            stats = _wait_until_idle(collector, on_spin=bar.update)
        if on_idle is not None:
            on_idle()
    finally:
        if player is not None and player.poll() is None:
            stop_process(player, signal.SIGINT, 30)
        output, killed = stop_process(node, signal.SIGINT, 120)
        if killed:
            output += "\n[vbrl_node did not exit within 120 s of SIGINT and was killed]"
    closures = [row for msg in collector.messages[CLOSURE_TOPIC] for row in parse_closures(msg)]
    markers = collector.messages[MARKER_TOPIC][-1] if collector.messages[MARKER_TOPIC] else None
    collector.close()
    probe.destroy_node()
    return SessionResult(closures, stats, markers, output, node.returncode)


def stop_process(process: subprocess.Popen, how: int, timeout: float) -> tuple[str, bool]:
    """Send ``how`` and wait ``timeout`` seconds for the exit; kill it if it does not come.

    Returns its output and whether it had to be killed: a process stuck in its shutdown must
    not outlive the session (it would keep its DDS domain busy)."""
    process.send_signal(how)
    try:
        output, _ = process.communicate(timeout=timeout)
        return output or "", False
    except subprocess.TimeoutExpired:
        process.kill()
        output, _ = process.communicate()
        return output or "", True


class SessionProgress:
    """A tqdm bar over the scans the node has received (from its diagnostics), or nothing."""

    def __init__(self, collector, name: str, scans: int | None, enabled: bool) -> None:
        self.collector, self.name, self.scans, self.enabled = collector, name, scans, enabled
        self._seen = (0, 0)  # (diagnostics, closure messages) already shown

    def __enter__(self) -> SessionProgress:
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=self.scans, desc=f"replaying {self.name}", unit="scan",
                            dynamic_ncols=True)
        return self

    def update(self) -> None:
        """Show the latest diagnostics (cheap when nothing new came: called on every spin)."""
        messages = self.collector.messages
        seen = (len(messages["/diagnostics"]), len(messages[CLOSURE_TOPIC]))
        if not self.enabled or seen == self._seen or not seen[0]:
            return
        self._seen = seen
        values = {kv.key: kv.value for kv in messages["/diagnostics"][-1].status[0].values}
        received = int(float(values.get("scans_received", 0)))
        self.bar.update(received - self.bar.n)
        self.bar.set_postfix(keyframes=values.get("keyframes_processed", "?"),
                             closures=len(messages[CLOSURE_TOPIC]))

    def __exit__(self, *exc: object) -> None:
        if self.enabled:
            self.bar.close()


#: The counters that move while the node still works on what it received.
BUSY_COUNTERS = ("keyframes_processed", "loop_closures", "rejected_by_verification", "unverified_keyframes",
                 "verification_errors")


def _wait_until_idle(collector, timeout: float = 120.0, on_spin=lambda: None) -> dict[str, str]:
    """Diagnostics once the node's keyframe and verification counts stop moving and no keyframe
    waits for the sensor to pass it."""
    previous, deadline = None, time.monotonic() + timeout
    while time.monotonic() < deadline:
        collector.spin_until(lambda: on_spin() or False, 1.2)  # drain: > 2 diagnostics periods
        last = collector.messages["/diagnostics"][-1].status[0]
        current = {kv.key: kv.value for kv in last.values}
        if (previous is not None and all(current.get(k) == previous.get(k) for k in BUSY_COUNTERS)
                and current.get("keyframes_waiting", "0") == "0"):
            return current
        previous = current
    raise RuntimeError("vbrl_node never went idle")


def closure_errors(closures: list[dict], positions: dict[float, np.ndarray]) -> np.ndarray:
    """Ground-truth distance (m) between the query and match scan of each closure."""
    return np.array([
        np.linalg.norm(positions[stamp_key(c["query_stamp"])] - positions[stamp_key(c["match_stamp"])])
        for c in closures
    ])


def revisit_stamps(
    positions: dict[float, np.ndarray], database: dict[float, np.ndarray],
    exclude_recent_s: float | None, radius: float = 3.0,
) -> set[float]:
    """Stamps of scans with a database scan within ``radius`` (older than exclude_recent_s, if given)."""
    db_stamps = np.array(list(database))
    db_xyz = np.array(list(database.values()))
    out = set()
    for stamp, xyz in positions.items():
        visible = np.ones(len(db_stamps), dtype=bool)
        if exclude_recent_s is not None:  # same session: the node's recency exclusion
            visible = db_stamps < stamp - exclude_recent_s
        if visible.any() and (np.linalg.norm(db_xyz[visible] - xyz, axis=1) < radius).any():
            out.add(stamp)
    return out


def precision_recall(
    closures: list[dict], positions: dict[float, np.ndarray], revisits: set[float]
) -> tuple[float, float]:
    """Precision of the closures, and the share of revisit scans that got a correct one."""
    if not closures:
        return float("nan"), 0.0
    errors = closure_errors(closures, positions)
    correct = {stamp_key(c["query_stamp"]) for c, e in zip(closures, errors) if e < CORRECT_WITHIN_M}
    recall = len(correct & revisits) / len(revisits) if revisits else float("nan")
    return float(np.mean(errors < CORRECT_WITHIN_M)), recall
