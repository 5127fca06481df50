"""A tilted sensor's field of view, mirrored: a reversed pass of a tilted sensor keeps the same
band of the world, and level or wide-field sensors are left alone."""

import math

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.datasets.mount_tilt import mount_rotation
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.features.field_of_view import (
    MIN_TILT_DEG,
    MIRROR_RAMP_DEG,
    field_top,
    mirrored_top,
    mirrors,
    seen_both_ways,
)
from vbrl_ros.features.parallel import describe_keyframe

GRID = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0), frame="ground")


def featurizer(mirror: bool) -> Featurizer:
    return Featurizer(VBRLConfig(grid=GRID, features=FeatureConfig(
        modalities=("height", "spectrum"), min_points=1, normalise=True, mirror_field_of_view=mirror)))


def beams(low_deg: float, high_deg: float, count: int = 16, columns: int = 360, radius: float = 20.0):
    """Sensor-frame points of ``count`` beams from ``low_deg`` to ``high_deg``, all ``radius`` away."""
    elevation = np.radians(np.linspace(low_deg, high_deg, count))[:, None]
    azimuth = np.radians(np.arange(columns) * 360.0 / columns)[None, :]
    return radius * np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation) * np.ones_like(azimuth)], axis=-1).reshape(-1, 3)


def test_the_top_of_the_field_of_view_is_read_from_the_scan():
    assert math.degrees(field_top(beams(-30.0, 10.0))) == pytest.approx(10.0, abs=0.1)
    stray = np.vstack([beams(-30.0, 10.0), [[5.0, 0.0, 20.0]]])  # one return above the top beam
    assert math.degrees(field_top(stray)) == pytest.approx(10.0, abs=0.1)
    assert math.isnan(field_top(np.zeros((0, 3)))) and math.isnan(field_top(beams(-1, 1, 2, 10, 0.5)))


def test_only_a_tilted_sensor_whose_field_tops_out_low_is_mirrored():
    tilted, top = mount_rotation(0.0, 10.0).T, math.radians(10.0)  # sensor -> levelled
    assert mirrors(tilted, top)
    assert not mirrors(np.eye(3), top)  # level: both ways see the same band
    assert not mirrors(mount_rotation(0.0, 2.0).T, top)  # barely tilted
    assert not mirrors(tilted, math.radians(45.0))  # a wide field sees the tops either way
    assert not mirrors(tilted, math.nan)


