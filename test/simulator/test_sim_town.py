"""Procedural town: determinism, variety, sane placement, validation."""

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.town import STYLES, TownConfig, generate_town

SMALL = TownConfig(blocks_x=3, blocks_y=3)


def _arrays(town):
    s = town.static
    return [s.boxes.center, s.boxes.half_size, s.boxes.yaw, s.cylinders.center_xy, s.ellipsoids.center,
            s.ellipsoids.radii, town.nodes, town.parked_cars.center, town.parked_occupied]


def test_same_seed_same_town_other_seed_other_town():
    a, b, c = generate_town(SMALL, 4), generate_town(SMALL, 4), generate_town(SMALL, 5)
    for x, y in zip(_arrays(a), _arrays(b)):
        np.testing.assert_array_equal(x, y)
    assert len(a.static.boxes) != len(c.static.boxes) or not np.array_equal(a.static.boxes.center,
                                                                              c.static.boxes.center)


def test_town_holds_every_kind_of_object():
    town = generate_town(TownConfig(), 0)
    materials = set(np.concatenate([town.static.boxes.material, town.static.cylinders.material,
                                    town.static.ellipsoids.material]).tolist())
    expected = {Material.BUILDING, Material.TRUNK, Material.FOLIAGE, Material.CONIFER, Material.POLE}
    assert expected <= materials
    assert materials & {Material.WALL, Material.FENCE}
    assert town.parked_occupied.sum() > 50
    assert len(set(town.block_styles.ravel().tolist())) >= 3  # places differ in character
    assert town.block_styles.max() < len(STYLES)
    # Buildings are rotated to follow the jittered streets, not all axis-aligned.
    yaw = np.mod(town.static.boxes.yaw[town.static.boxes.material == Material.BUILDING], np.pi / 2)
    assert np.mean(np.minimum(yaw, np.pi / 2 - yaw) > 0.01) > 0.5
    heights = 2 * town.static.boxes.half_size[town.static.boxes.material == Material.BUILDING, 2]
    assert heights.min() < 8 and heights.max() > 20


def _distance_to_streets(town, xy):
    a, b = town.street_endpoints()
    ab = b - a
    t = np.clip(np.einsum("pkj,kj->pk", xy[:, None] - a[None], ab) / np.einsum("kj,kj->k", ab, ab), 0, 1)
    return np.linalg.norm(xy[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)


def test_nothing_static_stands_on_the_road():
    town = generate_town(SMALL, 1)
    cfg = town.config
    boxes = town.static.boxes
    building = boxes.material == Material.BUILDING
    # A building's footprint circle may not reach into the road (curb = road half width).
    reach = _distance_to_streets(town, boxes.center[building, :2]) - np.hypot(*boxes.half_size[building, :2].T)
    assert np.all(reach > -1.0)  # footprint circles overestimate; the boxes themselves are set back
    trunks = town.static.cylinders.material == Material.TRUNK
    assert np.all(_distance_to_streets(town, town.static.cylinders.center_xy[trunks]) > cfg.curb_offset_m)
    parked = _distance_to_streets(town, town.parked_cars.center[:, :2])
    assert np.all((parked > cfg.curb_offset_m - 2.5) & (parked < cfg.curb_offset_m))


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"blocks_x": 0}, "blocks_x"), ({"block_size_m": (100.0, 50.0)}, "block_size_m"),
     ({"road_width_m": -1.0}, "road_width_m"), ({"evergreen_fraction": 1.5}, "evergreen_fraction"),
     ({"intersection_jitter_m": 50.0}, "intersection_jitter_m")],
)
def test_bad_config_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        TownConfig(**changes)


def test_bad_seed_is_rejected():
    with pytest.raises(ValueError, match="seed"):
        generate_town(SMALL, -1)
