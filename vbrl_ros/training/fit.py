"""From raw descriptors and scenario labels to a :class:`~vbrl_ros.model.model_file.VBRLModel`."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vbrl_ros.config import VBRLConfig
from vbrl_ros.features.featurizer import FeatureLayout, Featurizer
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.model.solver import RowGroups, SolverResult, solve_vbrl
from vbrl_ros.training.pair_targets import pair_targets

#: Features whose spread over the training set is below this are constant:
#: they keep a unit scale instead of blowing up to 1/0.
MIN_FEATURE_SCALE = 1e-6


@dataclass
class TrainingResult:
    model: VBRLModel
    solver: SolverResult
    seconds: float


def standardization(
    descriptors: np.ndarray, tie_of_row: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature mean and scale (standard deviation, 1 where a feature is constant).

    ``tie_of_row`` (``FeatureLayout.tie_of_row``) pools both over each tie
    class — on a polar grid, one feature in every sector — so all sectors share
    one standardisation; else a comparison under a sector shift would mix scales.
    """
    X = np.asarray(descriptors, dtype=np.float64)
    mean = X.mean(axis=0)
    if tie_of_row is None or _untied(tie_of_row):
        scale = X.std(axis=0)
    else:
        mean, var = pool_tied(mean, X.var(axis=0), tie_of_row)
        scale = np.sqrt(var)
    scale[scale < MIN_FEATURE_SCALE] = 1.0
    return mean, scale


def _untied(tie_of_row: np.ndarray) -> bool:
    """Every row its own class (a Cartesian grid): nothing to pool."""
    return len(np.unique(tie_of_row)) == len(tie_of_row)


