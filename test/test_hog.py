import numpy as np
import pytest

skimage_feature = pytest.importorskip("skimage.feature")

from vbrl_ros.hog import hog_batch


@pytest.mark.parametrize("cells, orientations", [(1, 9), (2, 9), (4, 6), (1, 12)])
def test_matches_scikit_image_hog(cells, orientations):
    rng = np.random.default_rng(cells * 100 + orientations)
    size = 8
    rasters = rng.integers(0, 5, (60, size, size)).astype(np.float64)
    rasters[:10] = (rng.random((10, size, size)) < 0.2)  # sparse, binary-ish snapshots
    rasters[10] = 0.0  # empty
    ours = hog_batch(rasters, orientations=orientations, cells=cells)
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


def test_vertical_edge_votes_into_the_zero_degree_bin():
    raster = np.zeros((1, 8, 8))
    raster[0, :, 4:] = 1.0  # intensity changes along columns: gradient at 0 degrees
    h = hog_batch(raster, orientations=9, cells=1)[0]
    assert h.argmax() == 0 and h[1:].max() == 0
