"""Method adapters for offline evaluation: VBRL models and the Scan Context baseline.

Every source is described ONCE (:func:`describe_source`): the raw VBRL
descriptor and the Scan Context descriptor of each keyframe, computed together
in worker processes. All VBRL variants (full model, ablations) share the raw
descriptors; only their standardisation and row weights differ.

A method turns (query descriptors, database descriptors) into a
``distances_fn(query_index, candidate_indices) -> distances`` for
:mod:`vbrl_ros.evaluation.retrieval` (lower = more similar). Matching uses the
descriptors only: poses are carried alongside for the ground truth and never
reach a method.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.datasets import open_source
from vbrl_ros.evaluation.retrieval import DistancesFn, select_top_k
from vbrl_ros.features import Featurizer
from vbrl_ros.model import VBRLModel
from vbrl_ros.scan_context import ScanContextConfig, ScanContextDatabase, scan_context
from vbrl_ros.training.keyframes import _bounded_map, default_workers, select_keyframes, source_points

__all__ = ["SourceDescriptors", "describe_source", "VBRLMethod", "ScanContextMethod",
           "weighted_l1_top_k"]


@dataclass
class SourceDescriptors:
    """Descriptors of one source's keyframes, in source order."""

    name: str
    vbrl: np.ndarray  # (n, d) float32 raw (unstandardised) VBRL descriptors
    scan_context: np.ndarray  # (n, rings, sectors) float32
    keyframe_index: np.ndarray  # (n,) scan index of each keyframe in its source
    positions: np.ndarray | None  # (n, 3) ground truth only; None without poses

    def __len__(self) -> int:
        return len(self.keyframe_index)


_worker: tuple[Featurizer, ScanContextConfig] | None = None


def _init_worker(config_dict: dict, sc_dict: dict) -> None:
    global _worker
    _worker = (Featurizer(VBRLConfig.from_dict(config_dict)), ScanContextConfig(**sc_dict))


def _describe(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    assert _worker is not None
    featurizer, sc_config = _worker
    return featurizer.describe(points), scan_context(points, sc_config)


def describe_source(
    path: Path,
    config: VBRLConfig,
    sc_config: ScanContextConfig,
    *,
    topic: str | None = None,
    poses: str = "auto",
    keyframe_distance: float | None = None,
    every: int | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> SourceDescriptors:
    """Read the keyframes of ``path`` once and compute both descriptors of each."""
    workers = default_workers() if workers is None else workers
    with open_source(path, topic=topic, poses=poses, progress=progress) as source:
        indices = select_keyframes(source, distance=keyframe_distance, every=every)
        scans = source_points(source, indices)
        bar = tqdm(total=len(indices), desc=f"describing {source.name}", unit="scan",
                   disable=not progress, leave=False)
        vbrl, sc = [], []
        try:
            if workers <= 1:
                _init_worker(config.to_dict(), asdict(sc_config))
                rows = map(_describe, scans)
                for a, b in rows:
                    vbrl.append(a), sc.append(b), bar.update()
            else:
                with ProcessPoolExecutor(workers, initializer=_init_worker,
                                         initargs=(config.to_dict(), asdict(sc_config))) as pool:
                    for a, b in _bounded_map(pool, _describe, scans, 4 * workers):
                        vbrl.append(a), sc.append(b), bar.update()
        finally:
            bar.close()
        positions = None if source.poses is None else source.poses[indices, :3, 3].copy()
        d = Featurizer(config).dimension
        return SourceDescriptors(
            name=source.name,
            vbrl=np.stack(vbrl) if vbrl else np.zeros((0, d), np.float32),
            scan_context=np.stack(sc) if sc else np.zeros((0, *sc_config.shape), np.float32),
            keyframe_index=np.asarray(indices, dtype=np.int64),
            positions=positions,
        )


def weighted_l1_top_k(
    queries: np.ndarray,
    templates: np.ndarray,
    weights: np.ndarray,
    k: int = 1,
    limits: Sequence[int] | np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Top-k (indices, distances) of Σ_r w_r |q_r − t_r| for every query; (n_q, k) each.

    Query q sees ``templates[:limits[q]]`` (None = all). Inputs are already
    standardised and restricted to the active rows. Ties go to the lower index.
    """
    Q = np.asarray(queries, dtype=np.float32)
    T = np.asarray(templates, dtype=np.float32)
    w = np.asarray(weights, dtype=np.float32)
    lim = np.full(len(Q), len(T)) if limits is None else np.asarray(limits)
    out_i = np.full((len(Q), k), -1, dtype=np.int64)
    out_d = np.full((len(Q), k), np.inf)
    for q in np.flatnonzero(lim > 0):  # one vectorised (limit, k_rows) product per query
        dist = np.abs(T[: lim[q]] - Q[q]) @ w
        out_i[q], out_d[q] = select_top_k(np.arange(lim[q]), dist.astype(np.float64), k)
    return out_i, out_d


class VBRLMethod:
    """Eq. 4 distances with one model's standardisation and importances."""

    def __init__(self, name: str, model: VBRLModel) -> None:
        self.name, self.model = name, model
        self.scorer = model.scorer()

    def _compact(self, raw: np.ndarray) -> np.ndarray:
        rows = self.scorer.active_rows
        # Standardise only the rows that score: the others have zero weight.
        out = (raw[:, rows].astype(np.float64) - self.model.feature_mean[rows]) / self.model.feature_scale[rows]
        return out.astype(np.float32)

    def distances_fn(self, queries: SourceDescriptors, database: SourceDescriptors) -> DistancesFn:
        Q = self._compact(queries.vbrl)
        T = Q if database is queries else self._compact(database.vbrl)
        w = self.scorer.active_weights

        def fn(i: int, candidates: np.ndarray) -> np.ndarray:
            n = len(candidates)
            # The drivers ask for database prefixes: a slice avoids a gather copy.
            if n and candidates[-1] - candidates[0] == n - 1:
                templates = T[candidates[0]: candidates[0] + n]
            else:
                templates = T[candidates]
            return (np.abs(templates - Q[i]) @ w).astype(np.float64)

        return fn


class ScanContextMethod:
    """Scan Context (Kim & Kim 2018): ring-key k-d tree prefilter, then the exact
    column-shift distance over all shifts on the ``num_candidates`` nearest ring keys.
    Candidates the prefilter drops get distance inf (never retrieved)."""

    name = "Scan Context"

    def __init__(self, config: ScanContextConfig, num_candidates: int = 10) -> None:
        self.config, self.num_candidates = config, num_candidates

    def distances_fn(self, queries: SourceDescriptors, database: SourceDescriptors) -> DistancesFn:
        db = ScanContextDatabase(self.config)
        for descriptor in database.scan_context:
            db.add(descriptor)
        Q = queries.scan_context

        def fn(i: int, candidates: np.ndarray) -> np.ndarray:
            out = np.full(len(candidates), np.inf)
            # Candidates are always a database prefix 0..limit-1 (P1 and P2 drivers).
            limit = int(candidates.max()) + 1 if len(candidates) else 0
            idx, dist, _ = db.query_top_k(Q[i], k=self.num_candidates,
                                          num_candidates=self.num_candidates, max_index=limit)
            out[idx] = dist
            return out

        return fn
