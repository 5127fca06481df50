"""Poses per scan: poses.txt, interpolation, tf chains and pose topics in real bags, real KISS-ICP odometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from vbrl_ros.datasets import open_source
from vbrl_ros.datasets.kitti_style import write_kitti_style
from vbrl_ros.io.bag_writer import write_scan_bag
from vbrl_ros.io.pointcloud2 import split_stamp, to_rosbags_msg
from vbrl_ros.datasets.poses import (
    OdometryFrameWarning,
    OutsidePoseRangeWarning,
    PoseSourceError,
    chain_tf,
    interpolate_poses,
    invert_transforms,
    lidar_mounting,
    parse_pose_spec,
    read_poses_txt,
    write_poses_txt,
)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def transform(yaw: float, translation: tuple[float, float, float]) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    matrix[:3, 3] = translation
    return matrix


# Constant-rate yaw about a fixed axis and linear translation: SLERP and lerp reproduce them exactly.
def map_odom(t: float) -> np.ndarray:
    return transform(0.1 * (t - 100), (0.2 * (t - 100), 0.0, 0.0))


def odom_base(t: float) -> np.ndarray:
    return transform(0.3 * (t - 100), (1.0 * (t - 100), 0.5 * (t - 100), 0.0))


BASE_LIDAR = transform(np.pi / 2, (0.3, 0.0, 1.1))
BASE_IMU = transform(0.0, (-0.2, 0.0, 0.1))


def test_poses_txt_round_trip_and_errors(tmp_path: Path) -> None:
    poses = np.stack([transform(0.3 * i, (i, -i, 0.5)) for i in range(4)])
    write_poses_txt(tmp_path / "poses.txt", poses)
    np.testing.assert_allclose(read_poses_txt(tmp_path / "poses.txt"), poses, atol=1e-9)
    (tmp_path / "bad.txt").write_text("1 2 3\n4 5 6\n")
    with pytest.raises(PoseSourceError, match="3 numbers per line, expected 12"):
        read_poses_txt(tmp_path / "bad.txt")


def test_interpolation_is_slerp_plus_lerp_and_nan_outside() -> None:
    sample_times = np.array([100.3, 100.0, 100.2, 100.1, 100.2])  # unsorted; of a repeated stamp the last wins
    samples = np.stack([odom_base(t) for t in sample_times])
    samples[2] = BASE_LIDAR
    queries = np.array([99.9, 100.0, 100.05, 100.17, 100.3, 100.31])
    with pytest.warns(OutsidePoseRangeWarning, match="2 of 6 scans lie outside"):
        result = interpolate_poses(sample_times, samples, queries)
    assert np.isnan(result[[0, 5]]).all()
    expected = np.stack([odom_base(t) for t in queries[1:5]])
    np.testing.assert_allclose(result[1:5], expected, atol=1e-12)
    single = interpolate_poses([5.0], [BASE_LIDAR], [5.0], warn=False)
    np.testing.assert_allclose(single[0], BASE_LIDAR)


def test_invert_transforms_matches_matrix_inverse() -> None:
    transforms = np.stack([map_odom(t) @ BASE_LIDAR for t in (100.0, 103.0)])
    np.testing.assert_allclose(invert_transforms(transforms), np.linalg.inv(transforms), atol=1e-12)


def tf_edges(times: np.ndarray) -> dict:
    return {
        ("map", "odom"): (times, np.stack([map_odom(t) for t in times]), False),
        ("odom", "base_link"): (times, np.stack([odom_base(t) for t in times]), False),
        ("base_link", "lidar"): (np.array([0.0]), BASE_LIDAR[None], True),
        ("base_link", "imu"): (np.array([0.0]), BASE_IMU[None], True),
    }


def test_chain_tf_walks_up_and_down_the_tree() -> None:
    edges, queries = tf_edges(np.linspace(100.0, 101.0, 11)), np.array([100.05, 100.5, 100.93])
    world_lidar = chain_tf(edges, "map", "lidar", queries)
    expected = np.stack([map_odom(t) @ odom_base(t) @ BASE_LIDAR for t in queries])
    np.testing.assert_allclose(world_lidar, expected, atol=1e-12)
    np.testing.assert_allclose(chain_tf(edges, "lidar", "map", queries), np.linalg.inv(expected), atol=1e-12)
    imu_lidar = chain_tf(edges, "imu", "/lidar", queries)  # sibling frames: up to base_link, down to lidar
    np.testing.assert_allclose(imu_lidar, np.broadcast_to(np.linalg.inv(BASE_IMU) @ BASE_LIDAR, (3, 4, 4)),
                               atol=1e-12)
    with pytest.warns(OutsidePoseRangeWarning, match="map->lidar: 1 of 2"):
        assert np.isnan(chain_tf(edges, "map", "lidar", [99.0, 100.5])[0]).all()
    with pytest.raises(PoseSourceError, match="no frame 'camera' .frames: base_link, imu, lidar, map, odom."):
        chain_tf(edges, "map", "camera", queries)
    edges[("world", "gps")] = (np.array([0.0]), np.eye(4)[None], True)
    with pytest.raises(PoseSourceError, match="'map' and 'gps' are not connected"):
        chain_tf(edges, "map", "gps", queries)


def header(stamp: float) -> object:
    sec, nanosec = split_stamp(stamp)
    return TYPESTORE.types["std_msgs/msg/Header"](
        stamp=TYPESTORE.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="")


def pose_fields(matrix: np.ndarray) -> tuple[list[float], list[float]]:
    return matrix[:3, 3].tolist(), Rotation.from_matrix(matrix[:3, :3]).as_quat().tolist()


def tf_message(stamp: float, parent: str, child: str, matrix: np.ndarray) -> object:
    types = TYPESTORE.types
    (x, y, z), (qx, qy, qz, qw) = pose_fields(matrix)
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=header(stamp), child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](translation=types["geometry_msgs/msg/Vector3"](x, y, z),
                                                       rotation=types["geometry_msgs/msg/Quaternion"](qx, qy, qz, qw)))
    stamped.header.frame_id = parent
    return types["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def odometry_message(stamp: float, matrix: np.ndarray, child: str = "lidar") -> object:
    types = TYPESTORE.types
    (x, y, z), (qx, qy, qz, qw) = pose_fields(matrix)
    pose = types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x, y, z),
                                           orientation=types["geometry_msgs/msg/Quaternion"](qx, qy, qz, qw))
    vector = types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    return types["nav_msgs/msg/Odometry"](
        header=header(stamp), child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vector, angular=vector), covariance=np.zeros(36)))


def write_tf_bag(path: Path, scan_stamps: np.ndarray, odometry_topics: tuple[str, ...] = ("/odom",)) -> Path:
    """Clouds at scan_stamps, /tf map->odom at 10 Hz and odom->base_link at 20 Hz over [100, 101],
    /tf_static base_link->lidar once, and map->lidar Odometry at 10 Hz on each odometry topic."""
    messages = [(t, "/points", "sensor_msgs/msg/PointCloud2",
                 to_rosbags_msg(np.ones((3, 3)), ["x", "y", "z"], typestore=TYPESTORE, stamp=float(t)))
                for t in scan_stamps]
    messages.append((99.0, "/tf_static", "tf2_msgs/msg/TFMessage", tf_message(99.0, "base_link", "lidar", BASE_LIDAR)))
    for t in np.linspace(100.0, 101.0, 11):
        messages.append((t, "/tf", "tf2_msgs/msg/TFMessage", tf_message(t, "map", "odom", map_odom(t))))
        for topic in odometry_topics:
            pose = map_odom(t) @ odom_base(t) @ BASE_LIDAR
            messages.append((t, topic, "nav_msgs/msg/Odometry", odometry_message(t, pose)))
    for t in np.linspace(100.0, 101.0, 21):
        messages.append((t, "/tf", "tf2_msgs/msg/TFMessage", tf_message(t, "odom", "base_link", odom_base(t))))
    return write_messages(path, messages)


def write_messages(path: Path, messages: list[tuple[float, str, str, object]]) -> Path:
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for t, topic, msgtype, msg in sorted(messages, key=lambda m: m[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            sec, nanosec = split_stamp(float(t))
            writer.write(connections[topic], sec * 10**9 + nanosec, TYPESTORE.serialize_cdr(msg, msgtype))
    return path


def write_base_link_bag(path: Path, scan_stamps: np.ndarray, *, with_tf: bool) -> Path:
    """Clouds in frame 'lidar', Odometry of base_link at 10 Hz over [100, 101], and (``with_tf``)
    /tf_static base_link->lidar."""
    messages = [(t, "/points", "sensor_msgs/msg/PointCloud2",
                 to_rosbags_msg(np.ones((3, 3)), ["x", "y", "z"], typestore=TYPESTORE, stamp=float(t),
                                frame_id="lidar")) for t in scan_stamps]
    if with_tf:
        messages.append((99.0, "/tf_static", "tf2_msgs/msg/TFMessage",
                         tf_message(99.0, "base_link", "lidar", BASE_LIDAR)))
    messages += [(t, "/odom", "nav_msgs/msg/Odometry", odometry_message(t, odom_base(t), child="base_link"))
                 for t in np.linspace(100.0, 101.0, 11)]
    return write_messages(path, messages)


def test_odometry_of_base_link_is_carried_over_to_the_lidar_by_the_bag_s_tf(tmp_path: Path) -> None:
    """A robot's odometry moves base_link; taken as the LiDAR's, submaps merged by it would smear
    wherever the LiDAR is turned against base_link (here by 90 degrees, 0.3 m ahead)."""
    scan_stamps = np.array([100.1, 100.5, 100.9])
    source = open_source(write_base_link_bag(tmp_path / "mounted", scan_stamps, with_tf=True))
    expected = np.stack([odom_base(t) @ BASE_LIDAR for t in scan_stamps])
    np.testing.assert_allclose(source.poses, expected, atol=2e-3)  # SLERP between samples, as above


def test_odometry_of_another_frame_without_tf_is_said_and_kept(tmp_path: Path) -> None:
    scan_stamps = np.array([100.1, 100.5, 100.9])
    bag = write_base_link_bag(tmp_path / "unmounted", scan_stamps, with_tf=False)
    with pytest.warns(OdometryFrameWarning, match="odometry moves frame 'base_link', the clouds are in 'lidar', "
                                                  "and the bag's tf does not connect them"):
        source = open_source(bag)
    np.testing.assert_allclose(source.poses, np.stack([odom_base(t) for t in scan_stamps]), atol=2e-3)
    with pytest.raises(PoseSourceError, match="no frame 'base_link' \\(frames: none\\)"):  # a bag without tf
        open_source(bag, poses="tf:base_link:lidar")


@pytest.mark.parametrize("spec", ["tf:map:lidar", "odom:/odom", "auto"])
def test_bag_poses_interpolated_to_scan_stamps(tmp_path: Path, spec: str) -> None:
    scan_stamps = np.array([99.95, 100.05, 100.33, 100.6, 100.95])
    bag = write_tf_bag(tmp_path / "tf_bag", scan_stamps)
    with pytest.warns(OutsidePoseRangeWarning, match="1 of 5 scans"):
        source = open_source(bag, poses=spec)
    assert np.isnan(source.poses[0]).all()
    expected = np.stack([map_odom(t) @ odom_base(t) @ BASE_LIDAR for t in scan_stamps[1:]])
    # Odometry messages hold the composed pose; between samples SLERP of the composition is close, not exact.
    np.testing.assert_allclose(source.poses[1:], expected, atol=1e-12 if spec.startswith("tf") else 2e-3)
    assert len(source) == 5 and len(source[4].points) == 3


def test_pose_topic_selection(tmp_path: Path) -> None:
    bag = write_tf_bag(tmp_path / "two_odom", np.array([100.5]), odometry_topics=("/odom", "/slam/odom"))
    with pytest.raises(PoseSourceError, match="several pose topics.*: /odom, /slam/odom"):
        open_source(bag)
    assert open_source(bag, poses="none").poses is None
    assert open_source(bag, poses="odom:/slam/odom").poses.shape == (1, 4, 4)
    with pytest.raises(ValueError, match="'/tf' is a tf2_msgs/msg/TFMessage topic; pose topics: /odom, /slam/odom"):
        open_source(bag, poses="pose:/tf")


def test_written_bag_poses_come_back_through_every_topic(tmp_path: Path) -> None:
    poses = np.stack([transform(0.2 * i, (i, 2.0 * i, 0.1)) for i in range(4)])
    bag = write_scan_bag(tmp_path / "b.bag", [np.ones((2, 4), np.float32)] * 4, 50.0 + np.arange(4), poses, ros1=True)
    for spec in ("auto", "odom:/odom", "pose:/ground_truth"):
        np.testing.assert_allclose(open_source(bag, poses=spec).poses, poses, atol=1e-9)


def test_pose_spec_errors(tmp_path: Path) -> None:
    for spec in ("tf:map", "odom:", "gps", "tf:a:b:c"):
        with pytest.raises(PoseSourceError, match="unknown pose spec"):
            parse_pose_spec(spec)
    folder = write_kitti_style(tmp_path / "run", [np.ones((2, 4))] * 3, None)
    with pytest.raises(PoseSourceError, match="needs a bag"):
        open_source(folder, poses="tf:map:lidar")
    write_poses_txt(tmp_path / "two.txt", np.stack([np.eye(4)] * 2))
    with pytest.raises(PoseSourceError, match="2 poses for 3 scans"):
        open_source(folder, poses=f"file:{tmp_path / 'two.txt'}")
    write_poses_txt(tmp_path / "three.txt", np.stack([transform(0.0, (i, 0, 0)) for i in range(3)]))
    assert open_source(folder, poses=f"file:{tmp_path / 'three.txt'}").poses[2, 0, 3] == 2.0


# --------------------------------------------------------------------------- KISS-ICP on a synthetic room

BOXES = [((-8, -5, 0), (8, 5, 3)),  # the room: floor, ceiling, four walls
         ((-5, -4, 0), (-3.5, -2.5, 1.5)), ((2, 1, 0), (3, 4, 2.2)), ((5, -4.5, 0), (6.5, -3, 0.8)),
         ((-1, 3, 0), (0.5, 4.2, 2.8)), ((-6, 2, 0), (-5.2, 2.8, 1.2))]


def box_room_scan(rng: np.random.Generator, world_lidar: np.ndarray, per_face: int = 330) -> np.ndarray:
    """Fresh random samples of every box face (so no two scans share points), 1 cm noise, sensor frame."""
    faces = []
    for low, high in BOXES:
        for axis in range(3):
            for side in (low[axis], high[axis]):
                face = rng.uniform(low, high, size=(per_face, 3))
                face[:, axis] = side
                faces.append(face)
    world = np.vstack(faces)
    local = (world - world_lidar[:3, 3]) @ world_lidar[:3, :3]
    return local + rng.normal(0.0, 0.01, local.shape)


def test_kiss_icp_odometry_recovers_known_motion(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rng = np.random.default_rng(0)
    truth = np.stack([transform(np.deg2rad(4.0) * i, (-4 + 0.35 * i, -1 + 0.1 * i, 1.2)) for i in range(6)])
    scans = [np.column_stack([box_room_scan(rng, pose), np.zeros(len(BOXES) * 6 * 330)]) for pose in truth]
    folder = write_kitti_style(tmp_path / "room", scans, None)
    source = open_source(folder, poses="kiss-icp", max_range=20.0, voxel_size=0.25)
    assert "KISS-ICP odometry" in capsys.readouterr().err
    relative_truth = np.linalg.inv(truth[0]) @ truth  # KISS-ICP's world is the first scan's frame
    translation_error = np.linalg.norm(source.poses[:, :3, 3] - relative_truth[:, :3, 3], axis=1)
    rotation_error = Rotation.from_matrix(
        np.swapaxes(source.poses[:, :3, :3], 1, 2) @ relative_truth[:, :3, :3]).magnitude()
    assert translation_error.max() < 0.05, translation_error
    assert np.rad2deg(rotation_error.max()) < 0.5, np.rad2deg(rotation_error)
    assert np.linalg.norm(relative_truth[-1, :3, 3]) > 1.5  # the motion was real, not a trivially small one


def test_the_lidar_mounting_is_read_from_the_bag_s_tf_and_told_to_the_node_s_user(tmp_path: Path) -> None:
    """vbrl replay tells vbrl_node's odometry_lidar_pose (the node has no tf) when a bag's odometry
    moves base_link; nothing when the odometry moves the clouds' own frame."""
    from vbrl_ros.tools.replay import mounting_hint

    stamps = np.array([100.1, 100.5])
    mounted = write_base_link_bag(tmp_path / "mounted", stamps, with_tf=True)
    mounting = lidar_mounting(open_source(mounted), "/odom")
    assert (mounting.moved, mounting.lidar) == ("base_link", "lidar")
    np.testing.assert_allclose(mounting.T_moved_lidar, BASE_LIDAR, atol=1e-12)
    assert mounting_hint(mounted) == ("odometry on /odom moves 'base_link', the clouds are in 'lidar': run vbrl_node "
                                      "with -p 'odometry_lidar_pose:=[0.300000, 0.000000, 1.100000, 0.000000, "
                                      "0.000000, 1.570796]' (the bag's tf)")
    unmounted = write_base_link_bag(tmp_path / "unmounted", stamps, with_tf=False)
    assert lidar_mounting(open_source(unmounted, poses="none"), "/odom").T_moved_lidar is None
    assert mounting_hint(unmounted).endswith("and the bag's tf does not connect them: give vbrl_node "
                                             "odometry_lidar_pose")
    own = write_scan_bag(tmp_path / "own", [np.ones((2, 4), np.float32)] * 2, stamps,
                         np.stack([transform(0.1, (1.0, 0.0, 0.0))] * 2))
    assert lidar_mounting(open_source(own), "/odom") is None and mounting_hint(own) is None
