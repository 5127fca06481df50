"""``vbrl bench``: what sequence matching adds per keyframe, by id and by place, in a large database.

Each keyframe re-scores the translation search's pool of 100 candidates over itself and the
three keyframes before it (:mod:`vbrl_ros.index.sequence_matching`). By place, with odometry,
it also looks up where the candidates were and whether any stored keyframe lies near each
place an earlier term asks about (:mod:`vbrl_ros.index.keyframe_places`). Timed here on a
walk of ``keyframes`` positions 1.5 m apart folded into a 2 km square (streets passed many
times), with pools of candidates drawn from all of it — more places to look up than a real
pool, whose candidates cluster.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vbrl_ros.index.keyframe_places import KeyframePlaces
from vbrl_ros.index.sequence_matching import DEFAULT_LENGTH, PLACE_SLACK_M, SequenceHistory
from vbrl_ros.index.translation_search import POOL

SPACING_M = 1.5
AREA_M = 2000.0


def walk(keyframes: int, seed: int = 0) -> np.ndarray:
    """(keyframes, 3) positions of a random walk, ``SPACING_M`` apart, folded into the area."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(keyframes, 2))
    positions = np.zeros((keyframes, 3))
    positions[:, :2] = np.cumsum(SPACING_M * steps / np.linalg.norm(steps, axis=1)[:, None], axis=0) % AREA_M
    return positions


def measure(keyframes: int = 100_000, repeats: int = 300, seed: int = 0) -> dict[str, Any]:
    """Median and p95 ms of one keyframe's rescoring by id and by place, and of adding a place."""
    positions = walk(keyframes, seed)
    places = KeyframePlaces(PLACE_SLACK_M)
    start = time.perf_counter()
    for keyframe_id, position in enumerate(positions):
        places.add(keyframe_id, position)
    add_ms = 1e3 * (time.perf_counter() - start) / keyframes
    rng = np.random.default_rng(seed + 1)
    out: dict[str, Any] = {"keyframes": keyframes, "pool": POOL, "length": DEFAULT_LENGTH, "add_place_ms": add_ms}
    for name, by_place in (("by_id", False), ("by_place", True)):
        history, times = SequenceHistory(DEFAULT_LENGTH), []
        for k in range(repeats + 10):  # the first ten fill the history (and compile)
            ids = np.sort(rng.choice(keyframes, POOL, replace=False))
            distances = rng.uniform(10.0, 20.0, POOL)
            here = positions[rng.integers(keyframes)]
            start = time.perf_counter()
            history.rescore(ids, distances, here=here if by_place else None, places=places if by_place else None)
            if k >= 10:
                times.append(time.perf_counter() - start)
        out[f"{name}_ms"] = 1e3 * float(np.median(times))
        out[f"{name}_p95_ms"] = 1e3 * float(np.percentile(times, 95))
    return out
