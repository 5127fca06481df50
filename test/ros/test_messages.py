import numpy as np
from scipy.spatial.transform import Rotation

from vbrl_ros.detection.candidate_verification import LoopClosure
from vbrl_ros.ros.messages import CLOSURE_COLUMNS, closures_message, lio_sam_message, parse_closures


def closure(verified: bool) -> LoopClosure:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T[:3, 3] = [1.0, -2.0, 0.5]
    return LoopClosure(
        query_id=42, match_id=7, query_stamp=1700000000.125, match_stamp=1699999000.5,
        query_session="3", match_session="1", distance=2.5, yaw=-0.75,
        T_query_match=T if verified else None, fitness=0.9 if verified else float("nan"),
        covariance=np.diag(np.arange(1.0, 7.0)) if verified else None,
    )


def test_rows_round_trip_through_the_labelled_layout():
    msg = closures_message([closure(True), closure(False)])
    assert msg.layout.dim[0].label == "closure" and msg.layout.dim[0].size == 2
    assert msg.layout.dim[1].size == len(CLOSURE_COLUMNS) == 52
    rows = parse_closures(msg)
    first, second = rows
    assert first["query_stamp"] == 1700000000.125 and first["match_stamp"] == 1699999000.5
    assert (first["query_keyframe_id"], first["match_keyframe_id"]) == (42, 7)
    assert (first["query_session"], first["match_session"]) == (3, 1)
    assert (first["x"], first["y"], first["z"]) == (1.0, -2.0, 0.5)
    quat = [first[k] for k in ("qx", "qy", "qz", "qw")]
    np.testing.assert_allclose(Rotation.from_quat(quat).as_euler("zyx", degrees=True)[0], 30)
    assert first["cov_55"] == 6.0 and first["cov_01"] == 0.0
    assert first["descriptor_yaw"] == second["descriptor_yaw"] == -0.75  # unverified keep it too
    assert np.isnan(second["fitness"]) and np.isnan(second["qw"]) and np.isnan(second["cov_00"])


def test_lio_sam_convention():
    assert list(lio_sam_message(closure(True)).data) == [1700000000.125, 1699999000.5]
