"""LiDAR simulator: procedural town, looping route, long-term change scenarios.

The built-in data source of the project (demo, test fixtures, training and
evaluation on known ground truth)::

    from vbrl_ros.simulator import (LidarConfig, RouteConfig, TownConfig, generate_town,
                                    make_route, simulate_run)

    town = generate_town(TownConfig(), seed=0)
    route = make_route(town, RouteConfig(loops=4, spacing_m=1.0))
    summer = simulate_run(town, route, LidarConfig(beams=64), "summer_clear", seed=1)
    winter = simulate_run(town, route, LidarConfig(beams=64), "winter_snow", seed=2)
    scan = winter.scan(10)   # Scan: points (N, 4) float32 sensor frame, labels, pose, stamp

Modules: :mod:`.geometry` (ray-primitive intersection), :mod:`.town`,
:mod:`.scene` (nearest-hit ray cast), :mod:`.route`, :mod:`.lidar` (sensor model, culling, rendering),
:mod:`.scenarios` (season / weather / traffic), :mod:`.keyframes` (thinned, ground-free
keyframes as SLAM front-ends publish them), :mod:`.run` (lazy sessions);
``vbrl simulate`` is :mod:`vbrl_ros.tools.simulate`.
"""

from .geometry import Boxes, Cylinders, Ellipsoids, Material, PrimitiveKind
from .scene import Hits, Scene
from .keyframes import KeyframeFilter
from .lidar import LidarConfig, WeatherEffects, render_scan
from .route import Route, RouteConfig, make_route
from .run import PointClouds, Scan, SimulatedRun, simulate_run
from .scenarios import SCENARIO_PRESETS, SEASONS, WEATHER, Scenario
from .town import Town, TownConfig, generate_town

__all__ = [
    "Boxes", "Cylinders", "Ellipsoids", "Hits", "KeyframeFilter", "LidarConfig", "Material", "PointClouds",
    "PrimitiveKind", "Route", "RouteConfig", "SCENARIO_PRESETS", "SEASONS", "Scan", "Scenario", "Scene",
    "SimulatedRun", "Town", "TownConfig", "WEATHER", "WeatherEffects", "generate_town", "make_route",
    "render_scan", "simulate_run",
]
