import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import MODALITIES, Featurizer

CONFIG = VBRLConfig(
    grid=VoxelGridConfig(extent_xy=8.0, cells_xy=4, z_edges=(-2.0, 0.0, 2.0)),
    features=FeatureConfig(raster_size=8, hog_orientations=9, hog_cells=1, min_points=3),
)
# voxel size 4 x 4 x 2 m; voxel (layer 1, iy 2, ix 1) spans x [-4,0), y [0,4), z [0,2)
VOXEL = (1 * 4 + 2) * 4 + 1
LOW = np.array([-4.0, 0.0, 0.0])
SIZE = np.array([4.0, 4.0, 2.0])


def cloud_in_voxel(local: np.ndarray) -> np.ndarray:
    """Points given in voxel-local [0,1)^3 coordinates -> sensor frame."""
    return LOW + np.asarray(local) * SIZE


def test_layout_matches_blocks():
    f = Featurizer(CONFIG)
    v = CONFIG.grid.n_voxels
    assert f.layout.features_per_modality == (6, 9, 9, 9, 8)
    assert f.dimension == v * 41
    rng = np.random.default_rng(0)
    pts = rng.uniform(-8, 8, (2000, 3)) * [1, 1, 0.2]
    blocks = f.modalities(pts)
    assert [b.shape for b in blocks] == [(v, k) for k in f.layout.features_per_modality]
    desc = f.describe(pts)
    for m, block in enumerate(blocks):
        rows = f.layout.modality_slice(m)
        np.testing.assert_allclose(desc[rows], block.ravel().astype(np.float32))
        assert (f.layout.modality_of_row[rows] == m).all()
        assert (f.layout.voxel_of_row[rows] == np.repeat(np.arange(v), block.shape[1])).all()
    assert len(MODALITIES) == f.layout.n_modalities


def test_covariance_matches_numpy_cov_per_voxel():
    f = Featurizer(CONFIG)
    rng = np.random.default_rng(1)
    # anisotropic blobs far from the voxel centre, plus sensor-far coordinates
    pts = np.concatenate(
        [rng.normal([-2.0, 2.0, 1.0], [0.5, 0.1, 0.3], (500, 3)),
         rng.normal([6.0, -6.0, -1.0], [0.2, 0.6, 0.2], (300, 3))]
    )
    cov = f.modalities(pts)[0]
    a = f.grid.assign(pts)
    for voxel in np.unique(a.voxel[a.voxel < a.n_voxels]):
        inside = pts[a.voxel == voxel]
        if len(inside) < CONFIG.features.min_points:
            continue
        c = np.cov(inside.T)
        expected = [c[0, 0], c[1, 1], c[2, 2], c[0, 1], c[0, 2], c[1, 2]]
        np.testing.assert_allclose(cov[voxel], expected, rtol=1e-9, atol=1e-12)


def test_occupancy_bits_of_hand_made_clouds():
    f = Featurizer(CONFIG)
    # one point each in octants (x,y,z) = (0,0,0), (1,0,0), (1,1,1): bits 0, 1, 7
    pts = cloud_in_voxel([[0.1, 0.1, 0.1], [0.9, 0.2, 0.3], [0.6, 0.7, 0.99], [0.2, 0.3, 0.2]])
    occupancy = f.modalities(pts)[4]
    assert occupancy[VOXEL].tolist() == [1, 1, 0, 0, 0, 0, 0, 1]
    assert occupancy.sum() == 3  # nothing elsewhere


def test_sparse_voxels_count_as_empty():
    f = Featurizer(CONFIG)
    pts = cloud_in_voxel([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9]])  # 2 < min_points
    for block in f.modalities(pts):
        assert not block.any()


def test_snapshot_hog_matches_scikit_image_on_the_same_raster():
    skimage_feature = pytest.importorskip("skimage.feature")
    f = Featurizer(CONFIG)
    rng = np.random.default_rng(2)
    pixels = rng.integers(0, 8, (40, 3))
    pts = cloud_in_voxel((pixels + 0.5) / 8.0)
    hogs = f.modalities(pts)[1:4]
    # rows x columns of each face: XY = (y, x), XZ = (z, x), YZ = (z, y)
    for block, (row_axis, col_axis) in zip(hogs, [(1, 0), (2, 0), (2, 1)]):
        raster = np.zeros((8, 8))
        np.add.at(raster, (pixels[:, row_axis], pixels[:, col_axis]), 1.0)
        raster /= raster.max()
        expected = skimage_feature.hog(
            raster, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(1, 1),
            block_norm="L2", feature_vector=True,
        )
        np.testing.assert_allclose(block[VOXEL], expected, atol=2e-6)


