"""The featurizer's and the solver's speed targets (docs/design.md §5), measured.

Figures are medians over repeated runs in one process; :func:`format_table`
prints them beside their targets. ``vbrl bench`` runs this and
:mod:`vbrl_ros.bench.index`.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.index.translation_search import view_offsets
from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config

BENCH_POINTS = 120_000


def median_seconds(func: Callable[[], Any], repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        func()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def benchmark_scan(n_points: int = BENCH_POINTS, seed: int = 0) -> np.ndarray:
    """A real 64-beam scan of the simulated town, trimmed to exactly ``n_points`` (float32).

    2400 columns give ~130k returns at a street corner; a random subset
    keeps the benchmark input the same size whatever the town looks like.
    """
    from vbrl_ros.simulator import LidarConfig, RouteConfig, generate_town, make_route, simulate_run

    town = generate_town(seed=seed)
    route = make_route(town, RouteConfig(loops=1, max_scans=1))
    points = simulate_run(town, route, LidarConfig(beams=64, columns=2400), "summer_clear",
                          seed=seed).scan(0).points[:, :3]
    rng = np.random.default_rng(seed)
    index = rng.choice(len(points), size=n_points, replace=len(points) < n_points)
    return points[index].astype(np.float32)


def measure(repeats: int = 30, config: VBRLConfig | None = None) -> dict[str, Any]:
    from vbrl_ros.bench.solver import time_one_iteration

    featurizer = Featurizer(config)
    scan = benchmark_scan()
    describe_s = median_seconds(lambda: featurizer.describe(scan), repeats)
    # the polar grid has ~2.6x the occupied voxels: same budget
    polar = Featurizer(VBRLConfig(grid=VoxelGridConfig(kind="polar")))
    polar_s = median_seconds(lambda: polar.describe(scan), repeats)
    # the built-in model's descriptor as the node computes it per keyframe: level the scan on
    # its ground, then describe it from every translation-search viewpoint
    recognition = Featurizer(recognition_config())
    offsets = view_offsets(RECOGNITION_TRANSLATION_SEARCH_M)
    recognition_s = median_seconds(
        lambda: recognition.describe_views(scan, offsets, recognition.frame(scan)), repeats)
    solver = time_one_iteration(n=700, d=featurizer.dimension)
    return {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "numpy": np.__version__, "blas_threads": _blas_threads()},
        "describe": {"points": len(scan), "dimension": featurizer.dimension,
                     "median_ms": 1e3 * describe_s, "target_ms": 10.0},
        "describe_polar": {"points": len(scan), "dimension": polar.dimension,
                           "median_ms": 1e3 * polar_s, "target_ms": 10.0},
        "describe_recognition": {"points": len(scan), "dimension": recognition.dimension,
                                 "views": len(offsets), "median_ms": 1e3 * recognition_s,
                                 "target_ms": 10.0},
        "solver_iteration": {"n": 700, "d": featurizer.dimension, **solver},
    }


def format_table(results: dict[str, Any]) -> str:
    s = results["solver_iteration"]
    rows = [
        (f"describe one scan{suffix}", f"{d['points']:,} points -> d={d['dimension']}",
         f"{d['median_ms']:.2f} ms", f"<= {d['target_ms']:.0f} ms",
         "ok" if d["median_ms"] <= d["target_ms"] else "MISSED")
        for suffix, d in (("", results["describe"]), (", polar grid", results["describe_polar"]),
                          (f", built-in (levelled, {results['describe_recognition']['views']} views)",
                           results["describe_recognition"]))
    ] + [
        ("solver iteration, fast path", f"n={s['n']}, d={s['d']} ({s['fast_path']})",
         f"{1e3 * s['fast_s']:.1f} ms", "", ""),
        ("solver iteration, literal d x d", f"n={s['n']}, d={s['d']}",
         f"{1e3 * s['literal_s']:.1f} ms", "", ""),
        ("speed-up (literal / fast)", "", f"{s['speedup']:.1f}x", "", ""),
    ]
    header = ("benchmark", "input", "median", "target", "")
    widths = [max(len(str(r[i])) for r in (header, *rows)) for i in range(len(header))]
    line = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    m = results["machine"]
    footer = f"({m['cpus']} CPUs, Python {m['python']}, numpy {m['numpy']}, BLAS threads: {m['blas_threads']})"
    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows), footer])


def _blas_threads() -> str:
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        if os.environ.get(name):
            return f"{os.environ[name]} ({name})"
    return "library default"


