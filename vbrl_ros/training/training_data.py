"""The training set: raw descriptors of the keyframes of several sources, with their labels."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vbrl_ros.config import VBRLConfig
from vbrl_ros.datasets.base import ScanSource
from vbrl_ros.datasets.keyframe_selection import keyframe_poses, select_keyframes, source_points
from vbrl_ros.datasets.registry import open_source
from vbrl_ros.evaluation.methods import scan_trail_horizon
from vbrl_ros.features.parallel import featurize
from vbrl_ros.features.session_trails import with_trail


@dataclass
class TrainingData:
    """Raw descriptors of the keyframes of several sources, with their scenario labels."""

    descriptors: np.ndarray  # (n, d) float32
    labels: np.ndarray  # (n,) scenario index
    scenario_names: list[str]
    positions: np.ndarray  # (n, 3), NaN where unknown
    source_of_row: np.ndarray  # (n,) index into the sources
    keyframe_index: np.ndarray  # (n,) scan index inside its source


def described_clouds(source: ScanSource, indices: Sequence[int],
                     config: VBRLConfig) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(points, the cloud it is described by: with its trail) of the keyframes ``indices`` of ``source``."""
    return with_trail(source_points(source, indices), keyframe_poses(source, indices), config.features.trail_m,
                      config.features.forward_trail_m, **scan_trail_horizon(indices),
                      ahead_m=config.features.trail_ahead_m)


def source_labels(paths: list[Path], labels: list[str] | None) -> list[str]:
    """Scenario label of each source: ``labels`` or the file/folder name."""
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"--labels needs one label per source ({len(paths)}), got {len(labels)}")
    return labels or [Path(p).stem if Path(p).is_file() else Path(p).name for p in paths]


def load_training_data(
    paths: list[Path],
    config: VBRLConfig,
    *,
    labels: list[str] | None,
    topic: str | None,
    poses: str,
    keyframe_distance: float | None,
    every: int | None,
    workers: int | None,
    progress: bool = True,
) -> TrainingData:
    names = source_labels(paths, labels)
    scenario_names = list(dict.fromkeys(names))  # sources with the same label share a scenario
    rows, label_rows, positions, source_rows, index_rows = [], [], [], [], []
    for k, (path, name) in enumerate(zip(paths, names)):
        with open_source(path, topic=topic, poses=poses, progress=progress) as source:
            indices = select_keyframes(source, distance=keyframe_distance, every=every)
            descriptors = featurize(
                described_clouds(source, indices, config), config, total=len(indices), workers=workers,
                progress=progress, description=f"featurizing {source.name}",
            )
            rows.append(descriptors)
            label_rows.append(np.full(len(indices), scenario_names.index(name)))
            source_rows.append(np.full(len(indices), k))
            index_rows.append(indices)
            if source.poses is None:
                positions.append(np.full((len(indices), 3), np.nan))
            else:
                positions.append(source.poses[indices, :3, 3])
    return TrainingData(
        descriptors=np.concatenate(rows),
        labels=np.concatenate(label_rows),
        scenario_names=scenario_names,
        positions=np.concatenate(positions),
        source_of_row=np.concatenate(source_rows),
        keyframe_index=np.concatenate(index_rows),
    )
