"""The polar grid: voxel numbering, voxel-local frames and the sector-shift symmetry."""

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.grids.cartesian import CartesianVoxelGrid
from vbrl_ros.grids.kinds import make_grid
from vbrl_ros.grids.polar import PolarVoxelGrid, approximate_azimuth

# ring width 5 m, sector 45 degrees, layers z in [-2, 0) and [0, 4)
GRID = VoxelGridConfig(kind="polar", rings=4, sectors=8, max_range=20.0, z_edges=(-2.0, 0.0, 4.0))


def polar_points(r, theta_deg, z) -> np.ndarray:
    t = np.radians(np.asarray(theta_deg, dtype=np.float64))
    return np.stack([r * np.cos(t), r * np.sin(t), np.asarray(z, dtype=np.float64)], axis=1)


def rotate(points: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.array(points, dtype=np.float64)
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def test_make_grid_picks_the_class():
    assert isinstance(make_grid(GRID), PolarVoxelGrid)
    assert isinstance(make_grid(VoxelGridConfig()), CartesianVoxelGrid)
    with pytest.raises(ValueError, match="polar"):
        PolarVoxelGrid(VoxelGridConfig())
    with pytest.raises(ValueError, match="cartesian"):
        CartesianVoxelGrid(GRID)


def test_points_at_known_r_theta_z_land_in_the_expected_voxel():
    grid = PolarVoxelGrid(GRID)
    pts = polar_points(
        r=[7.5, 19.9, 2.0, 12.0],
        theta_deg=[100.0, 359.9, 0.0, 181.0],
        z=[1.0, -0.1, -2.0, 3.9],
    )
    a = grid.assign(pts, 4)
    # (layer * rings + ring) * sectors + sector
    assert a.voxel.tolist() == [(1 * 4 + 1) * 8 + 2, (0 * 4 + 3) * 8 + 7, (0 * 4 + 0) * 8 + 0,
                                (1 * 4 + 2) * 8 + 4]
    # (radial, angular, z) on a 4-lattice: 7.5 m is mid ring 1; 100 deg is 10/45 into
    # sector 2; z = 1 is 1/4 into [0, 4)
    assert a.subcell[:, 0].tolist() == [2, 0, 1]
    assert a.subcell[:, 1].tolist() == [3, 3, 3]  # 19.9 m, 44.9/45 of sector 7, -0.1 near top
    assert a.subcell[:, 2].tolist() == [1, 0, 0]
    assert grid.voxel_ring()[a.voxel].tolist() == [1, 3, 0, 2]
    assert grid.voxel_sector()[a.voxel].tolist() == [2, 7, 0, 4]
    assert grid.voxel_layer()[a.voxel].tolist() == [1, 0, 0, 1]


def test_xyz_is_in_the_sector_local_frame():
    grid = PolarVoxelGrid(GRID)
    pts = polar_points(r=[7.5, 12.0], theta_deg=[100.0, 181.0], z=[1.0, 3.9])
    a = grid.assign(pts)
    # rotated by minus the sector centre (112.5 and 202.5 degrees): x' radial, y' tangential
    expected = polar_points(r=[7.5, 12.0], theta_deg=[100.0 - 112.5, 181.0 - 202.5], z=[1.0, 3.9])
    np.testing.assert_allclose(a.xyz.T, expected, atol=1e-12)


def test_azimuth_edges_wrap_into_the_right_sector():
    grid = PolarVoxelGrid(GRID)
    pts = np.array([
        [10.0, 0.0, 1.0],  # on +x: sector 0, first angular sub-cell
        [10.0, -0.0, 1.0],
        [10.0, -1e-300, 1.0],  # just below +x: the last sector (azimuth rounds to 2 pi)
        [10.0, -1e-12, 1.0],
        [-10.0, 0.0, 1.0],  # azimuth pi: first sub-cell of sector 4
        [0.0, 10.0, 1.0],  # pi / 2: first sub-cell of sector 2
    ])
    a = grid.assign(pts, 8)
    assert grid.voxel_sector()[a.voxel].tolist() == [0, 0, 7, 7, 4, 2]
    assert a.subcell[1].tolist() == [0, 0, 7, 7, 0, 0]


def test_dropped_points_go_to_the_sentinel():
    grid = PolarVoxelGrid(GRID)
    pts = np.array([
        [20.0, 0.0, 1.0],  # r == max_range: outside (half-open)
        [15.0, 15.0, 1.0],  # corner of the square around the disc
        [0.0, 0.0, 1.0],  # on the z axis: no azimuth
        [1.0, 1.0, 4.0],  # z == top edge
        [1.0, 1.0, -2.5],
        [np.nan, 1.0, 1.0],
        [1.0, np.inf, 1.0],
        [-np.inf, np.nan, 1.0],
        [1.0, 1.0, -np.inf],
        [3.0, -4.0, 0.5],  # the only inside point
    ])
    a = grid.assign(pts, 8)
    assert (a.voxel[:-1] == GRID.n_voxels).all()
    assert a.voxel[-1] == (1 * 4 + 1) * 8 + 6 and a.n_inside == 1
    assert ((a.subcell >= 0) & (a.subcell < 8)).all()  # in range even for garbage rows


def test_voxel_centers_contain_their_points():
    grid = PolarVoxelGrid(GRID)
    a = grid.assign(grid.voxel_centers(), 2)
    assert a.voxel.tolist() == list(range(GRID.n_voxels))
    np.testing.assert_allclose(a.xyz[1], 0.0, atol=1e-12)  # the centre line of every sector


def test_angular_bins_equal_atan2_bins_away_from_edges():
    """The trig-free binning (polynomial guess + exact boundary tests) is the azimuth's bin."""
    config = VoxelGridConfig(kind="polar", rings=2, sectors=360, max_range=100.0)
    grid = PolarVoxelGrid(config)
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(0, 30, (200000, 2)), np.zeros((200000, 1))], axis=1)
    sub = 32  # 11520 bins of 0.03 degrees: the guess alone would often be a bin off
    azimuth = np.mod(np.arctan2(pts[:, 1], pts[:, 0]), 2 * np.pi) * (360 * sub / (2 * np.pi))
    clear = np.abs(azimuth - np.round(azimuth)) > 1e-6
    a = grid.assign(pts, sub)
    inside = a.voxel < config.n_voxels
    assert inside.sum() > 190000
    bins = grid.voxel_sector()[a.voxel[inside]] * sub + a.subcell[1, inside]
    np.testing.assert_array_equal(bins[clear[inside]], np.floor(azimuth[inside & clear]))
    # the guess it starts from is within 1.2e-5 rad
    exact = np.mod(np.arctan2(pts[:, 1], pts[:, 0]), 2 * np.pi)
    assert np.abs(approximate_azimuth(pts[:, 0], pts[:, 1]) - exact).max() < 1.2e-5


