import numpy as np
import pytest

from vbrl_ros.training.targets import place_labels


def test_keyframes_in_one_cell_share_a_place():
    positions = np.array([[0.5, 0.5, 0], [5.9, 1.0, 3], [6.1, 0.0, 0], [-0.1, 0.0, 0], [0.2, 5.0, 1]])
    labels, names = place_labels(positions, 6.0)
    assert labels[0] == labels[1] == labels[4]  # same 6 m cell, z ignored
    assert len({labels[0], labels[2], labels[3]}) == 3
    assert len(names) == 3 and names[labels[0]] == "place_0_0"


def test_missing_poses_and_bad_cell_size_are_errors():
    with pytest.raises(ValueError, match="pose"):
        place_labels(np.array([[0.0, np.nan, 0.0]]), 6.0)
    with pytest.raises(ValueError, match="place-size"):
        place_labels(np.zeros((2, 3)), 0.0)
