"""Procedural town: a jittered street grid lined with varied urban furniture.

The town is a ``blocks_x`` x ``blocks_y`` grid of blocks. Intersections are
jittered, so streets are straight but not axis-aligned and everything placed
along them is a yaw-rotated primitive. Every side of every street segment (a
*frontage*) gets a style from the block behind it -- downtown (tall street
walls), residential (detached houses, fences, hedges, front-yard trees),
industrial (large low halls behind walls) or park (trees, low wall) -- and its
own random sizes, gaps and set-backs, so no two places look alike. Street
trees, lamp posts and parking slots follow every street.

Parked cars are kept apart from the static geometry: the town fixes the slots
and a resident car per slot, a run (see :mod:`.scenarios`) decides which slots
are occupied, so parked cars change between sessions as they do in reality.

Generation is deterministic for ``(config, seed)``. It loops in Python over
objects (a few thousand, once per town); ray casting is where vectorisation
matters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import Boxes, Cylinders, Ellipsoids, Material
from .scene import Scene

STYLES = ("downtown", "residential", "industrial", "park")
_STYLE_WEIGHTS = (0.3, 0.35, 0.2, 0.15)

# Per style: building frontage/depth/height/gap/set-back ranges (m), yaw jitter
# (rad), street-tree probability, boundary type probabilities (fence, wall, hedge).
_STYLE = {
    "downtown": dict(front=(12, 32), depth=(12, 26), height=(12, 36), gap=(0, 4), setback=(0.3, 2.0),
                     yaw_jitter=0.0, tree_p=0.45, boundary=(0.0, 0.0, 0.0)),
    "residential": dict(front=(8, 14), depth=(8, 13), height=(4, 9), gap=(4, 11), setback=(4, 9),
                        yaw_jitter=0.25, tree_p=0.8, boundary=(0.3, 0.15, 0.3)),
    "industrial": dict(front=(22, 50), depth=(18, 35), height=(6, 13), gap=(6, 16), setback=(6, 12),
                       yaw_jitter=0.0, tree_p=0.2, boundary=(0.3, 0.5, 0.0)),
    "park": dict(front=(6, 10), depth=(5, 8), height=(3, 5), gap=(60, 200), setback=(15, 30),
                 yaw_jitter=0.6, tree_p=1.0, boundary=(0.1, 0.4, 0.2)),
}


def _check_range(name: str, value: tuple[float, float], low: float = 0.0) -> None:
    if len(value) != 2 or not all(math.isfinite(v) for v in value) or not low < value[0] <= value[1]:
        raise ValueError(f"TownConfig.{name} must be a (min, max) pair with {low} < min <= max, got {value!r}")


@dataclass(frozen=True)
class TownConfig:
    """Size and look of the town (all lengths in metres).

    ``block_size_m`` is the range of distances between neighbouring street
    centre lines, drawn per grid row/column. ``intersection_jitter_m`` moves
    each intersection by up to that much in x and y, which tilts the streets.
    ``parking_occupancy`` is the probability that a parking slot holds its
    resident car in the town's own (reference) state.
    """

    blocks_x: int = 5
    blocks_y: int = 5
    block_size_m: tuple[float, float] = (70.0, 110.0)
    road_width_m: float = 10.0
    sidewalk_width_m: float = 3.0
    intersection_jitter_m: float = 5.0
    tree_spacing_m: tuple[float, float] = (7.0, 16.0)
    evergreen_fraction: float = 0.25
    pole_spacing_m: float = 30.0
    parking_slot_length_m: float = 6.0
    parking_occupancy: float = 0.6

    def __post_init__(self) -> None:
        for name in ("blocks_x", "blocks_y"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 1 <= value <= 50:
                raise ValueError(f"TownConfig.{name} must be an integer in [1, 50], got {value!r}")
        _check_range("block_size_m", self.block_size_m, low=30.0 - 1e-9)
        _check_range("tree_spacing_m", self.tree_spacing_m, low=1.0 - 1e-9)
        positive = ("road_width_m", "sidewalk_width_m", "pole_spacing_m", "parking_slot_length_m")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"TownConfig.{name} must be a positive number, got {value!r}")
        if not 0 <= self.intersection_jitter_m <= self.block_size_m[0] / 6:
            raise ValueError("TownConfig.intersection_jitter_m must lie in [0, block_size_m[0] / 6], "
                             f"got {self.intersection_jitter_m!r}")
        for name in ("evergreen_fraction", "parking_occupancy"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"TownConfig.{name} must lie in [0, 1], got {value!r}")

    @property
    def curb_offset_m(self) -> float:
        """Distance from a street's centre line to its curb."""
        return self.road_width_m / 2

    @property
    def property_offset_m(self) -> float:
        """Distance from a street's centre line to the back of its sidewalk."""
        return self.road_width_m / 2 + self.sidewalk_width_m