# -- the sector-shift symmetry --------------------------------------------------------

POLAR = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=6, sectors=12, max_range=30.0))


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    """A simulated street scan, turned by a generic yaw.

    The simulated LiDAR fires at exact multiples of 360/1024 degrees, some of which are
    sub-cell edges; the extra yaw moves every ray off the edges so that float rounding of
    the rotations below cannot move points across them.
    """
    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=6.0))
    run = sim.simulate_run(town, route, sim.LidarConfig(beams=32, columns=1024), "summer_clear",
                           seed=1)
    return rotate(run.scan(2).points[:, :3].astype(np.float64), 0.0123)


@pytest.mark.parametrize("k", [1, 5, 11, 12 + 3, -2])  # 11 = S - 1 and 15, -2 wrap around
def test_rotating_by_whole_sectors_rolls_the_sectors(scan, k):
    f = Featurizer(POLAR)
    S = POLAR.grid.sectors
    rows = f.layout.sector_rows
    original = f.describe(scan)
    rotated = f.describe(rotate(scan, k * 2 * np.pi / S))
    assert np.count_nonzero(original) > 0.2 * len(original)  # a real, populated descriptor
    expected = np.empty_like(original)
    expected[rows[(np.arange(S) + k) % S]] = original[rows]  # sector s moved to s + k
    covariance = f.layout.modality_slice(0)
    # HOG and occupancy come from integer counts: exactly equal
    np.testing.assert_array_equal(rotated[covariance.stop:], expected[covariance.stop:])
    # covariances of rotated coordinates: equal up to float rounding
    np.testing.assert_allclose(rotated[covariance], expected[covariance], rtol=1e-5, atol=1e-6)
    # in float64, before the descriptor's float32 cast: rotation only changes round-off
    a = f.modalities(scan)[0]
    b = f.modalities(rotate(scan, k * 2 * np.pi / S))[0]
    voxel = np.arange(f.grid.n_voxels)
    source = voxel - voxel % S + (voxel % S - k) % S  # same column, sector s - k
    np.testing.assert_allclose(b, a[source], rtol=1e-9, atol=1e-9)


def test_the_shift_must_match_the_rotation(scan):
    """Sanity: the wrong shift, or the Cartesian grid, does not see a rotated scan as equal."""
    f = Featurizer(POLAR)
    S = POLAR.grid.sectors
    rows = f.layout.sector_rows
    original, rotated = f.describe(scan), f.describe(rotate(scan, 2 * 2 * np.pi / S))
    right = np.abs(rotated[rows[(np.arange(S) + 2) % S]] - original[rows]).sum()
    wrong = np.abs(rotated[rows[(np.arange(S) + 1) % S]] - original[rows]).sum()
    assert right < 1e-3 < wrong
    cartesian = Featurizer(VBRLConfig())
    assert cartesian.layout.sector_rows.shape == (1, cartesian.dimension)
    a, b = cartesian.describe(scan), cartesian.describe(rotate(scan, 2 * 2 * np.pi / S))
    assert np.abs(a - b).sum() > 0.1 * np.abs(a).sum()
