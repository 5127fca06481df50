"""A simulated session: one scenario driven along a route through a town.

Scans are rendered lazily and are random-access: ``run.scan(i)`` is the same
array whether scans are read in order or not, because every scan draws its
noise from its own generator seeded by ``(run seed, scenario, i)``. Run-level
randomness (parked cars, traffic) comes from ``(run seed, scenario)``. So the
same ``(town seed, run seed, scenario)`` gives bit-identical scans. A
:class:`~.keyframes.KeyframeFilter` turns each rendered scan into the sparse
keyframe a SLAM front-end would publish; it draws no randomness.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np

from .geometry import Boxes, Cylinders, Ellipsoids, Material
from .keyframes import KeyframeFilter
from .scene import Scene
from .lidar import LidarConfig, render_scan
from .route import Route
from .scenarios import (Scenario, agents_at, parked_cars_for_run, sample_moving_cars,
                        sample_pedestrians)
from .town import Town


@dataclass(frozen=True, eq=False)
class Scan:
    """One rendered scan.

    ``points``: (N, 4) float32 x, y, z, intensity in the LiDAR frame, intensity
    in [0, 1], only rays that returned. ``labels``: (N,) uint8
    :class:`~.geometry.Material` per point (ground truth, not a sensor
    output). ``rings``: (N,) uint16 beam index (0 = lowest beam).
    ``pose``: T_world_lidar (4, 4). ``stamp``: seconds.
    """

    index: int
    stamp: float
    pose: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    rings: np.ndarray

    def points_world(self) -> np.ndarray:
        """(N, 3) point positions in the world frame."""
        xyz, rotation = self.points[:, :3].astype(np.float64), self.pose[:3, :3]
        # Column-wise product: (N, 3) @ (3, 3) through BLAS is pathologically slow on some builds.
        return xyz[:, 0:1] * rotation[:, 0] + xyz[:, 1:2] * rotation[:, 1] + xyz[:, 2:3] * rotation[:, 2] + self.pose[:3, 3]


def _seasonal_crowns(ellipsoids: Ellipsoids, foliage_density: float) -> Ellipsoids:
    """Deciduous crowns take the season's density; evergreen ones keep their own."""
    deciduous = ellipsoids.material == Material.FOLIAGE
    density = np.where(deciduous, foliage_density, ellipsoids.density)
    return Ellipsoids(center=ellipsoids.center, radii=ellipsoids.radii, material=ellipsoids.material,
                      density=density)


class SimulatedRun(Sequence[Scan]):
    """Lazily rendered scans of ``scenario`` along ``route`` (see :func:`simulate_run`).

    ``len(run)``, ``run[i]`` / ``run.scan(i)`` (renders scan i), iteration
    (renders in order), ``run.poses`` (n, 4, 4) T_world_lidar, ``run.stamps``
    (n,) seconds, ``run.point_clouds()`` (lazy sequence of the (N, 4) arrays,
    what the bag and KITTI writers take). ``keyframes`` filters every scan.
    """

    def __init__(self, town: Town, route: Route, lidar: LidarConfig, scenario: Scenario, seed: int,
                 keyframes: KeyframeFilter | None = None) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.town, self.route, self.lidar, self.scenario, self.seed = town, route, lidar, scenario, int(seed)
        self.keyframes = keyframes or KeyframeFilter()
        run_rng = np.random.default_rng([self.seed, scenario.seed_salt, 1])
        parked = parked_cars_for_run(town, scenario, run_rng)
        self.moving_cars = sample_moving_cars(town, scenario, run_rng)
        self.pedestrians = sample_pedestrians(town, scenario, run_rng)
        self._static_boxes = Boxes.concat([town.static.boxes, parked])
        self._static_cylinders = town.static.cylinders
        self._ellipsoids = _seasonal_crowns(town.static.ellipsoids, scenario.foliage_density)
        self._ground = Material.SNOW_GROUND if scenario.snow_on_ground else Material.GROUND

    def __len__(self) -> int:
        return len(self.route)

    @property
    def poses(self) -> np.ndarray:
        return self.route.poses

    @property
    def stamps(self) -> np.ndarray:
        return self.route.stamps

    def scene_at(self, index: int) -> Scene:
        """Everything the sensor can see at scan ``index`` (world frame)."""
        cars, pedestrians = agents_at(self.moving_cars, self.pedestrians, float(self.stamps[index]),
                                      self.poses[index, :2, 3])
        return Scene(Boxes.concat([self._static_boxes, cars]), Cylinders.concat([self._static_cylinders, pedestrians]),
                     self._ellipsoids, ground_z=0.0, ground_material=self._ground)

    def scan(self, index: int) -> Scan:
        """Render scan ``index`` (negative indices count from the end)."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"scan index {index} out of range for a run of {n} scans")
        index = int(index) % n
        rng = np.random.default_rng([self.seed, self.scenario.seed_salt, 2, index])
        pose = self.poses[index]
        points, labels, rings = render_scan(self.scene_at(index), pose, self.lidar, rng,
                                            self.scenario.weather_effects)
        if not self.keyframes.keeps_everything:
            kept = self.keyframes.keep(points, labels)
            points, labels, rings = points[kept], labels[kept], rings[kept]
        return Scan(index=index, stamp=float(self.stamps[index]), pose=pose.copy(), points=points, labels=labels,
                    rings=rings)

    @overload
    def __getitem__(self, index: int) -> Scan: ...

    @overload
    def __getitem__(self, index: slice) -> list[Scan]: ...

    def __getitem__(self, index: int | slice) -> Scan | list[Scan]:
        if isinstance(index, slice):
            return [self.scan(i) for i in range(*index.indices(len(self)))]
        return self.scan(index)

    def __iter__(self) -> Iterator[Scan]:
        for index in range(len(self)):
            yield self.scan(index)

    def point_clouds(self, progress: bool = False, description: str | None = None) -> PointClouds:
        """Lazy (N, 4) arrays, optionally with a tqdm bar advancing as scans are rendered."""
        return PointClouds(self, progress, description or self.scenario.name)


class PointClouds(Sequence[np.ndarray]):
    """Read-only lazy view: ``clouds[i]`` renders ``run.scan(i).points``."""

    def __init__(self, run: SimulatedRun, progress: bool = False, description: str = "") -> None:
        self._run, self._progress, self._description = run, progress, description

    def __len__(self) -> int:
        return len(self._run)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return [self._run.scan(i).points for i in range(*index.indices(len(self)))]
        return self._run.scan(index).points

    def __iter__(self) -> Iterator[np.ndarray]:
        if not self._progress:
            for index in range(len(self)):
                yield self._run.scan(index).points
            return
        from tqdm import tqdm

        with tqdm(total=len(self), desc=self._description, unit="scan") as bar:
            for index in range(len(self)):
                yield self._run.scan(index).points
                bar.update(1)


def simulate_run(town: Town, route: Route, lidar: LidarConfig | None = None,
                 scenario: Scenario | str = "summer_clear", seed: int = 0,
                 keyframes: KeyframeFilter | None = None) -> SimulatedRun:
    """A lazily rendered session; ``scenario`` is a :class:`Scenario` or a name for ``Scenario.from_name``;
    ``keyframes`` thins the scans or removes their ground (default: the scans as rendered)."""
    if isinstance(scenario, str):
        scenario = Scenario.from_name(scenario)
    return SimulatedRun(town, route, lidar or LidarConfig(), scenario, seed, keyframes)