@dataclass(frozen=True, eq=False)
class Town:
    """A generated town: static scene, parking slots and the street graph.

    ``nodes[i, j]`` is the (x, y) of intersection (i, j); ``streets`` lists
    street segments as pairs of flat node ids ``i * (blocks_y + 1) + j``.
    ``parked_cars`` holds one resident car per slot, ``parked_occupied`` says
    which are present in the reference state. ``block_styles[i, j]`` indexes
    :data:`STYLES`.
    """

    config: TownConfig
    seed: int
    nodes: np.ndarray  # (bx+1, by+1, 2)
    streets: np.ndarray  # (E, 2) flat node ids
    static: Scene
    parked_cars: Boxes
    parked_occupied: np.ndarray  # (S,) bool
    block_styles: np.ndarray  # (bx, by) int
    extent: tuple[float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0))  # xmin, ymin, xmax, ymax

    def node_xy(self, i: int, j: int) -> np.ndarray:
        return self.nodes[i, j]

    def street_endpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """(E, 2) start and end points of all street segments."""
        flat = self.nodes.reshape(-1, 2)
        return flat[self.streets[:, 0]], flat[self.streets[:, 1]]

    def reference_scene(self) -> Scene:
        """Static geometry plus the parked cars of the reference state."""
        return Scene(Boxes.concat([self.static.boxes, self.parked_cars.take(self.parked_occupied)]),
                     self.static.cylinders, self.static.ellipsoids, self.static.ground_z)


class _Collector:
    """Accumulates primitives as rows, converted to arrays once at the end."""

    def __init__(self) -> None:
        self.boxes: list[tuple] = []
        self.cylinders: list[tuple] = []
        self.ellipsoids: list[tuple] = []

    def box(self, xy: np.ndarray, z0: float, length: float, width: float, height: float, yaw: float,
            material: Material, density: float = 1.0) -> None:
        self.boxes.append((xy[0], xy[1], z0 + height / 2, length / 2, width / 2, height / 2, yaw, material, density))

    def tree(self, rng: np.random.Generator, xy: np.ndarray, evergreen: bool) -> None:
        if evergreen:  # conifer: low, narrow, tall crown
            trunk_r, crown_base = rng.uniform(0.12, 0.25), rng.uniform(0.8, 1.8)
            r_xy, r_z = rng.uniform(1.2, 2.3), rng.uniform(3.0, 5.5)
        else:
            trunk_r, crown_base = rng.uniform(0.15, 0.4), rng.uniform(2.0, 4.0)
            r_xy, r_z = rng.uniform(1.8, 4.2), rng.uniform(1.8, 3.8)
        crown_z = crown_base + r_z
        self.cylinders.append((xy[0], xy[1], trunk_r, 0.0, crown_z, Material.TRUNK, 1.0))
        stretch = rng.uniform(0.85, 1.15)  # slightly oval crowns
        self.ellipsoids.append((xy[0], xy[1], crown_z, r_xy * stretch, r_xy / stretch, r_z,
                                Material.CONIFER if evergreen else Material.FOLIAGE, 0.9))

    def scene(self) -> Scene:
        b = np.array(self.boxes, dtype=np.float64).reshape(-1, 9)
        c = np.array(self.cylinders, dtype=np.float64).reshape(-1, 7)
        e = np.array(self.ellipsoids, dtype=np.float64).reshape(-1, 8)
        return Scene(
            Boxes(center=b[:, 0:3], half_size=b[:, 3:6], yaw=b[:, 6], material=b[:, 7], density=b[:, 8]),
            Cylinders(center_xy=c[:, 0:2], radius=c[:, 2], z_min=c[:, 3], z_max=c[:, 4], material=c[:, 5],
                      density=c[:, 6]),
            Ellipsoids(center=e[:, 0:3], radii=e[:, 3:6], material=e[:, 6], density=e[:, 7]),
        )


