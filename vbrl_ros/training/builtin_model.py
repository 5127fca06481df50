"""Building the built-in default model: simulated towns of every mount plus real recordings.

Rebuild it with::

    vbrl demo --rebuild-default-model [RECORDING ...]

which simulates :data:`BUILTIN_TOWNS`, reads the recordings (the shipped model: the four
in the optional data folder, see README), trains W and overwrites the file
:mod:`vbrl_ros.model.builtin` loads. Deterministic for the seeds given here. The demo
trains its own model the same way on one town (:func:`simulated_recognition_data`,
:func:`fit_recognition_model`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vbrl_ros.config import VBRLConfig
from vbrl_ros.evaluation.methods import scan_trail_horizon
from vbrl_ros.features.parallel import featurize
from vbrl_ros.features.session_trails import with_trail
from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH
from vbrl_ros.training.fit import TrainingResult, fit_model
from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config


@dataclass(frozen=True)
class SimulatedTown:
    """One simulated drive of the built-in model's training set: its own town and mount."""

    town_seed: int
    sensor_height_m: float
    beams: int
    lane_offset_m: float = 1.0
    tilt_deg: tuple[float, float] = (0.0, 0.0)  # roll, pitch
    blocked_azimuth_deg: tuple[float, float] | None = None  # a wedge hidden by the robot's mast
    scenario: str = "summer_clear"
    run_seed: int = 1


#: Towns of every mount class the node is built for: a car (1.8 m, 64 beams), a low ground
#: robot (0.6 m, 32 beams, wider lanes, 60° behind it hidden by its mast), a mast (2.4 m) and
#: a tilted hand-held sensor; their routes drive every street both ways, so reversed
#: revisits on the other lane are in it.
BUILTIN_TOWNS = (
    SimulatedTown(0, 1.8, 64, scenario="summer_clear", run_seed=101),
    SimulatedTown(5, 0.6, 32, lane_offset_m=1.5, blocked_azimuth_deg=(150.0, -150.0), scenario="winter_snow",
                  run_seed=102),
    SimulatedTown(6, 2.4, 64, scenario="autumn_fog", run_seed=103),
    SimulatedTown(7, 1.2, 32, tilt_deg=(5.0, 15.0), scenario="summer_clear", run_seed=104),
)


def simulated_recognition_data(towns: tuple[SimulatedTown, ...], config: VBRLConfig,
                               progress: bool = True) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, raw descriptors, positions) of every keyframe (2 m apart) of each town's drive."""
    from vbrl_ros.simulator import LidarConfig, RouteConfig, TownConfig, generate_town, make_route, simulate_run

    out = []
    for town_spec in towns:
        town = generate_town(TownConfig(blocks_x=3, blocks_y=3), seed=town_spec.town_seed)
        route = make_route(town, RouteConfig(
            loops=2, spacing_m=2.0, sensor_height_m=town_spec.sensor_height_m,
            lane_offset_m=town_spec.lane_offset_m, sensor_roll_deg=town_spec.tilt_deg[0],
            sensor_pitch_deg=town_spec.tilt_deg[1]))
        wide = (-45.0, 45.0) if any(town_spec.tilt_deg) else None  # a tilted hand-held sensor
        lidar = LidarConfig(beams=town_spec.beams, columns=1024, vertical_fov_deg=wide,
                            blocked_azimuth_deg=town_spec.blocked_azimuth_deg)
        run = simulate_run(town, route, lidar, town_spec.scenario, seed=town_spec.run_seed)
        name = f"town{town_spec.town_seed}_{town_spec.sensor_height_m:g}m_{town_spec.beams}beams"
        scans = with_trail((scan.points for scan in run), run.poses, config.features.trail_m,
                           config.features.forward_trail_m, **scan_trail_horizon(range(len(run))),
                           ahead_m=config.features.trail_ahead_m)
        descriptors = featurize(scans, config, total=len(run),
                                progress=progress, description=f"simulating {name}")
        out.append((name, descriptors, run.poses[:, :3, 3]))
    return out


TrainingPart = tuple[str, np.ndarray, np.ndarray]  # (name, raw descriptors, positions)


def recording_parts(recordings: tuple[Path, ...], config: VBRLConfig,
                    progress: bool = True) -> list[TrainingPart]:
    """Every scan of each recording (any source ``vbrl train`` reads), described."""
    from vbrl_ros.training.training_data import load_training_data

    if not recordings:
        return []
    data = load_training_data(list(recordings), config, labels=None, topic=None, poses="auto",
                              keyframe_distance=None, every=None, workers=None, progress=progress)
    return [(Path(path).name, data.descriptors[data.source_of_row == k],
             data.positions[data.source_of_row == k]) for k, path in enumerate(recordings)]


def fit_recognition_model(parts: list[TrainingPart], sources: list[str]) -> TrainingResult:
    """The recognition descriptor's model: Eq. 3 on 6 m place targets, each part in its own
    frame, with the acceptance threshold calibrated on P1 within each part."""
    from vbrl_ros.training.targets import place_labels
    from vbrl_ros.training.threshold import recommend_threshold

    descriptors = np.concatenate([p[1] for p in parts])
    positions = np.concatenate([p[2] for p in parts])
    source = np.concatenate([np.full(len(p[1]), k) for k, p in enumerate(parts)])
    keyframe_index = np.concatenate([np.arange(len(p[1])) for p in parts])
    labels, names = place_labels(positions, 6.0, source)
    result = fit_model(
        descriptors, labels, names, recognition_config(), lambda1=10.0, lambda2=0.1,
        metadata={"trained_on": [p[0] for p in parts], "sources": sources,
                  "targets": f"places ({len(names)} cells of 6 m, per source)",
                  "translation_search": RECOGNITION_TRANSLATION_SEARCH_M},
    )
    threshold = recommend_threshold(result.model, descriptors, source, positions, source_of_row=source,
                                    keyframe_index=keyframe_index, protocols=("P1",))
    if threshold is None:
        raise RuntimeError("the training data has no revisits to calibrate on")
    result.model.metadata["distance_threshold"] = threshold.pop("distance_threshold")
    result.model.metadata["distance_threshold_info"] = threshold
    return result


def build_default_model(
    out: Path = DEFAULT_MODEL_PATH, recordings: tuple[Path, ...] = (),
    towns: tuple[SimulatedTown, ...] = BUILTIN_TOWNS, progress: bool = True,
) -> TrainingResult:
    """The built-in model (:func:`fit_recognition_model`) on the simulated ``towns`` and the
    real ``recordings``; writes ``out``."""
    config = recognition_config()
    parts = simulated_recognition_data(towns, config, progress) + recording_parts(recordings, config, progress)
    result = fit_recognition_model(parts, [str(Path(r).resolve()) for r in recordings])
    result.model.save(out)
    return result
