"""A drive through the town: several loops with same- and opposite-direction revisits.

The route starts at a *home* intersection and drives a sequence of rectangular
loops around it, each with a corner at home, chosen from four templates that
chain without U-turns:

=====  =========================  ==========================================
loop   rectangle (from home)      moves
=====  =========================  ==========================================
A      east / north quadrant      E w, N h, W w, S h   (counter-clockwise)
B      east / south quadrant      S h, E w, N h, W w   (counter-clockwise)
C      east / north quadrant      N h, E w, S h, W w   (clockwise)
D      west / north quadrant      W w, N h, E w, S h   (clockwise)
=====  =========================  ==========================================

A then B drives the home->east street both ways; C drives A's rectangle the
other way round; D shares the home->north street with A (same direction) and C
(opposite). Sizes (w, h blocks) vary per loop, so later loops also reach places
never seen before -- real drives have queries without a revisit too.

The polyline through the intersections is shifted ``lane_offset_m`` to the
right of travel (so opposite passes are ``2 * lane_offset_m`` apart), sampled
densely, Gaussian-smoothed (rounded corners, smooth yaw) and driven at
``speed_mps``, slowing where the lateral acceleration would exceed
``max_lateral_accel``. Scans are taken every ``spacing_m`` metres or at
``rate_hz`` -- exactly one of the two.

No driver holds a lane to the centimetre, and two sessions of the same route
differ sideways by a metre or more. ``lane_wander_m`` moves the smoothed line
sideways by ``lane_wander_m * tanh(g(s))``, where ``g`` is a unit-variance
Gaussian process over the path length ``s`` with a correlation length of
``WANDER_CORRELATION_M`` drawn from ``lane_wander_seed``: smooth, within
the amplitude, and different for every seed. The poses follow the wandering line.

Nor does a sensor keep its tilt: a two-wheeled robot pitches as it brakes, a rover rolls over
kerbs and grass, a hand-held sensor sways with the walk. ``sensor_sway_deg`` adds to the
mount's roll and pitch two such processes over the path, each of that standard deviation
(clipped at three), correlated over ``SWAY_CORRELATION_M`` and drawn from
``sensor_sway_seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from vbrl_ros.datasets.mount_tilt import MAX_MOUNT_TILT_DEG, mount_rotation

from .town import Town

# (quadrant sign x, quadrant sign y, first axis) of the loop templates A-D.
_TEMPLATES = (("A", 1, 1, "x"), ("B", 1, -1, "y"), ("C", 1, 1, "y"), ("D", -1, 1, "x"))
# Loop sizes (w, h) in blocks, cycled; clipped to the room around home.
_SIZES = ((2, 1), (2, 1), (1, 1), (1, 2), (2, 2), (1, 1), (2, 1), (1, 2))
_DENSE_STEP_M = 0.25
#: Path length over which the lateral wander stays correlated (exp(-d^2 / 2 l^2) at distance d).
WANDER_CORRELATION_M = 30.0
#: Largest wander amplitude: beyond it the inner side of a rounded corner tightens towards a cusp.
MAX_LANE_WANDER_M = 3.0
_WANDER_SALT = 0x1A7E  # the wander's own random stream, apart from the town's and the run's
#: Path length over which a sensor's sway stays correlated.
SWAY_CORRELATION_M = 5.0
#: Largest sway (standard deviation, degrees).
MAX_SENSOR_SWAY_DEG = 10.0
_SWAY_SALT = 0x5A7


def _positive(name: str, value: float | None, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"RouteConfig.{name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class RouteConfig:
    """How the route is driven and sampled.

    Exactly one of ``spacing_m`` (one scan every so many metres of path) and
    ``rate_hz`` (scans at a fixed rate while driving at ``speed_mps``) is set.
    ``sample_offset_m`` shifts where along the path the scans are taken (in
    ``[0, spacing)`` in spacing mode, or the time offset ``sample_offset_m /
    speed_mps`` in rate mode), so two sessions of the same route do not scan
    from exactly the same spots, as real sessions never do.
    ``home`` is the start intersection (default: the grid centre).
    ``sensor_height_m`` is the LiDAR origin above the ground: the poses are
    T_world_lidar, z-up, yaw following the path. ``sensor_roll_deg`` and
    ``sensor_pitch_deg`` tilt the sensor on its mount (a hand-held sensor, or
    one mounted askew), fixed for the whole drive and included in the poses:
    R = Rz(yaw) Ry(pitch) Rx(roll), right-handed about the sensor's x (forward)
    and y (left) axes, so a positive roll lifts the left side and a positive
    pitch tips the front down. Each lies in [-45, 45] degrees. ``sensor_sway_deg`` (at most
    10, with the mount's tilt within 45 at three of it) sways both about the mount from
    ``sensor_sway_seed`` (module docstring).
    ``lane_wander_m`` (at most 3 m) is the amplitude of a smooth lateral wander
    of the driven line about its lane, drawn from ``lane_wander_seed``; give
    sessions different seeds so they drive different lines (module docstring).
    Parked cars begin about 3 m right of a street's centre line, so
    ``lane_offset_m + lane_wander_m`` beyond ~2.5 m can put the sensor inside one.
    """

    loops: int = 4
    spacing_m: float | None = 1.0
    rate_hz: float | None = None
    speed_mps: float = 8.0
    max_lateral_accel: float = 2.0
    lane_offset_m: float = 1.0
    lane_wander_m: float = 0.0
    lane_wander_seed: int = 0
    corner_smoothing_m: float = 5.0
    sensor_height_m: float = 1.8
    sensor_roll_deg: float = 0.0
    sensor_pitch_deg: float = 0.0
    sensor_sway_deg: float = 0.0
    sensor_sway_seed: int = 0
    sample_offset_m: float = 0.0
    home: tuple[int, int] | None = None
    max_scans: int | None = None
    start_stamp: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.loops, int) or not 1 <= self.loops <= 64:
            raise ValueError(f"RouteConfig.loops must be an integer in [1, 64], got {self.loops!r}")
        if (self.spacing_m is None) == (self.rate_hz is None):
            raise ValueError("RouteConfig.spacing_m / rate_hz: set exactly one of them "
                             f"(got spacing_m={self.spacing_m!r}, rate_hz={self.rate_hz!r})")
        _positive("spacing_m", self.spacing_m, allow_none=True)
        _positive("rate_hz", self.rate_hz, allow_none=True)
        for name in ("speed_mps", "max_lateral_accel", "corner_smoothing_m", "sensor_height_m"):
            _positive(name, getattr(self, name))
        for name in ("sensor_roll_deg", "sensor_pitch_deg"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not -MAX_MOUNT_TILT_DEG <= value <= MAX_MOUNT_TILT_DEG:
                raise ValueError(f"RouteConfig.{name} must lie in [-{MAX_MOUNT_TILT_DEG:g}, "
                                 f"{MAX_MOUNT_TILT_DEG:g}] degrees, got {value!r}")
        sway = self.sensor_sway_deg
        if not isinstance(sway, (int, float)) or not 0 <= sway <= MAX_SENSOR_SWAY_DEG or (
                max(abs(self.sensor_roll_deg), abs(self.sensor_pitch_deg)) + 3 * sway > MAX_MOUNT_TILT_DEG):
            raise ValueError(f"RouteConfig.sensor_sway_deg must lie in [0, {MAX_SENSOR_SWAY_DEG:g}] degrees, "
                             f"with the mount's roll and pitch plus three of it within {MAX_MOUNT_TILT_DEG:g}, "
                             f"got {sway!r}")
        if not isinstance(self.sensor_sway_seed, (int, np.integer)) or self.sensor_sway_seed < 0:
            raise ValueError(f"RouteConfig.sensor_sway_seed must be a non-negative integer, "
                             f"got {self.sensor_sway_seed!r}")
        if not isinstance(self.lane_offset_m, (int, float)) or not 0 <= self.lane_offset_m <= 5:
            raise ValueError(f"RouteConfig.lane_offset_m must lie in [0, 5], got {self.lane_offset_m!r}")
        if not isinstance(self.lane_wander_m, (int, float)) or not 0 <= self.lane_wander_m <= MAX_LANE_WANDER_M:
            raise ValueError(f"RouteConfig.lane_wander_m must lie in [0, {MAX_LANE_WANDER_M:g}], "
                             f"got {self.lane_wander_m!r}")
        if not isinstance(self.lane_wander_seed, (int, np.integer)) or self.lane_wander_seed < 0:
            raise ValueError(f"RouteConfig.lane_wander_seed must be a non-negative integer, "
                             f"got {self.lane_wander_seed!r}")
        if not isinstance(self.sample_offset_m, (int, float)) or not 0 <= self.sample_offset_m < 1e4:
            raise ValueError(f"RouteConfig.sample_offset_m must be a non-negative number, got {self.sample_offset_m!r}")
        if self.max_scans is not None and (not isinstance(self.max_scans, int) or self.max_scans < 1):
            raise ValueError(f"RouteConfig.max_scans must be a positive integer or None, got {self.max_scans!r}")
        if not math.isfinite(self.start_stamp) or self.start_stamp < 0:
            raise ValueError(f"RouteConfig.start_stamp must be a non-negative number, got {self.start_stamp!r}")


@dataclass(frozen=True, eq=False)
class Route:
    """Sampled route: ``poses[k]`` is T_world_lidar of scan k taken at ``stamps[k]`` (s)."""

    poses: np.ndarray  # (n, 4, 4)
    stamps: np.ndarray  # (n,) seconds
    arc_length: np.ndarray  # (n,) metres from the start
    loop_index: np.ndarray  # (n,) which loop of ``loop_names`` each scan belongs to
    loop_names: tuple[str, ...]  # template letter and size per loop, e.g. "A2x1"
    intersections: tuple[tuple[int, int], ...]  # grid nodes visited, in order

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def yaw(self) -> np.ndarray:
        return np.arctan2(self.poses[:, 1, 0], self.poses[:, 0, 0])

    @property
    def length_m(self) -> float:
        return float(self.arc_length[-1]) if len(self) else 0.0


def _loop_nodes(town: Town, config: RouteConfig) -> tuple[list[tuple[int, int]], list[int], list[str]]:
    """Grid nodes of the whole drive, the loop each node arrives in, loop names."""
    n_i, n_j = town.nodes.shape[0] - 1, town.nodes.shape[1] - 1
    home = config.home if config.home is not None else (n_i // 2, n_j // 2)
    if not (0 <= home[0] <= n_i and 0 <= home[1] <= n_j):
        raise ValueError(f"RouteConfig.home must be a grid node within (0..{n_i}, 0..{n_j}), got {home!r}")
    room = {(1, "x"): n_i - home[0], (-1, "x"): home[0], (1, "y"): n_j - home[1], (-1, "y"): home[1]}
    path, owner, names = [tuple(home)], [0], []
    last_move: tuple[str, int] | None = None
    template_cursor = 0
    for loop in range(config.loops):
        for attempt in range(len(_TEMPLATES)):
            name, sx, sy, first = _TEMPLATES[(template_cursor + attempt) % len(_TEMPLATES)]
            want_w, want_h = _SIZES[loop % len(_SIZES)]
            w, h = min(want_w, room[(sx, "x")]), min(want_h, room[(sy, "y")])
            legs = [("x", sx, w), ("y", sy, h), ("x", -sx, w), ("y", -sy, h)]
            if first == "y":
                legs = [legs[1], legs[0], legs[3], legs[2]]
            u_turn = last_move is not None and legs[0][0] == last_move[0] and legs[0][1] == -last_move[1]
            if w > 0 and h > 0 and not u_turn:
                break
        else:
            raise ValueError("RouteConfig.home leaves no room for a loop: the town needs a block next to home")
        template_cursor = (template_cursor + attempt + 1) % len(_TEMPLATES)
        names.append(f"{name}{w}x{h}")
        i, j = path[-1]
        for axis, sign, blocks in legs:
            for _ in range(blocks):
                i, j = (i + sign, j) if axis == "x" else (i, j + sign)
                path.append((i, j))
                owner.append(loop)
        last_move = (legs[-1][0], legs[-1][1])
    return path, owner, names


def _lane_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """Shift a polyline ``offset`` to the right of travel, mitring the joints."""
    direction = np.diff(points, axis=0)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    right = np.stack([direction[:, 1], -direction[:, 0]], axis=1)
    shifted = [points[0] + offset * right[0]]
    for k in range(1, len(points) - 1):
        # Miter: the offset point is at offset / cos(half turn) along the bisector.
        bisector = right[k - 1] + right[k]
        norm = np.linalg.norm(bisector)
        if norm < 1e-6:  # a U-turn never happens on our templates; keep it finite anyway
            shifted.append(points[k] + offset * right[k])
            continue
        bisector /= norm
        shifted.append(points[k] + bisector * offset / max(float(bisector @ right[k]), 0.2))
    shifted.append(points[-1] + offset * right[-1])
    return np.array(shifted)


def _smooth_process(count: int, correlation_m: float, rng: np.random.Generator) -> np.ndarray:
    """A unit-variance Gaussian process over ``count`` dense path points, correlated over
    ``correlation_m`` (exp(-d^2 / 2 l^2) at distance d)."""
    sigma = correlation_m / math.sqrt(2.0) / _DENSE_STEP_M
    process = gaussian_filter1d(rng.standard_normal(count), sigma, mode="reflect")
    # White noise smoothed by a unit-area Gaussian of width sigma has variance 1 / (2 sqrt(pi) sigma).
    return process * math.sqrt(2.0 * math.sqrt(math.pi) * sigma)


def _sway(s: np.ndarray, sway_deg: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch) in degrees added to the mount's at the dense path points ``s``."""
    rng = np.random.default_rng([seed, _SWAY_SALT])
    roll, pitch = (sway_deg * np.clip(_smooth_process(len(s), SWAY_CORRELATION_M, rng), -3.0, 3.0)
                   for _ in range(2))
    return roll, pitch


def _wander(xy: np.ndarray, amplitude: float, seed: int) -> np.ndarray:
    """Move the dense path ``xy`` (points ``_DENSE_STEP_M`` apart) sideways by the lateral wander."""
    process = _smooth_process(len(xy), WANDER_CORRELATION_M, np.random.default_rng([seed, _WANDER_SALT]))
    tangent = np.gradient(xy, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    right = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    return xy + (amplitude * np.tanh(process))[:, None] * right


def make_route(town: Town, config: RouteConfig | None = None) -> Route:
    """Sample the drive of ``config`` through ``town`` (deterministic: the wander is seeded by the config)."""
    cfg = config or RouteConfig()
    nodes, owner, names = _loop_nodes(town, cfg)
    corners = np.array([town.nodes[i, j] for i, j in nodes])
    lane = _lane_polyline(corners, cfg.lane_offset_m)

    # Dense resampling, then smoothing along the path to round the corners.
    seg_len = np.linalg.norm(np.diff(lane, axis=0), axis=1)
    s_corner = np.concatenate([[0.0], np.cumsum(seg_len)])
    s_dense = np.arange(0.0, s_corner[-1], _DENSE_STEP_M)
    xy = np.stack([np.interp(s_dense, s_corner, lane[:, 0]), np.interp(s_dense, s_corner, lane[:, 1])], axis=1)
    xy = gaussian_filter1d(xy, cfg.corner_smoothing_m / _DENSE_STEP_M, axis=0, mode="nearest")
    if cfg.lane_wander_m > 0:  # without wander the line stays bit-identical
        xy = _wander(xy, cfg.lane_wander_m, cfg.lane_wander_seed)
    dense_loop = np.searchsorted(s_corner, s_dense, side="right") - 1
    dense_loop = np.asarray(owner)[np.clip(dense_loop + 1, 0, len(owner) - 1)]

    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    tangent = np.gradient(xy, axis=0)
    yaw = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    curvature = np.abs(np.gradient(yaw) / np.maximum(np.gradient(s), 1e-9))
    speed = np.minimum(cfg.speed_mps, np.sqrt(cfg.max_lateral_accel / np.maximum(curvature, 1e-9)))
    # Brake before / accelerate after corners instead of jumping between speeds.
    speed = np.maximum(gaussian_filter1d(speed, 4.0 / _DENSE_STEP_M, mode="nearest"), 0.5)
    time = np.concatenate([[0.0], np.cumsum(step / (0.5 * (speed[1:] + speed[:-1])))])

    if cfg.spacing_m is not None:
        s_samples = np.arange(cfg.sample_offset_m % cfg.spacing_m, s[-1], cfg.spacing_m)
    else:
        t_offset = (cfg.sample_offset_m / cfg.speed_mps) % (1.0 / cfg.rate_hz)
        s_samples = np.interp(np.arange(t_offset, time[-1], 1.0 / cfg.rate_hz), time, s)
    if cfg.max_scans is not None:
        s_samples = s_samples[: cfg.max_scans]
    x, y = np.interp(s_samples, s, xy[:, 0]), np.interp(s_samples, s, xy[:, 1])
    heading = np.interp(s_samples, s, yaw)
    n = len(s_samples)
    poses = np.zeros((n, 4, 4))
    poses[:, 0, 0] = poses[:, 1, 1] = np.cos(heading)
    poses[:, 1, 0] = np.sin(heading)
    poses[:, 0, 1] = -np.sin(heading)
    poses[:, 2, 2] = poses[:, 3, 3] = 1.0
    if cfg.sensor_sway_deg > 0:
        roll, pitch = _sway(s, cfg.sensor_sway_deg, cfg.sensor_sway_seed)
        for i, (r, p) in enumerate(zip(np.interp(s_samples, s, roll), np.interp(s_samples, s, pitch))):
            poses[i, :3, :3] = poses[i, :3, :3] @ mount_rotation(cfg.sensor_roll_deg + r, cfg.sensor_pitch_deg + p)
    elif cfg.sensor_roll_deg or cfg.sensor_pitch_deg:  # untilted poses stay exactly yaw-only
        poses[:, :3, :3] = poses[:, :3, :3] @ mount_rotation(cfg.sensor_roll_deg, cfg.sensor_pitch_deg)
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = x, y, cfg.sensor_height_m
    loop_of_sample = dense_loop[np.clip(np.searchsorted(s, s_samples), 0, len(s) - 1)]
    return Route(poses=poses, stamps=cfg.start_stamp + np.interp(s_samples, s, time), arc_length=s_samples,
                 loop_index=loop_of_sample.astype(np.int64), loop_names=tuple(names),
                 intersections=tuple(nodes))
