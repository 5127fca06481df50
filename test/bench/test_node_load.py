"""``vbrl bench --node`` end to end on a short drive (a functional check, not a timing), and its /proc sampler."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from vbrl_ros.bench.process_usage import ProcessSampler, tree


def test_the_sampler_sees_a_child_s_cpu_and_memory():
    # a child that allocates ~80 MB and spins for a while, under a parent that only waits
    code = ("import subprocess, sys; subprocess.run([sys.executable, '-c', "
            "'import time; b = bytearray(80 << 20); t = time.process_time(); "
            "exec(\"while time.process_time() - t < 0.6: pass\")'])")
    parent = subprocess.Popen([sys.executable, "-c", code])
    sampler = ProcessSampler(parent.pid, period=0.05).start()
    parent.wait(timeout=60)
    usage = sampler.stop()
    assert usage.cpu_s >= 0.5  # the grandchild's spinning, not the parent's waiting
    assert usage.peak_rss_mb >= 80
    assert tree(-1) == [-1]  # a process that does not exist has no children


def test_bench_node_replays_a_tiny_drive_and_prints_its_table(tmp_path):
    pytest.importorskip("rclpy")
    out = tmp_path / "bench.json"
    result = subprocess.run(
        [sys.executable, "-m", "vbrl_ros.tools.cli", "bench", "--node", "--rates", "1", "--scans", "30",
         "--out-dir", str(tmp_path), "--json", str(out), "--quiet"],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "clouds sent/received" in result.stdout and "latency p50/p90/p99 ms" in result.stdout
    row = json.loads(out.read_text())["rates"][0]
    assert row["rate"] == 1 and row["clouds_sent"] == 30
    # 64-beam clouds (1.5 MB) published best effort: Fast DDS's default transports lost nearly all
    assert row["clouds_received"] == 30 and row["clouds_lost"] == 0
    # every cloud received is accounted for
    assert (row["keyframes_processed"] + row["keyframes_dropped"] + row["clouds_between_keyframes"]
            == row["clouds_received"])
    assert row["keyframes_processed"] > 0 and row["node_cpu_percent"] > 0 and row["peak_rss_mb"] > 100
    assert "1x    30/30" in result.stdout


def test_a_forward_looking_drive_is_rendered_as_one_and_kept_apart(tmp_path):
    from vbrl_ros.bench.node_load import Drive, drive_bag, seen_degrees
    from vbrl_ros.datasets.rosbag import RosbagSource

    forward = Drive(scans=2, blocked_azimuth_deg=(35.0, -35.0), vertical_fov_deg=(-38.0, 38.0))
    # the rendered bag is reused by name: another sensor must not find this one's
    assert forward.name() != Drive(scans=2).name()
    assert seen_degrees(35.0, -35.0) == 70.0 and seen_degrees(150.0, -150.0) == 300.0
    assert forward.sensor() == "64-beam LiDAR, 70° seen" and Drive().sensor() == "64-beam LiDAR"
    bag, count = drive_bag(forward, tmp_path)
    assert count == 2
    with RosbagSource(bag) as source:
        xyz = source[1].points[:, :3].astype(np.float64)
    assert len(xyz) > 1000
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    assert np.abs(azimuth).max() <= 35.5 and np.abs(azimuth).max() >= 33.0  # the whole 70°, no more
    assert elevation.max() <= 38.5 and elevation.max() > 20.0  # the wider field, not 64 beams' +15°
