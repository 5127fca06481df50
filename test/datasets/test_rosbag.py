"""RosbagSource over real ROS 2 (mcap, sqlite3) and ROS 1 bags written with rosbags."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vbrl_ros.datasets import detect_source_kind, open_source
from vbrl_ros.datasets.base import ScanSourceError
from vbrl_ros.datasets.rosbag import BagTopicError, RosbagSource, header_stamp_ns
from vbrl_ros.io.bag_writer import write_scan_bag
from vbrl_ros.io.pointcloud2 import PointCloud2Error, to_rosbags_msg

FORMATS = {"mcap": ({}, "bag"), "sqlite3": ({"storage": "sqlite3"}, "bag"), "ros1": ({"ros1": True}, "run.bag")}
CLOUD = "sensor_msgs/msg/PointCloud2"


def make_scans(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    scans = [rng.uniform(-20, 20, size=(300 + i, 4)).astype(np.float32) for i in range(count)]
    if count > 1:
        scans[1][::10, 0] = np.nan  # is_dense = false clouds: those rows must be dropped
    return scans


@pytest.fixture(params=list(FORMATS))
def written_bag(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, list[np.ndarray], np.ndarray]:
    options, name = FORMATS[request.param]
    scans = make_scans(6)
    stamps = 1_650_000_000.0 + np.array([0.0, 0.1, 0.2, 0.2, 0.45, 0.5])  # two scans share a stamp
    return write_scan_bag(tmp_path / name, scans, stamps, **options), scans, stamps


def test_reads_every_scan_in_order_and_by_index(written_bag) -> None:
    path, scans, stamps = written_bag
    assert detect_source_kind(path) == "rosbag"
    with RosbagSource(path) as source:
        assert source.topic == "/points" and len(source) == 6
        streamed = list(source)
        np.testing.assert_allclose(source.stamps, stamps, atol=1e-6)
        for index in (4, 0, 3, 2, -1):  # random access, including the duplicate log time
            scan = source[index]
            expected = scans[index]
            expected = expected[np.isfinite(expected[:, :3]).all(axis=1)].astype(np.float64)
            assert scan.index == index % 6 and abs(scan.stamp - stamps[index]) < 1e-6
            np.testing.assert_array_equal(scan.points, expected[:, :3])
            np.testing.assert_array_equal(scan.intensity, expected[:, 3])
            np.testing.assert_array_equal(streamed[index % 6].points, scan.points)
        assert len(streamed[1].points) == 300 + 1 - 31
        with pytest.raises(IndexError, match="out of range"):
            source[6]


def test_stamps_without_iterating_first(written_bag) -> None:
    path, _, stamps = written_bag
    with RosbagSource(path) as source:
        np.testing.assert_allclose(source.stamps, stamps, atol=1e-6)
        assert source[5].stamp == pytest.approx(stamps[5], abs=1e-6)


def test_ros2_bag_file_and_split_ros1_directory(tmp_path: Path) -> None:
    bag = write_scan_bag(tmp_path / "two", make_scans(2), [1.0, 2.0], storage="sqlite3")
    assert len(RosbagSource(bag / "two.db3")) == 2
    split = tmp_path / "split"
    split.mkdir()
    write_scan_bag(split / "part_1.bag", make_scans(2), [5.0, 6.0], ros1=True)
    write_scan_bag(split / "part_0.bag", make_scans(3), [1.0, 2.0, 3.0], ros1=True)
    with RosbagSource(split) as source:
        assert len(source) == 5
        np.testing.assert_allclose(source.stamps, [1, 2, 3, 5, 6])
        assert [s.stamp for s in source] == pytest.approx([1, 2, 3, 5, 6])


def write_custom_bag(path: Path, messages: list[tuple[str, str, int, object]]) -> Path:
    """ROS 2 mcap bag from (topic, msgtype, log time ns, message) tuples."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for topic, msgtype, log_ns, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(connections[topic], log_ns, typestore.serialize_cdr(msg, msgtype))
    return path


def cloud(stamp: float, count: int = 5, **options) -> object:
    points = np.arange(count * 3, dtype=np.float32).reshape(count, 3)
    return to_rosbags_msg(points, ["x", "y", "z"], typestore=get_typestore(Stores.ROS2_JAZZY), stamp=stamp,
                          **options)