def test_a_point_the_sensor_turned_round_would_not_see_is_dropped():
    # pitched 20 degrees down, a -30..10 degree sensor sees up to 30 degrees behind it but only
    # to -10 degrees ahead: turned round, it would not see what lies behind above -10 degrees
    to_level = mount_rotation(0.0, 20.0)  # the sensor's axes in the level frame: sensor -> levelled
    top = math.radians(10.0)

    def sensor_point(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
        a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
        level = 10.0 * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        return to_level.T @ level

    points = np.array([sensor_point(180.0, 20.0), sensor_point(180.0, -15.0), sensor_point(0.0, -20.0),
                       sensor_point(90.0, 5.0)])
    assert (points[:, 2] / np.hypot(points[:, 0], points[:, 1]) <= math.tan(top) + 1e-9).all()  # all were seen
    np.testing.assert_array_equal(seen_both_ways(points, to_level, top), [False, True, True, True])
    assert seen_both_ways(points, np.eye(3), top).all()


def test_mirroring_sets_in_gradually_so_a_swaying_sensor_is_not_cut_by_fits_and_starts():
    points, top = beams(-30.0, 10.0, count=32), math.radians(10.0)
    kept = {}
    for pitch in (2.9, 3.05, 4.0, 5.0, 6.0, 8.0):
        rotation = mount_rotation(0.0, pitch).T  # sensor -> levelled
        kept[pitch] = seen_both_ways(points, rotation, top).mean()
    assert kept[2.9] == 1.0 and kept[3.05] > 0.995  # no sudden cut at the threshold...
    shares = list(kept.values())
    assert all(a >= b for a, b in zip(shares, shares[1:])) and kept[5.0] < kept[4.0] < kept[3.05]  # ... a ramp
    full = MIN_TILT_DEG + MIRROR_RAMP_DEG
    assert mirrored_top(mount_rotation(0.0, full).T, top) == pytest.approx(top)  # then the whole mirror
    assert mirrored_top(mount_rotation(0.0, 8.0).T, top) == top
    assert kept[8.0] < 0.9  # what the tilted-sensor tests rely on


def test_the_height_map_drops_what_seen_both_ways_drops(town_scan):
    tilted = town_scan @ mount_rotation(5.0, 10.0)  # the level scan as a sensor so tilted sees it
    mirrored = featurizer(True)
    frame = mirrored.frame(tilted)
    assert mirrors(frame.rotation, frame.field_top)  # the case under test: something is dropped
    keep = seen_both_ways(tilted, frame.rotation, frame.field_top)
    assert 0.7 * len(keep) < keep.sum() < len(keep)
    plain = featurizer(False)
    np.testing.assert_array_equal(mirrored.describe_views(tilted, np.zeros((1, 2)), frame),
                                  plain.describe_views(tilted[keep], np.zeros((1, 2)), frame))


def test_a_level_scan_describes_the_same_either_way(town_scan):
    np.testing.assert_array_equal(featurizer(True).describe(town_scan), featurizer(False).describe(town_scan))


def shift_min_l1(f: Featurizer, a: np.ndarray, b: np.ndarray) -> float:
    rows = f.layout.sector_rows
    return min(float(np.abs(a[rows] - b[np.roll(rows, k, axis=0)]).sum()) for k in range(rows.shape[0]))


@pytest.fixture(scope="module")
def tilted_passes():
    """Scans of a sensor tilted 5 degrees in roll and 10 in pitch (a -22.5..22.5 degree field),
    1.5 m up: a place, the same place driven the other way, and a place 20 m on."""
    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0, sensor_height_m=1.5,
                                                 sensor_roll_deg=5.0, sensor_pitch_deg=10.0))
    lidar = sim.LidarConfig(beams=32, columns=720, vertical_fov_deg=(-22.5, 22.5))
    scene, rng = town.reference_scene(), np.random.default_rng(0)
    passes = {}
    for place in (30, 150):
        pose = route.poses[place]
        back = pose.copy()
        back[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ pose[:3, :3]  # a half turn about the vertical
        passes[place] = [sim.render_scan(scene, p, lidar, rng)[0][:, :3].astype(np.float64)
                         for p in (pose, back, route.poses[place + 20])]
    return passes


def test_a_reversed_pass_of_a_tilted_sensor_describes_like_the_first(tilted_passes):
    ratios = {}
    for mirror in (False, True):
        f = featurizer(mirror)
        for place, scans in tilted_passes.items():
            first, reversed_pass, elsewhere = (f.describe(s) for s in scans)
            ratios[mirror, place] = shift_min_l1(f, first, reversed_pass) / shift_min_l1(f, first, elsewhere)
    for place in tilted_passes:
        assert ratios[True, place] < 0.4 * ratios[False, place], ratios  # measured: 0.24-0.36 -> 0.04-0.10
        assert ratios[True, place] < 0.15, ratios


def test_the_setting_needs_height_maps_on_a_levelled_grid():
    with pytest.raises(ValueError, match="mirror_field_of_view"):
        FeatureConfig(mirror_field_of_view=True)  # the paper's modalities
    with pytest.raises(ValueError, match="mirror_field_of_view"):
        VBRLConfig(grid=VoxelGridConfig(kind="polar", frame="sensor"),
                   features=FeatureConfig(modalities=("height",), mirror_field_of_view=True))
    assert "mirror_field_of_view" not in FeatureConfig().to_dict()  # older models keep their identity
    on = FeatureConfig(modalities=("height",), mirror_field_of_view=True)
    assert VBRLConfig.from_dict(VBRLConfig(grid=GRID, features=on).to_dict()).features.mirror_field_of_view


def test_the_field_of_view_is_read_from_the_keyframe_not_its_trail(town_scan):
    tilted = town_scan @ mount_rotation(5.0, 10.0)
    # earlier keyframes merged in: near points seen from farther back rise above this sensor's top
    trail = np.array([[6.0 * math.cos(a), 6.0 * math.sin(a), 4.0] for a in np.linspace(0, 2 * np.pi, 2000)])
    cloud = np.vstack([tilted, trail @ mount_rotation(5.0, 10.0)])
    f = featurizer(True)
    assert f.frame(cloud, scan=tilted).field_top == field_top(tilted) < f.frame(cloud).field_top
    by_scan = describe_keyframe(f, (tilted, cloud))
    np.testing.assert_array_equal(by_scan, f.describe(cloud, scan=tilted))
    assert not np.array_equal(by_scan, f.describe(cloud))
