"""Blind wedges: found only where a long run of directions saw nothing, mirrored, and with the
mirror hidden a reversed revisit of a partly blind sensor describes like the first pass."""

import math

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.blind_wedges import (
    BIN_DEG,
    BINS,
    blind_bins,
    hide_mirrored_wedges,
    mirrored_blind_bins,
)
from vbrl_ros.features.featurizer import Featurizer


def ring(without: tuple[float, float] | None = None, radius: float = 10.0, count: int = 3600) -> np.ndarray:
    """Points on a circle, none with azimuth (degrees, [-180, 180)) in ``without``."""
    azimuth = np.linspace(-180.0, 180.0, count, endpoint=False) + 0.05  # none on a bin edge
    if without is not None:
        lo, hi = without
        azimuth = azimuth[~((azimuth >= lo) & (azimuth < hi))]
    a = np.radians(azimuth)
    return np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)


def degrees_of(bins: np.ndarray) -> np.ndarray:
    """Centre azimuths (degrees, [-180, 180)) of the True bins."""
    return np.flatnonzero(bins) * BIN_DEG - 180.0 + BIN_DEG / 2


def test_a_wedge_nobody_saw_is_found_where_it_is():
    blind = blind_bins(ring(without=(135.0, 180.0)) @ np.eye(2))  # 45° behind-left
    assert blind.sum() * BIN_DEG == 45.0
    assert degrees_of(blind).min() > 135.0 and degrees_of(blind).max() < 180.0


def test_a_wedge_across_the_seam_is_one_wedge():
    points = ring(without=(-180.0, -150.0))
    points = points[np.degrees(np.arctan2(points[:, 1], points[:, 0])) < 160.0]  # and 160..180: 50° in all
    assert blind_bins(points).sum() * BIN_DEG == 50.0


def test_short_gaps_and_returns_from_the_robot_itself_do_not_count():
    assert not blind_bins(ring(without=(30.0, 45.0))).any()  # 15°: a gap, not a wedge
    body = ring(radius=0.5)  # the robot's own body, all around
    assert blind_bins(np.vstack([ring(without=(90.0, 180.0)), body])).sum() * BIN_DEG == 90.0


def test_a_forward_looking_sensor_hides_nothing():
    forward = ring(without=(35.0, 180.0))
    forward = forward[np.degrees(np.arctan2(forward[:, 1], forward[:, 0])) > -35.0]  # a 70° field of view
    assert not mirrored_blind_bins(forward).any()
    assert hide_mirrored_wedges(forward).all()


def test_the_mirror_is_the_wedge_turned_half_a_turn():
    hidden = mirrored_blind_bins(ring(without=(135.0, 180.0)))
    assert np.allclose(np.sort(degrees_of(hidden)), np.arange(-45.0, 0.0, BIN_DEG) + BIN_DEG / 2)
    points = ring(without=(135.0, 180.0))
    keep = hide_mirrored_wedges(points)
    kept_azimuth = np.degrees(np.arctan2(points[keep, 1], points[keep, 0]))
    assert not ((kept_azimuth > -45.0) & (kept_azimuth < 0.0)).any() and keep.sum() > 0.8 * len(points)
    assert BINS == 72


def turned(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


def behind_hidden(points: np.ndarray) -> np.ndarray:
    """What a sensor whose mast hides the 90° behind it returns."""
    return points[np.abs(np.arctan2(points[:, 1], points[:, 0])) < math.radians(135.0)]


def shift_min_l1(featurizer: Featurizer, a: np.ndarray, b: np.ndarray) -> float:
    rows = featurizer.layout.sector_rows
    return min(float(np.abs(a[rows] - b[np.roll(rows, k, axis=0)]).sum()) for k in range(rows.shape[0]))


@pytest.mark.parametrize("mirror", [False, True])
def test_a_reversed_revisit_of_a_partly_blind_sensor(town_scan, mirror):
    grid = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0), frame="ground")
    featurizer = Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(
        modalities=("height", "spectrum"), min_points=1, normalise=True, mirror_blind_wedges=mirror)))
    first = featurizer.describe(behind_hidden(town_scan))
    # the same spot driven the other way: the world turned half a turn, the mast still behind
    reversed_pass = featurizer.describe(behind_hidden(turned(town_scan, math.pi)))
    other_place = featurizer.describe(behind_hidden(turned(town_scan, math.pi) + np.array([25.0, 0.0, 0.0])))
    revisit, elsewhere = shift_min_l1(featurizer, first, reversed_pass), shift_min_l1(featurizer, first, other_place)
    if mirror:  # both passes now describe the same half of the world: near each other, far from elsewhere
        assert revisit < 0.25 * elsewhere
    else:  # each pass describes what the other could not see
        assert revisit > 0.3 * elsewhere


def test_an_empty_or_tiny_scan_describes_without_error():
    grid = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0), frame="ground")
    featurizer = Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(
        modalities=("height", "spectrum"), min_points=1, normalise=True, mirror_blind_wedges=True)))
    for points in (np.zeros((0, 3)), np.array([[5.0, 0.0, 0.5]]), np.array([[np.nan, 1.0, 0.0], [3.0, 3.0, 1.0]])):
        descriptor = featurizer.describe(points)
        assert descriptor.shape == (featurizer.dimension,) and np.all(np.isfinite(descriptor))
    assert not blind_bins(np.zeros((0, 2))).any()


def test_the_numpy_reference_hides_the_same_mirror_as_the_compiled_path(town_scan):
    grid = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0), frame="ground")
    featurizer = Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(
        modalities=("height", "spectrum"), min_points=1, normalise=True, mirror_blind_wedges=True)))
    scan = behind_hidden(town_scan)
    framed = featurizer.frame(scan).apply(scan)
    assert mirrored_blind_bins(framed[:, :2]).any()  # the case under test: something is hidden
    for compiled, reference in zip(featurizer.modalities(framed), featurizer.modalities_numpy(framed)):
        np.testing.assert_array_equal(compiled, reference)
