"""The compiled featurizer pass computes exactly what the numpy reference computes."""

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer

CONFIGS = [
    VBRLConfig(),
    VBRLConfig(grid=VoxelGridConfig(extent_xy=12.0, cells_xy=5, z_edges=(-2.0, -0.5, 0.7, 4.0, 9.0)),
               features=FeatureConfig(raster_size=4, hog_cells=2, hog_orientations=6, min_points=1)),
]


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_kernel_equals_numpy_reference(config, dtype):
    f = Featurizer(config)
    rng = np.random.default_rng(0)
    extent = config.grid.extent_xy
    points = np.concatenate([rng.uniform(-1.2 * extent, 1.2 * extent, (30000, 2)),
                             rng.uniform(-4, 10, (30000, 1)), rng.random((30000, 1))], axis=1)
    points[::17, 0] = np.nan
    points[::19, 1] = np.inf
    points[::23, 2] = -np.inf
    # exactly on cell, layer and grid edges, and just below the far edges
    edges = np.array([[-extent, -extent, config.grid.z_edges[0]],
                      [0.0, 0.0, config.grid.z_edges[1]],
                      [np.nextafter(extent, 0), np.nextafter(extent, 0),
                       np.nextafter(config.grid.z_edges[-1], -np.inf)],
                      [extent, 0.0, 0.0]])
    points[:4, :3] = edges
    points = points.astype(dtype)
    for fast, reference in zip(f.modalities(points), f.modalities_numpy(points)):
        np.testing.assert_array_equal(fast, reference)


def test_kernel_rejects_bad_shapes_and_accepts_other_dtypes():
    f = Featurizer()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        f.modalities(np.zeros((4, 2)))
    ints = np.array([[1, 2, 0], [1, 2, 0], [1, 2, 0]], dtype=np.int16)
    np.testing.assert_array_equal(f.describe(ints), f.describe(ints.astype(np.float64)))


POLAR_CONFIGS = [
    VBRLConfig(grid=VoxelGridConfig(kind="polar")),
    VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=3, sectors=7, max_range=12.5,
                                    z_edges=(-2.0, -0.5, 0.7, 4.0, 9.0)),
               features=FeatureConfig(raster_size=4, hog_cells=2, hog_orientations=6, min_points=1)),
]


@pytest.mark.parametrize("config", POLAR_CONFIGS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("order", ["random", "azimuth"])
def test_polar_kernel_equals_numpy_reference(config, dtype, order):
    """Bit for bit, in random order and in the azimuth order of real scans.

    The kernel starts each point's angular bin from the previous point's and the
    numpy path from a polynomial guess; both must end in the same bin.
    """
    f = Featurizer(config)
    rng = np.random.default_rng(1)
    reach = config.grid.max_range
    points = np.concatenate([rng.uniform(-1.1 * reach, 1.1 * reach, (30000, 2)),
                             rng.uniform(-4, 10, (30000, 1)), rng.random((30000, 1))], axis=1)
    if order == "azimuth":
        points = points[np.argsort(np.arctan2(points[:, 1], points[:, 0]))]
    points[::17, 0] = np.nan
    points[::19, 1] = np.inf
    points[::23, 2] = -np.inf
    bins = config.grid.sectors * config.features.raster_size
    edge = 2 * np.pi * np.arange(bins) / bins  # every angular sub-cell edge, ring edges, axes
    radius = np.resize(np.arange(config.grid.rings + 1) * config.grid.ring_width, bins)
    radius[radius == 0] = 1e-3
    edges = np.stack([radius * np.cos(edge), radius * np.sin(edge), np.full(bins, 0.3)], axis=1)
    special = np.array([[0.0, 0.0, 0.5], [1.0, -0.0, 0.5], [1.0, -1e-300, 0.5], [-1.0, 0.0, 0.5],
                        [0.0, -1.0, 0.5], [np.nextafter(reach, 0), 0.0, 0.5], [reach, 0.0, 0.5]])
    points[: bins + len(special), :3] = np.concatenate([edges, special])
    points = points.astype(dtype)
    for fast, reference in zip(f.modalities(points), f.modalities_numpy(points)):
        np.testing.assert_array_equal(fast, reference)
