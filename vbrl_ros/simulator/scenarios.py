"""Long-term change scenarios: season, weather, traffic and parked cars per run.

A :class:`Scenario` is rendered on an unchanged town; what differs between
runs is what changes in reality between sessions:

* **season** -- deciduous crown density (a ray crossing a crown is returned
  with that probability): dense in summer, bare branches in winter. Evergreen
  crowns and hedges stay.
* **weather** -- :class:`~.lidar.WeatherEffects`: near clutter returns from
  fog droplets / snowflakes / rain, random dropouts, extinction, extra range
  noise; snow also covers the ground (much brighter returns).
* **dynamics** -- moving cars on the streets and pedestrians on the sidewalks,
  placed per run seed and moving with time along their street.
* **parked cars** -- each parking slot is re-rolled with probability
  ``parked_turnover``: a different car, or none.

Named presets are in :data:`SCENARIO_PRESETS`; ``Scenario.from_name`` also
accepts any free ``<season>_<weather>`` combination.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from .geometry import Boxes, Cylinders, Material
from .lidar import WeatherEffects
from .town import Town, car_boxes, random_car_dimensions

SEASONS = ("spring", "summer", "autumn", "winter")
# Probability that a ray crossing a deciduous crown is returned.
FOLIAGE_DENSITY = {"spring": 0.6, "summer": 0.9, "autumn": 0.45, "winter": 0.06}

WEATHER = {
    "clear": WeatherEffects(),
    "rain": WeatherEffects(clutter_prob=0.004, clutter_scale_m=4.0, clutter_intensity=(0.0, 0.08),
                           extinction_per_m=0.002, dropout_prob=0.03, extra_noise_m=0.01),
    "fog": WeatherEffects(clutter_prob=0.06, clutter_scale_m=3.0, clutter_intensity=(0.0, 0.04),
                          extinction_per_m=0.012, dropout_prob=0.02, extra_noise_m=0.04),
    "snow": WeatherEffects(clutter_prob=0.04, clutter_scale_m=4.0, clutter_intensity=(0.05, 0.45),
                           extinction_per_m=0.004, dropout_prob=0.05, extra_noise_m=0.03),
}
_SNOW_ON_GROUND = {"snow"}


@dataclass(frozen=True)
class Scenario:
    """A session's conditions. ``name`` defaults to ``<season>_<weather>``.

    Densities are per kilometre of street (both directions / sidewalks
    together). ``parked_turnover`` is the fraction of parking slots whose
    state is re-drawn for the run (0: exactly the town's reference parking).
    """

    season: str = "summer"
    weather: str = "clear"
    moving_cars_per_km: float = 8.0
    pedestrians_per_km: float = 20.0
    parked_turnover: float = 0.4
    name: str = ""

    def __post_init__(self) -> None:
        if self.season not in SEASONS:
            raise ValueError(f"Scenario.season must be one of {SEASONS}, got {self.season!r}")
        if self.weather not in WEATHER:
            raise ValueError(f"Scenario.weather must be one of {tuple(WEATHER)}, got {self.weather!r}")
        for field_name in ("moving_cars_per_km", "pedestrians_per_km"):
            value = getattr(self, field_name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or not 0 <= value <= 500:
                raise ValueError(f"Scenario.{field_name} must lie in [0, 500], got {value!r}")
        if not 0.0 <= self.parked_turnover <= 1.0:
            raise ValueError(f"Scenario.parked_turnover must lie in [0, 1], got {self.parked_turnover!r}")
        if not self.name:
            object.__setattr__(self, "name", f"{self.season}_{self.weather}")
        if not all(c.isalnum() or c in "_-" for c in self.name):
            raise ValueError(f"Scenario.name may hold only letters, digits, '_' and '-', got {self.name!r}")

    @classmethod
    def from_name(cls, name: str) -> Scenario:
        """A preset (:data:`SCENARIO_PRESETS`) or a free ``<season>_<weather>`` combination."""
        if name in SCENARIO_PRESETS:
            return SCENARIO_PRESETS[name]
        season, _, weather = name.partition("_")
        if season in SEASONS and weather in WEATHER:
            return cls(season=season, weather=weather)
        raise ValueError(f"unknown scenario {name!r}: use a preset ({', '.join(SCENARIO_PRESETS)}) "
                         f"or <season>_<weather> with season in {SEASONS} and weather in {tuple(WEATHER)}")

    @property
    def weather_effects(self) -> WeatherEffects:
        return WEATHER[self.weather]

    @property
    def foliage_density(self) -> float:
        return FOLIAGE_DENSITY[self.season]

    @property
    def snow_on_ground(self) -> bool:
        return self.weather in _SNOW_ON_GROUND

    @property
    def seed_salt(self) -> int:
        """Stable across processes (unlike ``hash``): mixes the scenario into run seeds."""
        return zlib.crc32(self.name.encode())


SCENARIO_PRESETS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("summer", "clear"),
        Scenario("summer", "rain"),
        Scenario("spring", "rain"),
        Scenario("autumn", "clear"),
        Scenario("autumn", "fog"),
        Scenario("winter", "clear"),
        Scenario("winter", "snow"),
        Scenario("winter", "fog"),
        # Reference condition for geometry checks: no traffic, reference parking.
        Scenario("summer", "clear", moving_cars_per_km=0.0, pedestrians_per_km=0.0, parked_turnover=0.0,
                 name="static"),
    )
}


@dataclass(frozen=True, eq=False)
class MovingAgents:
    """Cars and pedestrians moving at constant speed along street segments.

    Agent k moves along the segment from ``start[k]`` in ``direction[k]``,
    ``lateral[k]`` metres to its left, within [margin, length - margin] of the
    segment and reappears at the other end (no collision model).
    """

    start: np.ndarray  # (n, 2)
    direction: np.ndarray  # (n, 2) unit
    length: np.ndarray  # (n,) usable length of the segment
    margin: np.ndarray  # (n,)
    lateral: np.ndarray  # (n,) signed offset to the left of ``direction``
    s0: np.ndarray  # (n,) position along the usable part at t = 0
    speed: np.ndarray  # (n,) signed, m/s
    size: np.ndarray  # (n, 3) cars: length, width, height; pedestrians: radius, height, 0

    def positions(self, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) positions and (n,) yaw at ``time_s``."""
        s = self.margin + np.mod(self.s0 + self.speed * time_s, self.length)
        left = np.stack([-self.direction[:, 1], self.direction[:, 0]], axis=1)
        xy = self.start + self.direction * s[:, None] + left * self.lateral[:, None]
        yaw = np.arctan2(self.direction[:, 1], self.direction[:, 0]) + np.where(self.speed < 0, math.pi, 0.0)
        return xy, yaw


def _agents_on_streets(town: Town, rng: np.random.Generator, per_km: float, margin_m: float,
                       lateral: tuple[float, float], speed: tuple[float, float]) -> tuple:
    """Street-segment sampling shared by cars and pedestrians (proportional to length)."""
    a, b = town.street_endpoints()
    seg = b - a
    seg_len = np.linalg.norm(seg, axis=1)
    count = int(rng.poisson(per_km * seg_len.sum() / 1000.0))
    street = rng.choice(len(a), size=count, p=seg_len / seg_len.sum())
    usable = np.maximum(seg_len[street] - 2 * margin_m, 1.0)
    forward = rng.random(count) < 0.5
    magnitude = rng.uniform(*lateral, count)
    # Keep to the right of the direction of travel: left offset negative when moving forward.
    lateral_offset = np.where(forward, -magnitude, magnitude)
    velocity = rng.uniform(*speed, count) * np.where(forward, 1.0, -1.0)
    return (a[street], seg[street] / seg_len[street, None], usable, np.full(count, margin_m), lateral_offset,
            rng.uniform(0, 1, count) * usable, velocity, count)


def sample_moving_cars(town: Town, scenario: Scenario, rng: np.random.Generator) -> MovingAgents:
    cfg = town.config
    *geometry, count = _agents_on_streets(town, rng, scenario.moving_cars_per_km, cfg.property_offset_m,
                                          lateral=(1.4, 1.9), speed=(4.0, 12.0))
    return MovingAgents(*geometry, size=random_car_dimensions(rng, count))


def sample_pedestrians(town: Town, scenario: Scenario, rng: np.random.Generator) -> MovingAgents:
    cfg = town.config
    inner, outer = cfg.curb_offset_m + 0.4, cfg.property_offset_m - 0.4
    *geometry, count = _agents_on_streets(town, rng, scenario.pedestrians_per_km, cfg.property_offset_m,
                                          lateral=(inner, outer), speed=(0.7, 1.7))
    size = np.column_stack([rng.uniform(0.22, 0.35, count), rng.uniform(1.5, 1.95, count), np.zeros(count)])
    return MovingAgents(*geometry, size=size)


def parked_cars_for_run(town: Town, scenario: Scenario, rng: np.random.Generator) -> Boxes:
    """The town's parking with a ``parked_turnover`` fraction of slots re-drawn."""
    slots = town.parked_cars
    n = len(slots)
    redraw = rng.random(n) < scenario.parked_turnover
    occupied = np.where(redraw, rng.random(n) < town.config.parking_occupancy, town.parked_occupied)
    new_dims = random_car_dimensions(rng, n)
    fresh = car_boxes(slots.center[:, :2], slots.yaw, new_dims, Material.PARKED_CAR)
    center = np.where(redraw[:, None], fresh.center, slots.center)
    half = np.where(redraw[:, None], fresh.half_size, slots.half_size)
    keep = occupied
    return Boxes(center=center[keep], half_size=half[keep], yaw=slots.yaw[keep],
                 material=np.full(int(keep.sum()), Material.PARKED_CAR, dtype=np.uint8))


def agents_at(cars: MovingAgents, pedestrians: MovingAgents, time_s: float, sensor_xy: np.ndarray,
              clearance_m: float = 3.5) -> tuple[Boxes, Cylinders]:
    """Primitives of the moving agents at ``time_s``, minus any overlapping the sensor vehicle."""
    car_xy, car_yaw = cars.positions(time_s)
    keep = np.linalg.norm(car_xy - sensor_xy, axis=1) > clearance_m
    car_prims = car_boxes(car_xy[keep], car_yaw[keep], cars.size[keep], Material.MOVING_CAR)
    ped_xy, _ = pedestrians.positions(time_s)
    keep = np.linalg.norm(ped_xy - sensor_xy, axis=1) > 1.5
    radius, height = pedestrians.size[keep, 0], pedestrians.size[keep, 1]
    peds = Cylinders(center_xy=ped_xy[keep], radius=radius, z_min=np.zeros(len(radius)), z_max=height,
                     material=np.full(len(radius), Material.PEDESTRIAN, dtype=np.uint8))
    return car_prims, peds
