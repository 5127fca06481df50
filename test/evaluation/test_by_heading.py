"""Recall@1 split by the heading between a revisit and its nearest earlier pass."""

import math

import numpy as np
import pytest

from vbrl_ros.evaluation.by_heading import (
    HEADING_CLASSES,
    format_heading_recall,
    heading_classes,
    recall_by_heading,
    recalls_by_heading,
)


def pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = (x, y)
    return out


def test_each_revisit_is_classed_by_its_turn_against_the_nearest_earlier_pass():
    database = np.stack([pose(0, 0, 0), pose(50, 0, 0), pose(100, 0, 10)])
    queries = np.stack([pose(1, 0, 30), pose(51, 0, 90), pose(101, 0, -170), pose(300, 0, 0), pose(0, 1, 180)])
    assert heading_classes(queries, database, 5.0).tolist() == [0, 1, 2, -1, 2]


def test_the_nearest_pass_is_the_nearest_visible_one():
    # P1: the query sees only the database's first keyframe; the nearer, reversed one comes later
    database = np.stack([pose(3, 0, 0), pose(0.5, 0, 180)])
    queries = np.stack([pose(0, 0, 0)])
    assert heading_classes(queries, database, 5.0, np.array([1])).tolist() == [0]
    assert heading_classes(queries, database, 5.0).tolist() == [2]


def test_recall_counts_right_top1_per_class():
    database = np.stack([pose(0, 0, 0), pose(50, 0, 0), pose(100, 0, 0)])
    queries = np.stack([pose(0, 1, 0), pose(50, 1, 180), pose(100, 1, 180), pose(200, 0, 0)])
    top = np.array([[0, 2], [2, 1], [2, 0], [0, 1]])  # right, wrong (right second), right, no revisit
    recall = recall_by_heading(queries, database, top, 5.0)
    assert recall.revisits == {"same way": 1, "turned": 0, "reversed": 2}
    assert recall.hits == {"same way": 1, "turned": 0, "reversed": 1}
    assert recall.recall("reversed") == 0.5 and math.isnan(recall.recall("turned"))
    assert recall.summary()["reversed"] == {"revisits": 2, "hits": 1, "recall_at_1": 0.5}


def test_p2_takes_the_queries_into_the_databases_frame_and_p1_hides_the_recent_keyframes():
    database = np.stack([pose(0, 0, 0)])
    queries = np.stack([pose(10, 0, 180)])  # in session B's frame: 10 m off, turned round
    to_a = pose(-10, 0, 0)
    top = np.array([[0]])
    assert recalls_by_heading({"m": top}, queries, database, 5.0)["m"].revisits["reversed"] == 0
    aligned = recalls_by_heading({"m": top}, queries, database, 5.0, alignment=to_a)["m"]
    assert aligned.revisits["reversed"] == 1 and aligned.hits["reversed"] == 1
    # P1 over one session: keyframe 1 sees nothing of keyframe 0 within exclude 2
    session = np.stack([pose(0, 0, 0), pose(0.5, 0, 180), pose(0.2, 0, 180)])
    p1 = recalls_by_heading({"m": np.array([[-1], [-1], [0]])}, session, session, 5.0, exclude=2)["m"]
    assert p1.revisits == {"same way": 0, "turned": 0, "reversed": 1} and p1.hits["reversed"] == 1


def test_without_poses_there_is_no_split():
    assert recalls_by_heading({"m": np.zeros((1, 1), int)}, None, None, 5.0) is None


def test_the_table_names_every_class_and_its_counts():
    recall = recall_by_heading(np.stack([pose(0, 1, 180)]), np.stack([pose(0, 0, 0)]), np.array([[0]]), 5.0)
    text = format_heading_recall({"VBRL": recall}, 5.0)
    assert "radius 5 m" in text
    for name, _, _ in HEADING_CLASSES:
        assert name in text
    assert "1/1" in text and "0/0" in text


@pytest.mark.parametrize("turn, expected", [(44.9, 0), (45.0, 1), (134.9, 1), (135.0, 2), (-179.0, 2)])
def test_class_edges(turn, expected):
    assert heading_classes(np.stack([pose(0, 0, turn)]), np.stack([pose(0, 0, 0)]), 5.0).tolist() == [expected]