def random_car_dimensions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) length, width, height of cars; about one in seven is a van."""
    van = rng.random(n) < 0.15
    length = np.where(van, rng.uniform(4.8, 6.0, n), rng.uniform(3.7, 4.9, n))
    width = np.where(van, rng.uniform(1.9, 2.1, n), rng.uniform(1.65, 1.95, n))
    height = np.where(van, rng.uniform(1.9, 2.5, n), rng.uniform(1.35, 1.75, n))
    return np.stack([length, width, height], axis=1)


def car_boxes(xy: np.ndarray, yaw: np.ndarray, dims: np.ndarray, material: Material) -> Boxes:
    """Car bodies as boxes from 0.2 m above the ground (wheels not modelled) to ``dims[:, 2]``."""
    clearance = 0.2
    half = np.column_stack([dims[:, 0] / 2, dims[:, 1] / 2, (dims[:, 2] - clearance) / 2])
    center = np.column_stack([xy, clearance + half[:, 2]])
    return Boxes(center=center, half_size=half, yaw=yaw, material=np.full(len(xy), material, dtype=np.uint8))


def _frontage(out: _Collector, rng: np.random.Generator, cfg: TownConfig, start: np.ndarray, end: np.ndarray,
              outward: np.ndarray, style: str, max_depth: float) -> None:
    """Buildings, boundary and front-yard trees on one side of one street segment."""
    params = _STYLE[style]
    direction = (end - start) / np.linalg.norm(end - start)
    length = float(np.linalg.norm(end - start))
    street_yaw = math.atan2(direction[1], direction[0])
    first, last = cfg.property_offset_m + 1.0, length - cfg.property_offset_m - 1.0
    placed: list[tuple[float, float, float]] = []  # (s, offset, radius) of buildings on this side
    s = first + rng.uniform(0, 4)
    while True:
        front = rng.uniform(*params["front"])
        if s + front > last:
            break
        setback = rng.uniform(*params["setback"])
        depth = min(rng.uniform(*params["depth"]), max_depth - setback)
        if depth >= 4.0:
            centre_s, offset = s + front / 2, cfg.property_offset_m + setback + depth / 2
            xy = start + direction * centre_s + outward * offset
            out.box(xy, 0.0, front, depth, rng.uniform(*params["height"]),
                    street_yaw + rng.uniform(-1, 1) * params["yaw_jitter"], Material.BUILDING)
            placed.append((centre_s, offset, 0.5 * math.hypot(front, depth)))
        s += front + rng.uniform(*params["gap"])

    # Boundary along the property line, in runs with driveway/entrance gaps.
    boundary_p = np.array(params["boundary"])
    kind = rng.choice(4, p=np.append(boundary_p, 1 - boundary_p.sum()))
    if kind < 3:
        material, density, height, thickness = [
            (Material.FENCE, 0.5, rng.uniform(1.0, 1.8), 0.06),
            (Material.WALL, 1.0, rng.uniform(0.8, 2.5), 0.3),
            (Material.CONIFER, 0.85, rng.uniform(1.0, 1.9), 0.8),
        ][kind]
        s = first
        while s < last - 2:
            run = min(rng.uniform(8, 25), last - s)
            xy = start + direction * (s + run / 2) + outward * (cfg.property_offset_m + thickness / 2 + 0.2)
            out.box(xy, 0.0, run, thickness, height, street_yaw, material, density)
            s += run + rng.uniform(2.5, 5)

    # Trees behind the property line where there is room (front yards, park).
    n_yard_trees = int(rng.poisson(length / 25 if style in ("residential", "park") else length / 120))
    for _ in range(n_yard_trees):
        s_tree = rng.uniform(first, max(first, last))
        offset = cfg.property_offset_m + rng.uniform(2.5, max(3.0, max_depth - 2))
        if all(abs(s_tree - ps) > pr + 3 or abs(offset - po) > pr + 3 for ps, po, pr in placed):
            out.tree(rng, start + direction * s_tree + outward * offset, rng.random() < cfg.evergreen_fraction)


def _street_side(out: _Collector, rng: np.random.Generator, cfg: TownConfig, start: np.ndarray, end: np.ndarray,
                 outward: np.ndarray, tree_p: float, slots: list[tuple]) -> None:
    """Sidewalk trees, lamp posts and parking slots on one side of a street segment."""
    direction = (end - start) / np.linalg.norm(end - start)
    length = float(np.linalg.norm(end - start))
    yaw = math.atan2(direction[1], direction[0])
    first, last = cfg.property_offset_m + 1.5, length - cfg.property_offset_m - 1.5
    poles_s = np.arange(first + rng.uniform(0, cfg.pole_spacing_m / 2), last, cfg.pole_spacing_m)
    for s in poles_s:
        base = start + direction * s + outward * (cfg.curb_offset_m + 0.5)
        height = rng.uniform(6.0, 9.0)
        out.cylinders.append((base[0], base[1], rng.uniform(0.09, 0.15), 0.0, height, Material.POLE, 1.0))
        arm = 1.8  # lamp arm reaching over the road
        out.box(base - outward * arm / 2, height - 0.25, 0.25, arm, 0.2, yaw, Material.POLE)
    s = first + rng.uniform(0, 3)
    while s < last:
        if rng.random() < tree_p and np.all(np.abs(poles_s - s) > 2.5):
            xy = start + direction * s + outward * (cfg.curb_offset_m + cfg.sidewalk_width_m * 0.45)
            out.tree(rng, xy, rng.random() < cfg.evergreen_fraction)
        s += rng.uniform(*cfg.tree_spacing_m)
    # Parking slots: kept clear of the intersections.
    slot = cfg.parking_slot_length_m
    for s in np.arange(first + slot, last - slot, slot):
        xy = start + direction * (s + slot / 2) + outward * (cfg.curb_offset_m - 1.1)
        slots.append((xy[0], xy[1], yaw + rng.normal(0, 0.03)))


def _park_interior(out: _Collector, rng: np.random.Generator, cfg: TownConfig, corners: np.ndarray) -> None:
    """Scattered trees (and a pavilion now and then) inside a park block."""
    inset = cfg.property_offset_m + 3.0
    centre = corners.mean(axis=0)
    lo, hi = corners.min(axis=0) + inset, corners.max(axis=0) - inset
    n_trees = int(rng.poisson(np.prod(np.maximum(hi - lo, 0)) / 180))
    for xy in rng.uniform(lo, hi, size=(n_trees, 2)):
        if np.linalg.norm(xy - centre) > 6:
            out.tree(rng, xy, rng.random() < cfg.evergreen_fraction * 1.5)
    if rng.random() < 0.5:
        out.box(centre, 0.0, rng.uniform(5, 10), rng.uniform(5, 10), rng.uniform(3, 5), rng.uniform(0, math.pi),
                Material.BUILDING)


def generate_town(config: TownConfig | None = None, seed: int = 0) -> Town:
    """Generate the town for ``(config, seed)``; same inputs, same town."""
    cfg = config or TownConfig()
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng([int(seed), 0x70E1])
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*cfg.block_size_m, cfg.blocks_x))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*cfg.block_size_m, cfg.blocks_y))])
    nodes = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    nodes = nodes + rng.uniform(-cfg.intersection_jitter_m, cfg.intersection_jitter_m, nodes.shape)
    nodes -= nodes.reshape(-1, 2).mean(axis=0)  # town centred on the origin
    styles = rng.choice(len(STYLES), size=(cfg.blocks_x, cfg.blocks_y), p=_STYLE_WEIGHTS)
    ny = cfg.blocks_y + 1

    out = _Collector()
    slots: list[tuple] = []
    streets: list[tuple[int, int]] = []
    for i in range(cfg.blocks_x + 1):
        for j in range(cfg.blocks_y + 1):
            for di, dj in ((1, 0), (0, 1)):
                if i + di > cfg.blocks_x or j + dj > cfg.blocks_y:
                    continue
                streets.append((i * ny + j, (i + di) * ny + j + dj))
                start, end = nodes[i, j], nodes[i + di, j + dj]
                direction = (end - start) / np.linalg.norm(end - start)
                left = np.array([-direction[1], direction[0]])
                # Blocks on the left / right of the segment (None past the town border).
                if di:  # along x: left is +y
                    sides = ((left, (i, j) if j < cfg.blocks_y else None), (-left, (i, j - 1) if j > 0 else None))
                else:  # along y: left is -x
                    sides = ((left, (i - 1, j) if i > 0 else None), (-left, (i, j) if i < cfg.blocks_x else None))
                for outward, block in sides:
                    if block is None:  # outskirts: never a park, depth not bounded by a block
                        style, max_depth = STYLES[rng.choice(3)], 30.0
                    else:
                        style = STYLES[styles[block]]
                        c = nodes[block[0]:block[0] + 2, block[1]:block[1] + 2].reshape(-1, 2)
                        max_depth = 0.5 * float(np.min(c.max(axis=0) - c.min(axis=0))) - cfg.property_offset_m - 3
                    _frontage(out, rng, cfg, start, end, outward, style, max_depth)
                    _street_side(out, rng, cfg, start, end, outward, _STYLE[style]["tree_p"], slots)
    for bi in range(cfg.blocks_x):
        for bj in range(cfg.blocks_y):
            if STYLES[styles[bi, bj]] == "park":
                _park_interior(out, rng, cfg, nodes[bi:bi + 2, bj:bj + 2].reshape(-1, 2))

    slot_array = np.array(slots, dtype=np.float64).reshape(-1, 3)
    dims = random_car_dimensions(rng, len(slot_array))
    parked = car_boxes(slot_array[:, :2], slot_array[:, 2], dims, Material.PARKED_CAR)
    occupied = rng.random(len(slot_array)) < cfg.parking_occupancy
    flat = nodes.reshape(-1, 2)
    margin = 60.0
    extent = (float(flat[:, 0].min() - margin), float(flat[:, 1].min() - margin),
              float(flat[:, 0].max() + margin), float(flat[:, 1].max() + margin))
    return Town(config=cfg, seed=int(seed), nodes=nodes, streets=np.array(streets, dtype=np.int64),
                static=out.scene(), parked_cars=parked, parked_occupied=occupied, block_styles=styles,
                extent=extent)
