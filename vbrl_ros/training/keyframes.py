"""Keyframe selection and (parallel) featurization of scan sources."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

import numpy as np
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.datasets import ScanSource
from vbrl_ros.features.featurizer import Featurizer


def select_by_distance(poses: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of keyframes at least ``spacing`` metres of travel apart along the poses.

    The first scan with a known pose is always a keyframe; scans with unknown
    (NaN) poses are skipped. Travel is summed along the path, not measured as
    a straight line, so standing still never makes keyframes and a tight
    loop still does.
    """
    if spacing <= 0:
        raise ValueError(f"keyframe spacing must be positive, got {spacing}")
    positions = np.asarray(poses)[:, :3, 3]
    known = np.flatnonzero(np.isfinite(positions).all(axis=1))
    if len(known) == 0:
        return known
    steps = np.linalg.norm(np.diff(positions[known], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    selected = [0]
    next_at = spacing
    # Python loop over scans (not points): cheap, and a keyframe resets the
    # reference, which a vectorised floor(travelled / spacing) would not.
    for k in range(1, len(known)):
        if travelled[k] >= next_at:
            selected.append(k)
            next_at = travelled[k] + spacing
    return known[np.asarray(selected)]


def select_every(count: int, every: int) -> np.ndarray:
    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    return np.arange(0, count, every)


def select_keyframes(
    source: ScanSource, *, distance: float | None = None, every: int | None = None
) -> np.ndarray:
    """Keyframe indices of a source: by travelled distance (needs poses) or every N scans."""
    if distance is not None and every is not None:
        raise ValueError("choose either a keyframe distance or every N scans, not both")
    if distance is not None:
        if source.poses is None:
            raise ValueError(
                f"{source.name} has no poses, so keyframes cannot be spaced by distance; "
                "use --poses kiss-icp to estimate them, or --every N"
            )
        return select_by_distance(source.poses, distance)
    return select_every(len(source), every or 1)


# -- featurization ----------------------------------------------------------

_worker_featurizer: Featurizer | None = None


def _init_worker(config_dict: dict) -> None:
    global _worker_featurizer
    _worker_featurizer = Featurizer(VBRLConfig.from_dict(config_dict))


def _describe_in_worker(points: np.ndarray) -> np.ndarray:
    assert _worker_featurizer is not None
    return _worker_featurizer.describe(points)


def default_workers() -> int:
    return max(1, min(8, (os.cpu_count() or 1)))


def featurize(
    scans: Iterable[np.ndarray],
    config: VBRLConfig,
    *,
    total: int | None = None,
    workers: int | None = None,
    progress: bool = True,
    description: str = "featurizing",
) -> np.ndarray:
    """Raw descriptors (n, d) float32 of the scans, computed in worker processes.

    The caller's process reads the scans (I/O is sequential in bags) while
    ``workers`` processes featurize them; results keep the input order.
    """
    workers = default_workers() if workers is None else workers
    featurizer = Featurizer(config)
    bar = tqdm(total=total, desc=description, unit="scan", disable=not progress, leave=False)
    out: list[np.ndarray] = []
    try:
        if workers <= 1:
            results: Iterator[np.ndarray] = map(featurizer.describe, scans)
            for row in results:
                out.append(row)
                bar.update()
        else:
            with ProcessPoolExecutor(
                workers, initializer=_init_worker, initargs=(config.to_dict(),)
            ) as pool:
                for row in _bounded_map(pool, _describe_in_worker, scans, 4 * workers):
                    out.append(row)
                    bar.update()
    finally:
        bar.close()
    if not out:
        return np.zeros((0, featurizer.dimension), dtype=np.float32)
    return np.stack(out)


def _bounded_map(
    pool: ProcessPoolExecutor, fn: Callable[[Any], Any], items: Iterable[Any], in_flight: int
) -> Iterator[Any]:
    """Ordered ``pool.map`` that reads at most ``in_flight`` items ahead.

    ``Executor.map`` submits the whole iterable at once, which would pull
    every scan of a bag into memory before the first result comes back.
    """
    pending: deque[Future] = deque()
    for item in items:
        pending.append(pool.submit(fn, item))
        if len(pending) >= in_flight:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def source_points(source: ScanSource, indices: Sequence[int]) -> Iterator[np.ndarray]:
    """The points of the selected scans, read in order (sequential reads are cheap in bags)."""
    wanted = set(int(i) for i in indices)
    if len(wanted) == len(source):
        for scan in source:
            yield scan.points
        return
    for i in sorted(wanted):
        yield source[i].points
