"""Building the built-in default model: trained on the simulator's scenarios.

Rebuild it with::

    vbrl demo --rebuild-default-model

which simulates the scenarios of :class:`SimulatedTrainingSpec`, trains W and
overwrites the file :mod:`vbrl_ros.model.builtin` loads. Deterministic for
the seeds given here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vbrl_ros.config import VBRLConfig
from vbrl_ros.features.parallel import featurize
from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH
from vbrl_ros.training.fit import TrainingResult, fit_model


@dataclass(frozen=True)
class SimulatedTrainingSpec:
    """What the default model is trained on (the town of ``town_seed``; tests use other towns)."""

    scenarios: tuple[str, ...] = ("summer_clear", "winter_snow", "autumn_fog")
    town_seed: int = 0
    run_seeds: tuple[int, ...] = (101, 102, 103)
    loops: int = 2
    keyframe_spacing_m: float = 4.0
    beams: int = 64
    columns: int = 1800
    lambda1: float = 10.0
    lambda2: float = 0.1


def simulated_training_data(
    spec: SimulatedTrainingSpec, config: VBRLConfig, progress: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(descriptors, scenario labels, positions, keyframe index in its run) of every keyframe."""
    from vbrl_ros.simulator import LidarConfig, RouteConfig, generate_town, make_route, simulate_run

    town = generate_town(seed=spec.town_seed)
    route = make_route(town, RouteConfig(loops=spec.loops, spacing_m=spec.keyframe_spacing_m))
    lidar = LidarConfig(beams=spec.beams, columns=spec.columns)
    rows, labels, positions, indices = [], [], [], []
    for k, (name, seed) in enumerate(zip(spec.scenarios, spec.run_seeds)):
        run = simulate_run(town, route, lidar, name, seed=seed)
        rows.append(featurize((scan.points for scan in run), config, total=len(run),
                              progress=progress, description=f"simulating {name}"))
        labels.append(np.full(len(run), k))
        positions.append(run.poses[:, :3, 3])
        indices.append(np.arange(len(run)))
    return (np.concatenate(rows), np.concatenate(labels), np.concatenate(positions),
            np.concatenate(indices))


def build_default_model(
    out: Path = DEFAULT_MODEL_PATH, spec: SimulatedTrainingSpec | None = None, progress: bool = True
) -> TrainingResult:
    from vbrl_ros.training.threshold import recommend_threshold

    spec = spec or SimulatedTrainingSpec()
    config = VBRLConfig()
    descriptors, labels, positions, keyframe_index = simulated_training_data(spec, config, progress)
    result = fit_model(
        descriptors, labels, list(spec.scenarios), config,
        lambda1=spec.lambda1, lambda2=spec.lambda2,
        metadata={"trained_on": f"simulator: {spec}"},
    )
    model = result.model
    # Cross-session first: the route's own revisits are mostly driven in the
    # opposite direction, which the sensor-fixed grid cannot match anyway.
    threshold = recommend_threshold(model, descriptors, labels, positions,
                                    source_of_row=labels, keyframe_index=keyframe_index,
                                    protocols=("P2", "P1"))
    if threshold is None:
        raise RuntimeError("the simulated training data has no revisits to calibrate on")
    model.metadata["distance_threshold"] = threshold.pop("distance_threshold")
    model.metadata["distance_threshold_info"] = threshold
    model.save(out)
    return result
