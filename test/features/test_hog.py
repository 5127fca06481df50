import numpy as np
import pytest

from vbrl_ros.features.hog import hog_batch, hog_batch_numpy

IMPLEMENTATIONS = [hog_batch, hog_batch_numpy]


def _rasters(seed: int, size: int = 8) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rasters = rng.integers(0, 5, (60, size, size)).astype(np.float64)
    rasters[:10] = (rng.random((10, size, size)) < 0.2)  # sparse, binary-ish snapshots
    rasters[10] = 0.0  # empty
    return rasters


@pytest.mark.parametrize("hog", IMPLEMENTATIONS)
@pytest.mark.parametrize("cells, orientations", [(1, 9), (2, 9), (4, 6), (1, 12)])
def test_matches_scikit_image_hog(hog, cells, orientations):
    skimage_feature = pytest.importorskip("skimage.feature")
    size = 8
    rasters = _rasters(cells * 100 + orientations, size)
    ours = hog(rasters, orientations=orientations, cells=cells)
    reference = np.stack(
        [
            skimage_feature.hog(
                r,
                orientations=orientations,
                pixels_per_cell=(size // cells, size // cells),
                cells_per_block=(1, 1),
                block_norm="L2",
                feature_vector=True,
            )
            for r in rasters
        ]
    )
    # scikit-image accumulates cells in float32
    np.testing.assert_allclose(ours, reference, atol=2e-6)
    assert np.all(ours[10] == 0)


@pytest.mark.parametrize("cells, orientations", [(1, 9), (2, 9), (4, 6), (1, 12), (1, 8), (2, 4), (1, 1)])
def test_compiled_kernel_matches_numpy_reference(cells, orientations):
    rng = np.random.default_rng(orientations * 10 + cells)
    rasters = np.concatenate([
        _rasters(orientations),  # integers: gradients exactly on bin edges (45, 90, 135 degrees)
        rng.random((20, 8, 8)),
        rng.random((20, 8, 8)) * (rng.random((20, 8, 8)) < 0.1),  # like normalised snapshots
        np.full((2, 8, 8), 0.7),  # constant
        np.zeros((1, 8, 8)),
    ])
    rasters[-1, :, :4] = 1.0  # edge with gradient at 180 degrees ...
    rasters[-1, 4:, 4] = 1e-300  # ... plus a sliver that atan2 rounds to exactly pi: bin 0, not the last
    ours = hog_batch(rasters, orientations, cells)
    reference = hog_batch_numpy(rasters, orientations, cells)
    assert ours.shape == reference.shape == (len(rasters), cells * cells * orientations)
    assert ours.dtype == np.float64
    np.testing.assert_allclose(ours, reference, rtol=1e-12, atol=1e-14)
    # same bins exactly, not just similar values
    np.testing.assert_array_equal(ours > 0, reference > 0)
    assert np.isfinite(ours).all()
    assert np.all(ours[-3:-1] == 0) and np.all(ours[10] == 0)  # constant and empty rasters


@pytest.mark.parametrize("hog", IMPLEMENTATIONS)
def test_vertical_edge_votes_into_the_zero_degree_bin(hog):
    raster = np.zeros((1, 8, 8))
    raster[0, :, 4:] = 1.0  # intensity changes along columns: gradient at 0 degrees
    h = hog(raster, orientations=9, cells=1)[0]
    assert h.argmax() == 0 and h[1:].max() == 0


def test_empty_batch():
    assert hog_batch(np.zeros((0, 8, 8)), 9, 2).shape == (0, 36)


@pytest.mark.parametrize("hog", IMPLEMENTATIONS)
def test_bad_shapes(hog):
    with pytest.raises(ValueError):
        hog(np.zeros((2, 8, 4)), 9, 1)
    with pytest.raises(ValueError):
        hog(np.zeros((2, 8, 8)), 9, 3)
