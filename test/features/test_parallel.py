"""Featurizing in worker processes: the same descriptors as in the caller, from workers the caller did not fork."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.features.parallel import WorkerPoolError, bounded_map, featurize, init_worker, worker_pool


def scans(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [rng.uniform(-30, 30, (4000, 3)).astype(np.float32) * [1, 1, 0.1] for _ in range(count)]


def test_workers_describe_as_the_caller_does_in_the_input_order():
    config = VBRLConfig()
    clouds = scans(5)
    in_workers = featurize(clouds, config, workers=2, progress=False)
    featurizer = Featurizer(config)
    assert np.array_equal(in_workers, np.stack([featurizer.describe(cloud) for cloud in clouds]))


def test_workers_come_from_a_fork_server_not_from_a_caller_with_threads():
    # a caller that has run DDS or KISS-ICP keeps native threads; a fork of it can deadlock on
    # a lock one of them held, so the workers must not be the caller's children
    stop = threading.Event()
    busy = threading.Thread(target=stop.wait)
    busy.start()
    try:
        with worker_pool(2, init_worker, (VBRLConfig().to_dict(),)) as pool:
            parents = {pool.submit(os.getppid).result() for _ in range(4)}
    finally:
        stop.set()
        busy.join()
    assert os.getpid() not in parents


def test_a_worker_that_dies_is_one_line_naming_the_usual_causes():
    with worker_pool(2, init_worker, (VBRLConfig().to_dict(),)) as pool:
        with pytest.raises(WorkerPoolError, match="ended abruptly: out of memory or killed"):
            list(bounded_map(pool, os._exit, [1, 1], 2))  # as the OOM killer would end it
