"""Training without holding X: one pass of raw moments, algebraic standardisation, Gram solve.

A training set larger than memory (n·d·4 bytes; 100k scans x 7872 features is
3 GB) never has to be materialised. One pass over the raw descriptors x_t
(chunks of keyframes, straight from the featurization workers) accumulates

    G_raw = Σ x xᵀ (d×d),  s = Σ x (d),  B_raw = Σ x yᵀ (d×c),  Yᵀ1 (c),  ‖Y‖²,  n

(G_raw, B_raw, ‖Y‖², n by :class:`~vbrl_ros.model.gram.GramAccumulator`). The
standardisation of :func:`~vbrl_ros.training.fit.standardization` follows
algebraically, with μ = s/n and S = diag(scale), scale² = diag(G_raw)/n − μ²:

    G_std = S⁻¹ (G_raw − n μμᵀ) S⁻¹
    B_std = S⁻¹ (B_raw − μ (Yᵀ1)ᵀ)

which is exactly X_std X_stdᵀ and X_std Y of the in-memory path (up to float64
round-off: the subtraction cancels ~|μ|²/scale² of the relative precision, i.e.
~1e-12 for features whose mean is 1e4 times their spread), and the solver
then runs on the Gram path ((G + Λ)W = B, d×d solves). Memory: one d×d float64
matrix (0.5 GB at d = 7872) plus one chunk, whatever n is. The same moments
serve every (λ1, λ2): the ablations cost one solve each, no second pass.

With tie classes (polar grid: one feature in every sector), μ and scale are
pooled per class (:func:`~vbrl_ros.training.fit.pool_tied`), so μ ≠ m = s/n and

    G_std = S⁻¹ (G_raw − n m mᵀ + n (m − μ)(m − μ)ᵀ) S⁻¹

(the expansion of Σ (x − μ)(x − μ)ᵀ); B_std keeps its form.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.datasets.keyframe_selection import select_keyframes
from vbrl_ros.datasets.registry import open_source
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.features.parallel import (
    bounded_map,
    default_workers,
    describe_in_worker,
    describe_keyframe,
    init_worker,
    worker_pool,
)
from vbrl_ros.model.gram import GramAccumulator, GramStats
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.model.solver import solve_vbrl
from vbrl_ros.training.fit import MIN_FEATURE_SCALE, TrainingResult, pool_tied, row_groups
from vbrl_ros.training.training_data import described_clouds

DEFAULT_CHUNK = 512  # keyframes per Gram update: large enough for BLAS, small next to G


class RawMoments:
    """One-pass sums of raw descriptors and one-hot labels (see the module docstring)."""

    def __init__(self, d: int, c: int) -> None:
        self.gram = GramAccumulator(d, c)
        self.column_sum = np.zeros(d)
        self.label_count = np.zeros(c)

    @property
    def n(self) -> int:
        return self.gram.n

    def add(self, descriptors: np.ndarray, labels: np.ndarray) -> None:
        """Add k keyframes: raw descriptors (k, d) and scenario indices (k,)."""
        X = np.asarray(descriptors, dtype=np.float64)
        labels = np.asarray(labels, dtype=np.intp)
        if len(X) == 0:
            return
        Y = np.zeros((len(X), self.gram.c))
        Y[np.arange(len(X)), labels] = 1.0
        # X.T of a C-ordered (k, d) chunk is F-contiguous: dsyrk takes it without a copy.
        self.gram.add(X.T, Y)
        self.column_sum += X.sum(axis=0)
        self.label_count += Y.sum(axis=0)

    def standardized(
        self, tie_of_row: np.ndarray | None = None
    ) -> tuple[GramStats, np.ndarray, np.ndarray]:
        """(Gram statistics of the standardised data, feature mean, feature scale).

        ``tie_of_row``: pool mean and scale per tie class, as ``fit.standardization``.
        """
        n = self.n
        if n < 2:
            raise ValueError(f"training needs at least 2 scans, got {n}")
        raw = self.gram.stats()
        row_mean = self.column_sum / n
        var = np.maximum(np.diag(raw.G) / n - row_mean * row_mean, 0.0)  # clip round-off below 0
        mean = row_mean
        if tie_of_row is not None:
            mean, var = pool_tied(row_mean, var, tie_of_row)
        scale = np.sqrt(var)
        scale[scale < MIN_FEATURE_SCALE] = 1.0  # same rule as fit.standardization
        inv = 1.0 / scale
        G = raw.G  # a fresh copy from stats(): update in place, one d×d buffer
        G -= n * np.outer(row_mean, row_mean)
        if mean is not row_mean:  # pooled: centre on the class mean instead (module docstring)
            shift = row_mean - mean
            G += n * np.outer(shift, shift)
        G *= inv[:, None]
        G *= inv[None, :]
        B = (raw.B - np.outer(mean, self.label_count)) * inv[:, None]
        return GramStats(G, B, raw.yy, n), mean, scale


def fit_from_moments(
    moments: RawMoments,
    scenario_names: Sequence[str],
    config: VBRLConfig,
    lambda1: float,
    lambda2: float,
    *,
    tol: float = 1e-6,
    max_iter: int = 100,
    metadata: dict[str, Any] | None = None,
    standardized: tuple[GramStats, np.ndarray, np.ndarray] | None = None,
    on_iteration: Callable[[int, float], None] | None = None,
) -> TrainingResult:
    """Solve Eq. 3 on the Gram path from streamed moments and build the model.

    ``standardized`` lets several (λ1, λ2) share one standardisation; ``on_iteration``
    goes to :func:`~vbrl_ros.model.solver.solve_vbrl` (progress).
    """
    start = time.perf_counter()
    layout = Featurizer(config).layout
    stats, mean, scale = standardized or moments.standardized(layout.tie_of_row)
    if stats.G.shape[0] != layout.dimension:
        raise ValueError(f"moments have d={stats.G.shape[0]}, the configuration needs {layout.dimension}")
    result = solve_vbrl(groups=row_groups(layout), gram=stats, lambda1=lambda1, lambda2=lambda2, tol=tol,
                        max_iter=max_iter, on_iteration=on_iteration)
    seconds = time.perf_counter() - start
    info = {
        "scans": int(moments.n),
        "scans_per_scenario": moments.label_count.astype(int).tolist(),
        "solver_path": result.path,
        "solver_iterations": int(result.iterations),
        "solver_converged": bool(result.converged),
        "objective": float(result.objective_history[-1]),
        "training_seconds": round(seconds, 3),
        "streamed": True,
        **(metadata or {}),
    }
    model = VBRLModel(config=config, W=result.W, feature_mean=mean, feature_scale=scale,
                      lambda1=lambda1, lambda2=lambda2, scenarios=list(scenario_names), metadata=info)
    return TrainingResult(model=model, solver=result, seconds=seconds)


# -- streaming the keyframes of several sources -------------------------------------------


@dataclass
class StreamedSources:
    """What is kept of streamed sources besides the moments: small per-keyframe facts."""

    scenario_names: list[str]
    keyframes_per_source: list[int] = field(default_factory=list)
    positions: list[np.ndarray] = field(default_factory=list)  # (k, 3) per source, NaN if unknown


def count_keyframes(paths: Sequence[Path], *, topic: str | None, poses: str,
                    keyframe_distance: float | None, every: int | None) -> int:
    """Number of keyframes the sources give (opens each source, reads no points)."""
    total = 0
    for path in paths:
        with open_source(path, topic=topic, poses=poses, progress=False) as source:
            total += len(select_keyframes(source, distance=keyframe_distance, every=every))
    return total


def _chunks(rows: Iterable[np.ndarray], size: int) -> Iterator[np.ndarray]:
    buffer: list[np.ndarray] = []
    for row in rows:
        buffer.append(row)
        if len(buffer) == size:
            yield np.stack(buffer)
            buffer = []
    if buffer:
        yield np.stack(buffer)


def stream_moments(
    paths: Sequence[Path],
    names: Sequence[str],
    config: VBRLConfig,
    *,
    topic: str | None,
    poses: str,
    keyframe_distance: float | None,
    every: int | None,
    workers: int | None,
    progress: bool = True,
    chunk: int = DEFAULT_CHUNK,
) -> tuple[RawMoments, StreamedSources]:
    """Featurize every keyframe of every source once, folding it into :class:`RawMoments`.

    ``names[k]`` is the scenario label of ``paths[k]`` (equal labels share a scenario).
    Descriptors are never stacked beyond one chunk.
    """
    scenario_names = list(dict.fromkeys(names))
    featurizer = Featurizer(config)
    moments = RawMoments(featurizer.dimension, len(scenario_names))
    info = StreamedSources(scenario_names)
    workers = default_workers() if workers is None else workers
    pool = worker_pool(workers, init_worker, (config.to_dict(),)) if workers > 1 else None
    try:
        for path, name in zip(paths, names):
            with open_source(path, topic=topic, poses=poses, progress=progress) as source:
                indices = select_keyframes(source, distance=keyframe_distance, every=every)
                scans = described_clouds(source, indices, config)
                rows = (bounded_map(pool, describe_in_worker, scans, 4 * workers) if pool
                        else (describe_keyframe(featurizer, scan) for scan in scans))
                bar = tqdm(total=len(indices), desc=f"streaming {source.name}", unit="scan",
                           disable=not progress, leave=False)
                label = scenario_names.index(name)
                for block in _chunks(rows, chunk):
                    moments.add(block, np.full(len(block), label))
                    bar.update(len(block))
                bar.close()
                info.keyframes_per_source.append(len(indices))
                info.positions.append(np.full((len(indices), 3), np.nan) if source.poses is None
                                      else source.poses[indices, :3, 3])
    finally:
        if pool is not None:
            pool.shutdown()
    return moments, info
