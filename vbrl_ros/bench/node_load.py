"""``vbrl bench --node``: a simulated drive replayed into a running ``vbrl_node`` over DDS at several rates.

The drive is the speed target's (docs/design.md §5): a 64-beam LiDAR at 10 Hz
on a car at 10 m/s through a simulated town, twice round the same loop, so the
second lap revisits the first; every cloud, 1 m after the last, is a keyframe
(10 a second at 1x), and the node verifies its candidates. The bag is
rendered once and kept in ``out_dir``. For each rate a fresh node (default
parameters, its own ROS domain) receives the replay, best effort like a
driver's, and its diagnostics, CPU (node and verification process together)
and memory are read once it is idle. A benchmark, not a test: figures depend on
the machine and on what else runs on it.
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from vbrl_ros.bench.process_usage import ProcessSampler

#: Just under the drive's 1 m between clouds, so that every cloud is a keyframe (10 a second at
#: 1x): at exactly 1 m, rounding in the travel sum would skip every other one.
KEYFRAME_DISTANCE_M = 0.9


@dataclass(frozen=True)
class Drive:
    """The simulated drive; the defaults are the speed target's."""

    beams: int = 64
    columns: int = 1800
    rate_hz: float = 10.0
    speed_mps: float = 10.0
    loops: int = 2
    blocks: int = 1
    town_seed: int = 5
    scans: int | None = None  # only the first so many (None: the whole drive)
    vertical_fov_deg: tuple[float, float] | None = None  # None: the simulator's for ``beams``
    blocked_azimuth_deg: tuple[float, float] | None = None  # (35, -35): a forward-looking 70°

    def name(self) -> str:
        limit = f"_{self.scans}scans" if self.scans else ""
        fov = "" if self.vertical_fov_deg is None else "_fov{:g}to{:g}".format(*self.vertical_fov_deg)
        blocked = "" if self.blocked_azimuth_deg is None else "_blocked{:g}to{:g}".format(*self.blocked_azimuth_deg)
        return (f"drive_{self.beams}x{self.columns}{fov}{blocked}_{self.rate_hz:g}hz_{self.speed_mps:g}mps_"
                f"{self.loops}loops_{self.blocks}blocks_town{self.town_seed}{limit}")

    def sensor(self) -> str:
        """The sensor in words, for the table's heading."""
        seen = "" if self.blocked_azimuth_deg is None else f", {seen_degrees(*self.blocked_azimuth_deg):g}° seen"
        return f"{self.beams}-beam LiDAR{seen}"


def seen_degrees(blocked_from: float, blocked_to: float) -> float:
    """The azimuth a sensor sees round the circle when the wedge swept counter-clockwise from
    ``blocked_from`` to ``blocked_to`` (degrees) is blocked."""
    return 360.0 - (blocked_to - blocked_from) % 360.0


def drive_bag(drive: Drive, out_dir: Path, progress: bool = False) -> tuple[Path, int]:
    """(bag, number of clouds) of ``drive``, rendered into ``out_dir`` unless it is there already."""
    from vbrl_ros.io.bag_writer import write_scan_bag
    from vbrl_ros.simulator import (
        LidarConfig,
        RouteConfig,
        TownConfig,
        generate_town,
        make_route,
        simulate_run,
    )

    town = generate_town(TownConfig(blocks_x=drive.blocks, blocks_y=drive.blocks), seed=drive.town_seed)
    route = make_route(town, RouteConfig(loops=drive.loops, spacing_m=None, rate_hz=drive.rate_hz,
                                         speed_mps=drive.speed_mps))
    lidar = LidarConfig(beams=drive.beams, columns=drive.columns, vertical_fov_deg=drive.vertical_fov_deg,
                        blocked_azimuth_deg=drive.blocked_azimuth_deg)
    run = simulate_run(town, route, lidar, "summer_clear", seed=1)
    count = min(len(run), drive.scans or len(run))
    path = out_dir / drive.name()
    if not (path / "metadata.yaml").is_file():
        clouds = run.point_clouds(progress, f"rendering {drive.name()}")
        path = write_scan_bag(path, (clouds[i] for i in range(count)), run.stamps[:count], run.poses[:count])
    return path, count