def pool_tied(mean: np.ndarray, var: np.ndarray,
              tie_of_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-row mean and variance (over the same scans) -> those of each row's tie class, per row.

    Every row of a class has the same scan count, so the class mean is the mean
    of the row means and the class variance the mean of ``var + (mean - class
    mean)²`` (law of total variance). Untied rows come back unchanged.
    """
    tie = np.asarray(tie_of_row, dtype=np.intp)
    if _untied(tie):
        return mean, var
    size = np.bincount(tie).astype(np.float64)
    class_mean = np.bincount(tie, weights=mean) / size
    spread = var + (mean - class_mean[tie]) ** 2
    return class_mean[tie], (np.bincount(tie, weights=spread) / size)[tie]


def row_groups(layout: FeatureLayout) -> RowGroups:
    """The solver's sparsity groups: voxels, or (layer, ring) columns tied across polar sectors."""
    tied = layout.weight_layout
    return RowGroups(voxel_of_row=tied.voxel_of_row, modality_of_row=tied.modality_of_row)


def one_hot(labels: Sequence[int] | np.ndarray, n_classes: int) -> np.ndarray:
    """Y in {0, 1}^{n x c}: row i has a single 1 in the column of scan i's scenario."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or (len(labels) and (labels.min() < 0 or labels.max() >= n_classes)):
        raise ValueError(f"labels must be integers in [0, {n_classes}), got {labels}")
    Y = np.zeros((len(labels), n_classes))
    Y[np.arange(len(labels)), labels] = 1.0
    return Y


def fit_pairs(
    descriptors: np.ndarray,
    positions: np.ndarray,
    source_of_row: np.ndarray,
    config: VBRLConfig,
    lambda1: float = 10.0,
    lambda2: float = 0.1,
    *,
    tol: float = 1e-6,
    max_iter: int = 100,
    metadata: dict[str, Any] | None = None,
    on_iteration: Callable[[int, float], None] | None = None,
) -> TrainingResult:
    """Standardise, solve Eq. 3 on same/different-place pairs (:mod:`.pair_targets`), build the model.

    ``on_iteration`` goes to :func:`~vbrl_ros.model.solver.solve_vbrl` (progress)."""
    layout = Featurizer(config).layout
    descriptors = _checked_descriptors(descriptors, layout)
    start = time.perf_counter()
    mean, scale = standardization(descriptors, layout.tie_of_row)
    pairs = pair_targets((descriptors - mean) / scale, np.asarray(positions, np.float64),
                         np.asarray(source_of_row), layout)
    result = solve_vbrl(pairs.X.T, pairs.Y, row_groups(layout), lambda1=lambda1, lambda2=lambda2,
                        tol=tol, max_iter=max_iter, on_iteration=on_iteration)
    seconds = time.perf_counter() - start
    info = {"scans": int(len(descriptors)), "targets": "pairs",
            "pairs": {"same_place": pairs.n_same, "different_place": pairs.n_different},
            **_solver_info(result, seconds), **(metadata or {})}
    model = VBRLModel(config=config, W=result.W, feature_mean=mean, feature_scale=scale,
                      lambda1=lambda1, lambda2=lambda2, scenarios=["same_place", "different_place"],
                      metadata=info)
    return TrainingResult(model=model, solver=result, seconds=seconds)


def _checked_descriptors(descriptors: np.ndarray, layout: FeatureLayout) -> np.ndarray:
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or descriptors.shape[1] != layout.dimension:
        raise ValueError(
            f"descriptors must be (n, {layout.dimension}) for this configuration, "
            f"got {descriptors.shape}"
        )
    if len(descriptors) < 2:
        raise ValueError(f"training needs at least 2 scans, got {len(descriptors)}")
    return descriptors


def _solver_info(result: SolverResult, seconds: float) -> dict[str, Any]:
    return {
        "solver_path": result.path,
        "solver_iterations": int(result.iterations),
        "solver_converged": bool(result.converged),
        "objective": float(result.objective_history[-1]),
        "training_seconds": round(seconds, 3),
    }


def fit_model(
    descriptors: np.ndarray,
    labels: Sequence[int] | np.ndarray,
    scenario_names: Sequence[str],
    config: VBRLConfig | None = None,
    lambda1: float = 10.0,
    lambda2: float = 0.1,
    *,
    tol: float = 1e-6,
    max_iter: int = 100,
    metadata: dict[str, Any] | None = None,
    on_iteration: Callable[[int, float], None] | None = None,
) -> TrainingResult:
    """Standardise (n, d) raw descriptors, solve Eq. 3 against one-hot scenarios, build the model.

    The solver picks its path (Woodbury for n < d, Gram matrix otherwise); ``on_iteration``
    goes to :func:`~vbrl_ros.model.solver.solve_vbrl` (progress).
    """
    config = config or VBRLConfig()
    layout = Featurizer(config).layout
    descriptors = _checked_descriptors(descriptors, layout)
    Y = one_hot(labels, len(scenario_names))
    if len(Y) != len(descriptors):
        raise ValueError(f"{len(Y)} labels for {len(descriptors)} descriptors")

    start = time.perf_counter()
    mean, scale = standardization(descriptors, layout.tie_of_row)
    X = ((descriptors - mean) / scale).T  # (d, n), one column per scan as in the paper
    groups = row_groups(layout)
    result = solve_vbrl(X, Y, groups, lambda1=lambda1, lambda2=lambda2, tol=tol, max_iter=max_iter,
                        on_iteration=on_iteration)
    seconds = time.perf_counter() - start
    info = {
        "scans": int(len(descriptors)),
        "scans_per_scenario": np.bincount(np.asarray(labels), minlength=len(scenario_names)).tolist(),
        **_solver_info(result, seconds),
        **(metadata or {}),
    }
    model = VBRLModel(
        config=config,
        W=result.W,
        feature_mean=mean,
        feature_scale=scale,
        lambda1=lambda1,
        lambda2=lambda2,
        scenarios=list(scenario_names),
        metadata=info,
    )
    return TrainingResult(model=model, solver=result, seconds=seconds)
