"""vbrl_node over real DDS with a model that describes a keyframe with the metres after it too:
a keyframe waits until the sensor has passed it, goes after a silence as long as the trail
reaches in time, and one still waiting at shutdown is stored and saved."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from sensor_msgs.msg import PointCloud2  # noqa: E402

from vbrl_ros.detection.database import KeyframeDatabase  # noqa: E402
from vbrl_ros.model.builtin import load_default_model  # noqa: E402
from vbrl_ros.model.model_file import load_model  # noqa: E402
from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.settings import NodeSettings  # noqa: E402

from .test_node_poses import odometry, odometry_session, values  # noqa: E402

SPACING_M = 1.5  # odometry between keyframes: three lie within the model's 3 m


def cloud(stamp: float) -> PointCloud2:
    """A sparse keyframe all round (3000 points: a hand-held Livox's): three do not fill one's cloud."""
    rng = np.random.default_rng(int(10 * stamp))
    points = np.concatenate([rng.uniform(-30, 30, (3000, 2)), rng.uniform(-2, 4, (3000, 1))], axis=1)
    return to_ros_msg(points.astype(np.float32), ["x", "y", "z"], stamp=stamp, frame_id="lidar")


def model_with_trail_ahead(path):
    builtin = load_default_model()
    features = replace(builtin.config.features, trail_m=3.0, trail_ahead_m=3.0)
    return replace(builtin, config=replace(builtin.config, features=features)).save(path)


def stored_stamps(database, model_path) -> list[float]:
    model = load_model(model_path)
    loaded = KeyframeDatabase.load(database, model.scorer(prune=NodeSettings().weight_prune), model.identity())
    return [float(s) for s in loaded.stamps]


def test_keyframes_wait_for_the_metres_after_them_go_after_a_silence_and_are_saved_at_shutdown(tmp_path):
    database, model = tmp_path / "keyframes.npz", model_with_trail_ahead(tmp_path / "model.npz")
    stamps = [10.0, 10.5, 11.0, 20.0]  # within 2 s: none too late to join the first
    # a silence of half exclude_recent_s (2 s) lets the waiting keyframes go
    with odometry_session(f"database_path:={database}", "save_every:=0", f"model_path:={model}",
                          "exclude_recent_s:=4.0") as session:
        collector = session.collector

        def keyframe(k: int) -> None:
            session.odom.publish(odometry(stamps[k] - 0.1, SPACING_M * k))
            session.odom.publish(odometry(stamps[k] + 0.1, SPACING_M * k))
            # the node decides by the odometry it has when the cloud comes
            assert collector.spin_until(lambda: values(collector)["odometry_received"] >= 2 * (k + 1), 30)
            session.clouds.publish(cloud(stamps[k]))
            assert collector.spin_until(lambda: values(collector)["keyframes_waiting"]
                                        + values(collector)["keyframes_processed"] >= k + 1, 30), \
                values(collector)

        for k in range(3):  # 3 m along: none is passed yet
            keyframe(k)
        seen = values(collector)
        assert (seen["keyframes_waiting"], seen["keyframes_processed"]) == (3, 0), seen
        assert collector.spin_until(lambda: values(collector)["keyframes_processed"] == 3
                                    and values(collector)["keyframes_waiting"] == 0, 30), values(collector)
        keyframe(3)  # waits again: stored when the node stops
        seen = values(collector)
        assert (seen["keyframes_waiting"], seen["keyframes_processed"]) == (1, 3), seen
    assert session.returncode == 0, session.output
    assert stored_stamps(database, model) == stamps
