"""Featurizing many scans in worker processes, in order, without reading ahead unboundedly.

The caller's process reads the scans (I/O is sequential in bags) while worker
processes describe them. :func:`init_worker` / :func:`describe_in_worker` are
the workers' entry points for a :func:`worker_pool`; :func:`bounded_map`
feeds one with at most so many scans in flight.

Workers are forked from a fork server, never from the caller: a caller that has
used DDS (a test, a user's node) or KISS-ICP keeps native threads running, and a
fork of a process with threads can deadlock in the child on a lock one of them held.
As with any pool that does not fork the caller, a script that featurizes, evaluates or
trains with ``workers`` > 1 must guard its entry point with ``if __name__ == "__main__":``
(the ``vbrl`` command does).
"""

from __future__ import annotations

import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.features.featurizer import Featurizer

_worker_featurizer: Featurizer | None = None


def init_worker(config_dict: dict) -> None:
    global _worker_featurizer
    _worker_featurizer = Featurizer(VBRLConfig.from_dict(config_dict))


#: A keyframe to describe: its points, or (its points, the cloud it is described by: with its trail).
Keyframe = np.ndarray | tuple[np.ndarray, np.ndarray]


def describe_keyframe(featurizer: Featurizer, keyframe: Keyframe) -> np.ndarray:
    """``featurizer``'s descriptor of ``keyframe``; with a trail, the sensor's field of view is read
    from the keyframe's own points."""
    if isinstance(keyframe, tuple):
        scan, cloud = keyframe
        return featurizer.describe(cloud, scan=scan)
    return featurizer.describe(keyframe)


def describe_in_worker(keyframe: Keyframe) -> np.ndarray:
    assert _worker_featurizer is not None
    return describe_keyframe(_worker_featurizer, keyframe)


def default_workers() -> int:
    return max(1, min(8, (os.cpu_count() or 1)))


def worker_pool(workers: int, initializer: Callable[..., None], initargs: tuple) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes forked from a single-threaded fork server (``initargs`` are pickled).

    The server is started once per process, with the first pool's initializer module imported
    (numpy, numba, KISS-ICP): the workers of every later pool start from it in milliseconds.
    """
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([initializer.__module__])
    return ProcessPoolExecutor(workers, mp_context=context, initializer=initializer, initargs=initargs)


def featurize(
    scans: Iterable[Keyframe],
    config: VBRLConfig,
    *,
    total: int | None = None,
    workers: int | None = None,
    progress: bool = True,
    description: str = "featurizing",
) -> np.ndarray:
    """Raw descriptors (n, d) float32 of the scans (:data:`Keyframe`), computed in worker processes.

    The caller's process reads the scans (I/O is sequential in bags) while
    ``workers`` processes featurize them; results keep the input order.
    """
    workers = default_workers() if workers is None else workers
    featurizer = Featurizer(config)
    bar = tqdm(total=total, desc=description, unit="scan", disable=not progress, leave=False)
    out: list[np.ndarray] = []
    try:
        if workers <= 1:
            results: Iterator[np.ndarray] = (describe_keyframe(featurizer, scan) for scan in scans)
            for row in results:
                out.append(row)
                bar.update()
        else:
            with worker_pool(workers, init_worker, (config.to_dict(),)) as pool:
                for row in bounded_map(pool, describe_in_worker, scans, 4 * workers):
                    out.append(row)
                    bar.update()
    finally:
        bar.close()
    if not out:
        return np.zeros((0, featurizer.dimension), dtype=np.float32)
    return np.stack(out)


def bounded_map(
    pool: ProcessPoolExecutor, fn: Callable[[Any], Any], items: Iterable[Any], in_flight: int
) -> Iterator[Any]:
    """Ordered ``pool.map`` that reads at most ``in_flight`` items ahead.

    ``Executor.map`` submits the whole iterable at once, which would pull
    every scan of a bag into memory before the first result comes back.
    """
    pending: deque[Future] = deque()
    try:
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= in_flight:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    except BrokenProcessPool:
        raise WorkerPoolError("a worker process ended abruptly: out of memory or killed, or a script that "
                              "starts workers without an if __name__ == \"__main__\": guard") from None


class WorkerPoolError(ChildProcessError):
    """A worker process of :func:`worker_pool` died; the message says what usually causes it, in one line
    (an OSError, so that ``vbrl`` prints it as one)."""