def test_topic_selection_errors_list_the_cloud_topics(tmp_path: Path) -> None:
    string_type = get_typestore(Stores.ROS2_JAZZY).types["std_msgs/msg/String"]
    bag = write_custom_bag(tmp_path / "multi", [
        ("/os/points", CLOUD, 1, cloud(0.0)), ("/vel/points", CLOUD, 2, cloud(0.0)),
        ("/chatter", "std_msgs/msg/String", 3, string_type(data="hi")),
    ])
    with pytest.raises(BagTopicError, match="several .*PointCloud2 topics; choose one with topic=: /os/points, "
                                            "/vel/points"):
        RosbagSource(bag)
    with pytest.raises(BagTopicError, match="no topic '/lidar'; .*PointCloud2 topics: /os/points, /vel/points"):
        RosbagSource(bag, topic="/lidar")
    with pytest.raises(BagTopicError, match="'/chatter' is a std_msgs/msg/String topic"):
        RosbagSource(bag, topic="/chatter")
    assert len(RosbagSource(bag, topic="/vel/points")) == 1
    empty = write_custom_bag(tmp_path / "none", [("/chatter", "std_msgs/msg/String", 3, string_type(data="x"))])
    with pytest.raises(BagTopicError, match=r"no .*PointCloud2 topic in the bag \(topics: /chatter\)"):
        RosbagSource(empty)


def test_header_stamp_wins_over_log_time_unless_unset(tmp_path: Path) -> None:
    bag = write_custom_bag(tmp_path / "stamps", [
        ("/points", CLOUD, 5_000_000_000, cloud(1.25)),
        ("/points", CLOUD, 6_000_000_000, cloud(0.0)),  # unset header stamp -> log time
        ("/points", CLOUD, 7_000_000_000, cloud(2.5, big_endian=True)),
    ])
    source = RosbagSource(bag)
    np.testing.assert_allclose(source.stamps, [1.25, 6.0, 2.5])
    assert [scan.stamp for scan in source] == pytest.approx([1.25, 6.0, 2.5])
    np.testing.assert_array_equal(source[2].points, np.arange(15).reshape(5, 3))


def test_header_stamp_parsing_of_raw_messages() -> None:
    ros2, ros1 = get_typestore(Stores.ROS2_JAZZY), get_typestore(Stores.ROS1_NOETIC)
    msg2 = cloud((1_700_000_000, 123))
    assert header_stamp_ns(ros2.serialize_cdr(msg2, CLOUD), ros1=False) == 1_700_000_000 * 10**9 + 123
    msg1 = to_rosbags_msg(np.zeros((1, 3)), ["x", "y", "z"], typestore=ros1, stamp=(42, 7))
    assert header_stamp_ns(ros1.serialize_ros1(msg1, CLOUD), ros1=True) == 42 * 10**9 + 7
    assert header_stamp_ns(b"\x00\x01", ros1=False) == 0


def test_malformed_cloud_in_bag_is_a_pointcloud2_error_with_context(tmp_path: Path) -> None:
    broken = cloud(1.0)
    broken.row_step = 1  # smaller than width * point_step
    bag = write_custom_bag(tmp_path / "broken", [("/points", CLOUD, 1, cloud(0.5)), ("/points", CLOUD, 2, broken)])
    source = RosbagSource(bag)
    assert len(source[0].points) == 5
    with pytest.raises(PointCloud2Error, match=r"/points message 1: PointCloud2 row_step 1 < width 5"):
        source[1]


def test_bad_paths_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ScanSourceError, match="no such"):
        RosbagSource(tmp_path / "missing.mcap")
    lonely = tmp_path / "lonely.mcap"
    shutil.copy(write_scan_bag(tmp_path / "b", make_scans(1), [0.0]) / "b.mcap", lonely)
    with pytest.raises(ScanSourceError, match="needs the metadata.yaml"):
        RosbagSource(lonely)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanSourceError, match="neither a ROS 2 bag"):
        RosbagSource(tmp_path / "empty")
    with pytest.raises(ScanSourceError, match="topic= applies to bags only"):
        open_source(write_scan_bag(tmp_path / "c", make_scans(1), [0.0]), kind="kitti_style", topic="/points")


def test_random_access_while_iterating(written_bag) -> None:
    path, scans, _ = written_bag
    source = RosbagSource(path)
    source.stamps  # random access needs the index
    finite = [np.isfinite(scan[:, :3]).all(axis=1).sum() for scan in scans]
    for index, scan in enumerate(source):  # the iteration must survive reads elsewhere in the bag
        other = source[5 - index]
        assert len(scan.points) == finite[index] and len(other.points) == finite[5 - index]
        expected = scans[5 - index][np.isfinite(scans[5 - index][:, :3]).all(axis=1), :3]
        np.testing.assert_array_equal(other.points, expected)
    assert index == 5
