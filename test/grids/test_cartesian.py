import numpy as np
import pytest

from vbrl_ros.config import VoxelGridConfig
from vbrl_ros.grids.cartesian import CartesianVoxelGrid

GRID = VoxelGridConfig(extent_xy=10.0, cells_xy=4, z_edges=(-2.0, 0.0, 1.0, 5.0))


def test_voxel_index_is_layer_major():
    grid = CartesianVoxelGrid(GRID)
    # cell size 5 m; x=-7.5 -> ix 0, y=2.5 -> iy 2, z=0.5 -> layer 1 (unequal layer heights)
    a = grid.assign(np.array([[-7.5, 2.5, 0.5], [9.9, -9.9, 4.9], [0.0, 0.0, -2.0]]), 4)
    assert a.voxel.tolist() == [(1 * 4 + 2) * 4 + 0, (2 * 4 + 0) * 4 + 3, (0 * 4 + 2) * 4 + 2]
    # sub-cells: x=-7.5 is the middle of [-10,-5) -> 2 of 4; z=0.5 in [0,1) -> 2; z=4.9 in [1,5) -> 3
    assert a.subcell[:, 0].tolist() == [2, 2, 2]
    assert a.subcell[2, 1] == 3
    assert grid.voxel_layer()[a.voxel].tolist() == [1, 2, 0]


def test_voxel_centers_contain_their_points():
    grid = CartesianVoxelGrid(GRID)
    centers = grid.voxel_centers()
    a = grid.assign(centers, 2)
    assert a.voxel.tolist() == list(range(GRID.n_voxels))


def test_outside_and_non_finite_points_go_to_the_sentinel():
    grid = CartesianVoxelGrid(GRID)
    pts = np.array(
        [
            [10.0, 0, 0],  # x == extent: outside (half-open)
            [0, -10.01, 0],
            [0, 0, 5.0],  # z == top edge: outside
            [0, 0, -2.5],
            [np.nan, 0, 0],
            [0, np.inf, 0],
            [0, 0, -np.inf],
            [1.0, 1.0, 0.5],  # the only inside point
        ]
    )
    a = grid.assign(pts, 8)
    assert (a.voxel[:-1] == GRID.n_voxels).all()
    assert a.voxel[-1] < GRID.n_voxels
    assert a.n_inside == 1
    assert ((a.subcell >= 0) & (a.subcell < 8)).all()  # in range even for garbage rows


def test_float32_points_just_below_the_far_edge_stay_inside():
    grid = CartesianVoxelGrid(GRID)
    edge = np.nextafter(np.float32(10.0), np.float32(0))
    a = grid.assign(np.array([[edge, edge, np.nextafter(np.float32(5), np.float32(0))]], np.float32), 8)
    assert a.voxel[0] == GRID.n_voxels - 1
    assert a.subcell[:, 0].tolist() == [7, 7, 7]


def test_rejects_bad_shapes_and_subdivisions():
    grid = CartesianVoxelGrid(GRID)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        grid.assign(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="power of two"):
        grid.assign(np.zeros((5, 3)), 6)


def test_each_grid_refuses_the_other_kind_of_config():
    from vbrl_ros.grids.polar import PolarVoxelGrid

    with pytest.raises(ValueError, match="CartesianVoxelGrid needs a cartesian grid config"):
        CartesianVoxelGrid(VoxelGridConfig(kind="polar"))
    with pytest.raises(ValueError, match="PolarVoxelGrid needs a polar grid config"):
        PolarVoxelGrid(VoxelGridConfig())
    polar = PolarVoxelGrid(VoxelGridConfig(kind="polar"))
    assert polar.n_voxels == polar.config.n_voxels and len(polar.z_edges) == polar.config.n_layers + 1
