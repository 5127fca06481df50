"""A real scan for the feature tests: 32 beams ray-cast in a small simulated town."""

import numpy as np
import pytest


@pytest.fixture(scope="session")
def town_scan() -> np.ndarray:
    """(N, 3) float64 sensor-frame points of one keyframe of a 2 x 2-block town."""
    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=4)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=5.0)),
                           sim.LidarConfig(beams=32, columns=720), "summer_clear", seed=1)
    return run.scan(7).points[:, :3].astype(np.float64)
