"""Loop-closure verification, measured: milliseconds per candidate stage by stage, and what
it decided, on simulated 64-beam keyframes with known poses.

The keyframes are what the node verifies: each scan levelled on its own ground
(the built-in recognition featurizer's frame, turned to a random heading) and thinned to one point per
``VOXEL_M`` (:func:`~vbrl_ros.detection.detector.verification_cloud`, ~6k points).
Pairs are revisits 0.5-4 m apart, some driven the other way round, and unrelated
places more than ``UNRELATED_M`` apart; every pair is verified without an initial
guess, as the node does, on one thread (as ``vbrl eval --verify``'s workers); the
last column is the cost of a query's further candidates, its own preparation shared.

Accuracy is the detector's own rule at its default settings: a revisit should be
accepted with its pose within a few centimetres and a degree, an unrelated place rejected.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from vbrl_ros.detection.candidate_verification import closure_rejection, query_verifier, to_sensor_frames
from vbrl_ros.detection.detector import verification_cloud
from vbrl_ros.detection.registration import verify_loop, yaw_guess
from vbrl_ros.detection.settings import DetectorSettings

VOXEL_M = 1.0
REVISIT_M = (0.5, 4.0)
UNRELATED_M = 40.0
#: Keyframes closer in the drive than this are the same pass, not a revisit.
_SAME_PASS = 15
REVERSED_DEG = 150.0


@dataclass(frozen=True)
class KeyframePair:
    query: np.ndarray  # (N, 3) float32 verification cloud, levelled frame
    match: np.ndarray
    query_frame: np.ndarray  # 4x4 sensor -> levelled frame
    match_frame: np.ndarray
    truth: np.ndarray  # 4x4 T_query_match between the two sensors
    revisit: bool

    @property
    def reversed(self) -> bool:
        return abs(math.degrees(math.atan2(self.truth[1, 0], self.truth[0, 0]))) > REVERSED_DEG


def keyframe_pairs(revisits: int = 24, unrelated: int = 12, seed: int = 3) -> list[KeyframePair]:
    """``revisits`` revisit pairs (as many reversed ones as the route has, up to half) and
    ``unrelated`` pairs of far-apart places, from a three-loop drive through a simulated town."""
    from vbrl_ros.features.featurizer import Featurizer
    from vbrl_ros.simulator import (
        LidarConfig,
        RouteConfig,
        TownConfig,
        generate_town,
        make_route,
        simulate_run,
    )
    from vbrl_ros.training.presets import recognition_config

    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), seed=seed)
    run = simulate_run(town, make_route(town, RouteConfig(loops=3, spacing_m=2.0)), LidarConfig(beams=64),
                       "summer_clear", seed=1)
    poses = run.poses
    featurizer = Featurizer(recognition_config())
    keyframes: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def keyframe(i: int) -> tuple[np.ndarray, np.ndarray]:
        if i not in keyframes:
            points = run.scan(i).points[:, :3]
            # the town's streets are all at right angles: a heading of its own per keyframe makes
            # the relative yaws arbitrary, as on real recordings (and the heading search earn its keep)
            turn = yaw_guess(np.random.default_rng([seed, i]).uniform(-math.pi, math.pi))
            frame = turn @ featurizer.frame(points).matrix
            keyframes[i] = (verification_cloud(points, frame, VOXEL_M), frame)
        return keyframes[i]

    def pair(q: int, m: int, revisit: bool) -> KeyframePair:
        (query, query_frame), (match, match_frame) = keyframe(q), keyframe(m)
        return KeyframePair(query, match, query_frame, match_frame, np.linalg.inv(poses[q]) @ poses[m], revisit)

    same_way, other_way = [], []
    for q in range(len(run) - 1, _SAME_PASS, -2):
        gaps = np.linalg.norm(poses[:q - _SAME_PASS, :2, 3] - poses[q, :2, 3], axis=1)
        near = np.flatnonzero((gaps > REVISIT_M[0]) & (gaps < REVISIT_M[1]))
        if len(near):
            m = int(near[np.argmin(gaps[near])])
            turn = np.linalg.inv(poses[q]) @ poses[m]
            reversed_ = abs(math.degrees(math.atan2(turn[1, 0], turn[0, 0]))) > REVERSED_DEG
            (other_way if reversed_ else same_way).append((q, m))
    chosen = other_way[:revisits // 2]
    chosen += same_way[:revisits - len(chosen)]
    rng = np.random.default_rng(seed)
    far = []
    while len(far) < unrelated:
        q, m = (int(i) for i in rng.integers(0, len(run), 2))
        if np.linalg.norm(poses[q, :2, 3] - poses[m, :2, 3]) > UNRELATED_M:
            far.append((q, m))
    return [pair(q, m, True) for q, m in chosen] + [pair(q, m, False) for q, m in far]


def measure(pairs: list[KeyframePair] | None = None, repeats: int = 3) -> dict[str, Any]:
    """CPU milliseconds per candidate of each stage (mean over ``repeats`` passes over ``pairs``),
    for revisits and unrelated places apart, and for a query whose preparation is shared
    (:func:`~vbrl_ros.detection.candidate_verification.query_verifier`, as for a query's second and later
    candidates); the decisions and pose errors of the last pass."""
    pairs = keyframe_pairs() if pairs is None else pairs
    settings = DetectorSettings(verification_voxel=VOXEL_M)
    stages: list[dict[str, float]] = [{} for _ in pairs]
    shared: list[dict[str, float]] = [{} for _ in pairs]
    cpu, cpu_shared, wall = np.zeros(len(pairs)), np.zeros(len(pairs)), np.zeros(len(pairs))
    for _ in range(repeats):
        outcomes = []
        for i, p in enumerate(pairs):
            start, start_cpu = time.perf_counter(), time.process_time()
            check = verify_loop(p.query, p.match, voxel_size=VOXEL_M, max_threads=1,
                                max_closure_distance=settings.max_closure_distance, timings=stages[i],
                                query_sensor=p.query_frame, match_sensor=p.match_frame)
            cpu[i] += 1e3 * (time.process_time() - start_cpu)
            wall[i] += 1e3 * (time.perf_counter() - start)
            T, _ = to_sensor_frames(check, p.query_frame, p.match_frame)
            outcomes.append((closure_rejection(check, T, settings), check.fitness, *_pose_error(T, p.truth)))
            verifier = query_verifier(p.query, settings, max_threads=1, sensor=p.query_frame)
            # another candidate first: the query's side is ready
            verifier.verify(pairs[i - 1].match, sensor=pairs[i - 1].match_frame)
            start_cpu = time.process_time()
            verifier.verify(p.match, timings=shared[i], sensor=p.match_frame)
            cpu_shared[i] += 1e3 * (time.process_time() - start_cpu)
    revisit = np.array([p.revisit for p in pairs])
    columns = {"revisits": (revisit, stages, cpu), "unrelated": (~revisit, stages, cpu),
               "all": (np.ones_like(revisit), stages, cpu), "all, query shared": (np.ones_like(revisit), shared, cpu_shared)}
    names = list(dict.fromkeys(stage for timings in stages for stage in timings))
    return {
        "pairs": len(pairs), "repeats": repeats,
        "points": float(np.mean([len(p.query) for p in pairs])),
        "cpu_ms": {column: {**{stage: sum(timings[i].get(stage, 0.0) for i in np.flatnonzero(chosen))
                                / (repeats * chosen.sum()) for stage in names},
                            "total": float(totals[chosen].mean() / repeats)}
                   for column, (chosen, timings, totals) in columns.items()},
        "wall_ms": float(wall.mean() / repeats),
        "accuracy": _accuracy(pairs, outcomes, settings.min_fitness),
    }


def _pose_error(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(truth) @ T
    angle = math.degrees(math.acos(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(D[:3, 3])), angle


def _accuracy(pairs: list[KeyframePair], outcomes: list[tuple], min_fitness: float) -> dict[str, Any]:
    revisit = np.array([p.revisit for p in pairs])
    accepted = np.array([why is None for why, *_ in outcomes])
    fitness = np.array([f for _, f, _, _ in outcomes])
    errors = np.array([(t, r) for *_, t, r in outcomes])
    right = accepted & revisit
    return {
        "min_fitness": min_fitness,
        "revisits": int(revisit.sum()), "reversed": int(sum(p.reversed for p in pairs if p.revisit)),
        "revisits_accepted": int(right.sum()),
        "unrelated": int((~revisit).sum()), "unrelated_accepted": int((accepted & ~revisit).sum()),
        "translation_error_m": _spread(errors[right, 0]), "rotation_error_deg": _spread(errors[right, 1]),
        "revisit_fitness": _spread(fitness[revisit]), "unrelated_fitness": _spread(fitness[~revisit]),
        "decisions": [why for why, *_ in outcomes],
    }


def _spread(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {"min": math.nan, "median": math.nan, "max": math.nan}
    return {"min": float(np.min(values)), "median": float(np.median(values)), "max": float(np.max(values))}


def format_table(results: dict[str, Any]) -> str:
    cpu = results["cpu_ms"]
    header = ("stage (CPU ms per candidate)", *cpu)
    rows = [(stage, *(f"{cpu[column].get(stage, 0.0):.1f}" for column in cpu)) for stage in cpu["all"]]
    widths = [max(len(row[i]) for row in (header, *rows)) for i in range(len(header))]

    def line(row: tuple[str, ...]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))

    a = results["accuracy"]
    t, r = a["translation_error_m"], a["rotation_error_deg"]
    return "\n".join([
        (f"verification: {results['pairs']} simulated 64-beam keyframe pairs (~{results['points']:.0f} points "
         f"each), {results['repeats']} passes, one thread"),
        line(header), "  ".join("-" * w for w in widths), *map(line, rows),
        f"wall-clock per candidate, mean: {results['wall_ms']:.1f} ms",
        (f"accepted at min_fitness {a['min_fitness']}: {a['revisits_accepted']}/{a['revisits']} revisits "
         f"({a['reversed']} reversed), {a['unrelated_accepted']}/{a['unrelated']} unrelated places"),
        (f"pose error of accepted revisits: median {100 * t['median']:.1f} cm / {r['median']:.2f} deg, "
         f"max {100 * t['max']:.1f} cm / {r['max']:.2f} deg"),
        (f"fitness: revisits min {a['revisit_fitness']['min']:.2f}, median {a['revisit_fitness']['median']:.2f}; "
         f"unrelated places max {a['unrelated_fitness']['max']:.2f}"),
    ])