def measure(rates: tuple[float, ...], drive: Drive, out_dir: Path, *, node_params: tuple[str, ...] = (),
            progress: bool = False) -> dict:
    """Per rate: what the node received, processed and published, its latency, CPU and memory."""
    from vbrl_ros.ros.online_session import run_node_session
    from vbrl_ros.ros.testing import isolated_ros_env, ros_context

    out_dir.mkdir(parents=True, exist_ok=True)
    bag, sent = drive_bag(drive, out_dir, progress)
    rows = []
    for rate in rates:
        samplers: list[ProcessSampler] = []
        usage = []
        with tempfile.TemporaryDirectory() as folder, ros_context() as context:
            result = run_node_session(
                bag, Path(folder) / "keyframes.npz", isolated_ros_env(context.get_domain_id()), context,
                rate=rate, node_params=(f"keyframe_distance:={KEYFRAME_DISTANCE_M}", *node_params), progress=progress,
                scans=sent, replay_args=("--qos", "sensor"),
                on_node_up=lambda pid, samplers=samplers: samplers.append(ProcessSampler(pid).start()),
                on_idle=lambda samplers=samplers, usage=usage: usage.append(samplers[0].stop()))
        if result.returncode != 0:
            raise RuntimeError(f"vbrl_node failed at {rate:g}x:\n{result.node_output[-3000:]}")
        s = {key: float(value) for key, value in result.stats.items()}
        rows.append({
            "rate": rate, "clouds_sent": sent, "clouds_received": int(s["scans_received"]),
            "clouds_lost": int(s["scans_lost"]), "keyframes_processed": int(s["keyframes_processed"]),
            "keyframes_dropped": int(s["dropped_scans"]), "keyframes_unverified": int(s["unverified_keyframes"]),
            # a cloud that arrives before its odometry message is measured from the previous pose
            "clouds_between_keyframes": int(s["scans_between_keyframes"]),
            "closures": int(s["loop_closures"]), "rejected_by_verification": int(s["rejected_by_verification"]),
            "latency_ms": [s["latency_p50_ms"], s["latency_p90_ms"], s["latency_p99_ms"]],
            "retrieval_latency_ms": [s["retrieval_latency_p50_ms"], s["retrieval_latency_p90_ms"],
                                     s["retrieval_latency_p99_ms"]],
            "node_cpu_percent": usage[0].cpu_percent, "peak_rss_mb": usage[0].peak_rss_mb,
            "rss_mb_first_last": [usage[0].first_rss_mb, usage[0].last_rss_mb],
        })
    return {"drive": asdict(drive), "sensor": drive.sensor(), "bag": str(bag), "rates": rows}


def format_table(results: dict) -> str:
    d = results["drive"]
    head = (f"vbrl_node on a simulated drive ({results['sensor']} at {d['rate_hz']:g} Hz, "
            f"{d['speed_mps']:g} m/s, keyframes every 1 m), replayed over DDS; latency from a cloud's "
            f"arrival until its closures are decided (stored: until it is described, searched and stored)")
    header = ("rate", "clouds sent/received", "lost", "keyframes processed/dropped", "unverified",
              "closures", "latency p50/p90/p99 ms", "stored p50/p90/p99 ms", "node CPU", "peak RSS",
              "RSS first→last")
    lines = []
    for r in results["rates"]:
        lines.append((f"{r['rate']:g}x", f"{r['clouds_sent']}/{r['clouds_received']}", str(r["clouds_lost"]),
                      f"{r['keyframes_processed']}/{r['keyframes_dropped']}", str(r["keyframes_unverified"]),
                      str(r["closures"]), "/".join(f"{v:.0f}" for v in r["latency_ms"]),
                      "/".join(f"{v:.0f}" for v in r["retrieval_latency_ms"]), f"{r['node_cpu_percent']:.0f} %",
                      f"{r['peak_rss_mb']:.0f} MB", "→".join(f"{v:.0f}" for v in r["rss_mb_first_last"]) + " MB"))
    widths = [max(len(row[i]) for row in (header, *lines)) for i in range(len(header))]
    return "\n".join([head, *("  " + "  ".join(c.ljust(w) for c, w in zip(row, widths))
                              for row in (header, *lines))])