def test_snapshots_do_not_depend_on_point_density():
    f = Featurizer(CONFIG)
    rng = np.random.default_rng(3)
    local = (rng.integers(0, 8, (30, 3)) + 0.5) / 8.0
    once = f.modalities(cloud_in_voxel(local))
    thrice = f.modalities(cloud_in_voxel(np.repeat(local, 3, axis=0)))
    for m in (1, 2, 3, 4):
        np.testing.assert_allclose(once[m], thrice[m], atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_never_nan_on_hostile_input(dtype):
    f = Featurizer(CONFIG)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-20, 20, (5000, 4)).astype(dtype)
    pts[::7, 0] = np.nan
    pts[::11, 1] = np.inf
    pts[::13, 2] = -np.inf
    pts[:50] = pts[50]  # duplicates: zero-variance voxel contents
    desc = f.describe(pts)
    assert desc.shape == (f.dimension,) and desc.dtype == np.float32
    assert np.isfinite(desc).all()
    assert desc.any()


def test_empty_and_all_invalid_scans_give_zero_descriptors():
    f = Featurizer(CONFIG)
    assert not f.describe(np.zeros((0, 3))).any()
    assert not f.describe(np.full((10, 3), np.nan)).any()
    assert not f.describe(np.full((10, 3), 1e6)).any()


def test_describe_is_deterministic_and_ignores_extra_columns():
    f = Featurizer(CONFIG)
    rng = np.random.default_rng(5)
    pts = rng.uniform(-8, 8, (3000, 3))
    with_intensity = np.concatenate([pts, rng.random((3000, 1))], axis=1)
    np.testing.assert_array_equal(f.describe(pts), f.describe(with_intensity))
    shuffled = pts[rng.permutation(len(pts))]
    np.testing.assert_allclose(f.describe(pts), f.describe(shuffled), rtol=1e-5, atol=1e-6)


# -- sectors and tied weights (polar grid) --------------------------------------------

POLAR = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=3, sectors=5, max_range=15.0,
                                        z_edges=(-2.0, 0.0, 2.0)))


def test_cartesian_layout_is_one_sector_with_untied_weights():
    layout = Featurizer(CONFIG).layout
    d = layout.dimension
    assert layout.sectors == 1
    np.testing.assert_array_equal(layout.sector_rows, np.arange(d)[None, :])
    assert layout.sector_rows.dtype == np.int64
    np.testing.assert_array_equal(layout.tie_of_row, np.arange(d))
    assert layout.weight_layout is layout


def test_polar_sector_rows_line_up_the_same_feature_in_every_sector():
    layout = Featurizer(POLAR).layout
    S, d = 5, layout.dimension
    rows = layout.sector_rows
    assert rows.shape == (S, d // S) and rows.dtype == np.int64
    assert sorted(rows.ravel().tolist()) == list(range(d))  # a permutation of the rows
    voxel, modality = layout.voxel_of_row[rows], layout.modality_of_row[rows]
    assert (voxel % S == np.arange(S)[:, None]).all()  # row s is sector s
    # each column: one (modality, layer, ring, feature) in every sector
    assert (modality == modality[0]).all() and (voxel // S == voxel[0] // S).all()
    start = np.array([layout.modality_slice(m).start for m in range(layout.n_modalities)])
    feature = (rows - start[modality]) % np.array(layout.features_per_modality)[modality]
    assert (feature == feature[0]).all()
    # documented column order: descriptor order without the sector
    assert (np.diff(rows[0]) > 0).all()
    np.testing.assert_array_equal(layout.tie_of_row[rows], np.broadcast_to(np.arange(d // S), rows.shape))


def test_polar_weight_layout_ties_sectors_into_layer_ring_columns():
    layout = Featurizer(POLAR).layout
    tied = layout.weight_layout
    assert (tied.n_voxels, tied.n_modalities) == (2 * 3, 5)
    grid = Featurizer(POLAR).grid
    column = grid.voxel_layer() * 3 + grid.voxel_ring()
    np.testing.assert_array_equal(tied.voxel_of_row, column[layout.voxel_of_row])
    np.testing.assert_array_equal(tied.modality_of_row, layout.modality_of_row)
    # a tie class never spans two weight groups
    np.testing.assert_array_equal(tied.voxel_of_row[layout.sector_rows],
                                  np.broadcast_to(tied.voxel_of_row[layout.sector_rows[0]],
                                                  layout.sector_rows.shape))


def test_polar_features_are_never_nan_and_keep_the_layout():
    f = Featurizer(POLAR)
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(0, 8, (5000, 2)), rng.uniform(-3, 3, (5000, 1))], axis=1)
    pts[::7] = np.nan
    blocks = f.modalities(pts)
    assert [b.shape for b in blocks] == [(f.grid.n_voxels, k) for k in f.layout.features_per_modality]
    desc = f.describe(pts)
    assert desc.shape == (f.dimension,) and np.isfinite(desc).all() and desc.any()
