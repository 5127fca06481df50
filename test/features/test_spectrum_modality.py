"""The spectrum modality: unchanged by a few metres of translation, turned by a sector shift
when the scan turns, computed once for every view, and only on a polar grid."""

import math

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.bev_spectrum import SpectrumSampler
from vbrl_ros.features.featurizer import Featurizer

RINGS, SECTORS = 20, 30
GRID = VoxelGridConfig(kind="polar", rings=RINGS, sectors=SECTORS, max_range=40.0, z_edges=(0.0, 20.0),
                       frame="ground")


def featurizer(modalities=("height", "spectrum")) -> Featurizer:
    return Featurizer(VBRLConfig(grid=GRID, features=FeatureConfig(modalities=modalities, min_points=1,
                                                                   normalise=True)))


def blocks(descriptor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = RINGS * SECTORS
    return descriptor[:n].reshape(RINGS, SECTORS), descriptor[n:].reshape(RINGS, SECTORS)


def turned(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


def test_a_translation_barely_changes_the_spectrum_but_moves_the_heights(town_scan):
    f = featurizer()
    height, spectrum = blocks(f.describe(town_scan))
    for dx, dy in ((2.0, 0.0), (0.0, -3.0)):
        moved_height, moved_spectrum = blocks(f.describe(town_scan + [dx, dy, 0.0]))
        spectrum_change = np.abs(moved_spectrum - spectrum).sum()
        height_change = np.abs(moved_height - height).sum()
        assert spectrum_change < 0.25 * height_change, (spectrum_change, height_change)


def test_turning_the_scan_shifts_the_spectrum_by_the_same_sectors_as_the_heights(town_scan):
    f = featurizer()
    _, spectrum = blocks(f.describe(town_scan))
    k = 7  # sectors, 84 degrees
    _, turned_spectrum = blocks(f.describe(turned(town_scan, k * 2 * math.pi / SECTORS)))
    errors = [np.abs(np.roll(spectrum, shift, axis=1) - turned_spectrum).sum() for shift in range(SECTORS)]
    # a half turn leaves a real image's spectrum unchanged: k and k + 15 fit equally
    assert int(np.argmin(errors)) % (SECTORS // 2) == k
    assert min(errors) < 0.6 * np.median(errors)


def test_every_view_shares_one_spectrum_and_has_its_own_heights(town_scan):
    f = featurizer()
    offsets = np.array([[0.0, 0.0], [1.5, 0.0], [0.0, 3.0]])
    views = f.describe_views(town_scan, offsets, f.frame(town_scan))
    np.testing.assert_array_equal(views[1, RINGS * SECTORS:], views[0, RINGS * SECTORS:])
    assert not np.array_equal(views[1, :RINGS * SECTORS], views[0, :RINGS * SECTORS])
    np.testing.assert_array_equal(views[0], f.describe(town_scan))
    assert np.all(views >= 0) and np.isclose(views[0, RINGS * SECTORS:].sum(), 1.0)  # normalised block


def test_the_numpy_reference_and_the_compiled_path_agree(town_scan):
    f = featurizer(("height", "spectrum"))
    framed = f.frame(town_scan).apply(town_scan)
    for compiled, reference in zip(f.modalities(framed), f.modalities_numpy(framed)):
        np.testing.assert_array_equal(compiled, reference)


def test_an_empty_image_has_a_flat_zero_spectrum():
    sampler = SpectrumSampler(RINGS, SECTORS)
    empty = sampler.image(np.zeros((0, 2)), np.zeros(0))
    assert empty.shape == (sampler.size, sampler.size) and not empty.any()
    np.testing.assert_array_equal(sampler.spectrum(empty), np.zeros(RINGS * SECTORS))


def test_a_cartesian_grid_refuses_the_spectrum_by_name():
    with pytest.raises(ValueError, match=r"features\.modalities.*polar"):
        VBRLConfig(grid=VoxelGridConfig(), features=FeatureConfig(modalities=("height", "spectrum")))
