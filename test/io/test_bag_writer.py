"""write_scan_bag writes real ROS 1 / ROS 2 bags; read back here with rosbags' own AnyReader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from vbrl_ros.io.bag_writer import write_scan_bag
from vbrl_ros.io.pointcloud2 import read_points

FORMATS = {"mcap": ({}, "bag"), "sqlite3": ({"storage": "sqlite3"}, "bag"), "ros1": ({"ros1": True}, "run.bag")}


def make_scans(count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.normal(0.0, 10.0, size=(200 + 10 * i, 4)).astype(np.float32) for i in range(count)]


def make_poses(count: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("zyx", np.column_stack([np.linspace(0, 2, count), np.full(count, 0.1),
                                                                   np.full(count, -0.05)])).as_matrix()
    poses[:, :3, 3] = np.column_stack([np.arange(count) * 1.5, np.sin(np.arange(count)), np.zeros(count)])
    return poses


def read_back(path: Path) -> dict[str, list]:
    messages: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for connection, log_ns, rawdata in reader.messages():
            msg = reader.deserialize(rawdata, connection.msgtype)
            messages.setdefault(connection.topic, []).append((connection.msgtype, log_ns, msg))
    return messages


@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_holds_clouds_odometry_and_ground_truth(tmp_path: Path, fmt: str) -> None:
    options, name = FORMATS[fmt]
    scans, poses = make_scans(5), make_poses(5)
    stamps = 1_700_000_000.0 + np.arange(5) * 0.1 + 0.013
    produced = []

    def generator():  # the writer must accept a one-shot generator
        for scan in scans:
            produced.append(len(scan))
            yield scan

    path = write_scan_bag(tmp_path / name, generator(), stamps, poses, frame_id="os_sensor", odom_frame="map",
                          **options)
    assert produced == [len(s) for s in scans]
    messages = read_back(path)
    assert sorted(messages) == ["/ground_truth", "/odom", "/points"]
    for index, (msgtype, log_ns, cloud) in enumerate(messages["/points"]):
        assert msgtype == "sensor_msgs/msg/PointCloud2"
        assert cloud.header.frame_id == "os_sensor"
        stamp_ns = cloud.header.stamp.sec * 10**9 + cloud.header.stamp.nanosec
        assert stamp_ns == log_ns and abs(stamp_ns / 1e9 - stamps[index]) < 1e-6
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity"]
        assert all(f.datatype == 7 for f in cloud.fields)
        np.testing.assert_array_equal(read_points(cloud, ("x", "y", "z", "intensity")), scans[index])
    for index, (msgtype, _, odom) in enumerate(messages["/odom"]):
        assert msgtype == "nav_msgs/msg/Odometry"
        assert (odom.header.frame_id, odom.child_frame_id) == ("map", "os_sensor")
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], poses[index, :3, 3], atol=1e-12)
        np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), poses[index, :3, :3],
                                   atol=1e-12)
    truth = [msg for _, _, msg in messages["/ground_truth"]]
    assert [m.pose.position.x for m in truth] == pytest.approx(poses[:, 0, 3])
    if fmt == "ros1":
        assert [cloud.header.seq for _, _, cloud in messages["/points"]] == list(range(5))


def test_without_poses_only_clouds_are_written(tmp_path: Path) -> None:
    path = write_scan_bag(tmp_path / "bag", make_scans(3), [1.0, 2.0, 3.0], cloud_topic="/velodyne_points")
    assert list(read_back(path)) == ["/velodyne_points"]
    assert sorted(p.name for p in path.iterdir()) == ["bag.mcap", "metadata.yaml"]


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize(
    ("scans", "stamps", "message"),
    [
        (make_scans(3), [0.0, 1.0], "more scans than stamps"),
        (make_scans(2), [0.0, 1.0, 2.0], "got 2 scans for 3 stamps"),
        ([np.zeros((5, 4)), np.zeros((5, 3))], [0.0, 1.0], r"scan 1 has shape \(5, 3\)"),
    ],
)
def test_bad_input_leaves_no_partial_bag(tmp_path: Path, fmt: str, scans, stamps, message: str) -> None:
    options, name = FORMATS[fmt]
    with pytest.raises(ValueError, match=message):
        write_scan_bag(tmp_path / name, iter(scans), stamps, **options)
    assert list(tmp_path.iterdir()) == []


def test_refuses_bad_arguments_before_writing(tmp_path: Path) -> None:
    (tmp_path / "taken").mkdir()
    with pytest.raises(FileExistsError):
        write_scan_bag(tmp_path / "taken", make_scans(1), [0.0])
    with pytest.raises(ValueError, match=r"poses must have shape \(2, 4, 4\)"):
        write_scan_bag(tmp_path / "a", make_scans(2), [0.0, 1.0], make_poses(3))
    with pytest.raises(ValueError, match="must end in .bag"):
        write_scan_bag(tmp_path / "b.db", make_scans(1), [0.0], ros1=True)
    with pytest.raises(ValueError, match="storage must be one of"):
        write_scan_bag(tmp_path / "c", make_scans(1), [0.0], storage="zip")
    with pytest.raises(ValueError, match="non-finite"):
        write_scan_bag(tmp_path / "d", make_scans(1), [np.nan])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_progress_bar_only_when_asked(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_scan_bag(tmp_path / "quiet", make_scans(2), [0.0, 1.0])
    assert "scan" not in capsys.readouterr().err
    write_scan_bag(tmp_path / "loud", make_scans(2), [0.0, 1.0], progress=True)
    assert "writing loud" in capsys.readouterr().err
