"""Benchmark of :mod:`vbrl_ros.keyframe_index` (DESIGN.md §5: query + insert at 100k <= 10 ms).

``measure()`` returns a dict; ``format_table()`` renders it. Run with::

    python -m vbrl_ros.index_bench [--sizes 1000 10000 100000]

Descriptors are synthetic but shaped like real ones: standardised (unit
variance) rows, a low-rank smooth trajectory component (consecutive keyframes
resemble each other, like a drive) plus per-row noise, scored with the default
model's learned Eq. 4 weights (d = 7872). Queries are revisits: an earlier
place's trajectory component with fresh noise (another session). Brute force
is what :class:`~vbrl_ros.database.KeyframeDatabase` does today: blocked
``WeightedL1Scorer.distances_compact`` over every keyframe, then a top-k
selection. Figures are medians on one core (set OMP/OPENBLAS threads to 1 to
be strict; the index's kernel is single-threaded anyway).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from typing import Any

import numpy as np

from vbrl_ros.keyframe_index import KeyframeIndex
from vbrl_ros.scoring import WeightedL1Scorer

_BLOCK_ELEMENTS = 4 * 1024 * 1024


def default_weights() -> np.ndarray:
    """The default model's active Eq. 4 weights (sum-normalised), or uniform 7872 if missing."""
    try:
        from vbrl_ros.default_model import load_default_model

        return load_default_model().scorer().active_weights
    except Exception:  # noqa: BLE001 - the benchmark still runs without the model file
        return np.full(7872, 1.0 / 7872, np.float32)


class SyntheticDrive:
    """Realistic-ish compact descriptors: smooth low-rank trajectory + per-row noise, unit variance."""

    def __init__(self, d: int, rank: int = 48, rho: float = 0.9, signal: float = 0.6,
                 seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        spectrum = 1.0 / (1.0 + np.arange(rank)) ** 0.7
        basis = rng.standard_normal((rank, d)) * spectrum[:, None]
        basis *= np.sqrt(signal) / np.sqrt((basis**2).sum(0, keepdims=True))
        self.basis = basis.astype(np.float32)
        self.noise = np.float32(np.sqrt(1.0 - signal))
        self.rank, self.rho, self.rng = rank, rho, rng
        self._z = rng.standard_normal(rank)
        self.latents: list[np.ndarray] = []

    def next_batch(self, m: int) -> np.ndarray:
        z = np.empty((m, self.rank))
        for i in range(m):
            self._z = self.rho * self._z + np.sqrt(1 - self.rho**2) * self.rng.standard_normal(self.rank)
            z[i] = self._z
        self.latents.append(z.astype(np.float32))
        return self._render(z.astype(np.float32))

    def revisit(self, index: int, drift: float = 0.2) -> np.ndarray:
        """Another session's view of keyframe ``index``: same place, new noise, slight change."""
        z = np.concatenate(self.latents)[index] if len(self.latents) > 1 else self.latents[0][index]
        z = z + drift * self.rng.standard_normal(self.rank).astype(np.float32)
        return self._render(z[None])[0]

    def _render(self, z: np.ndarray) -> np.ndarray:
        x = z @ self.basis
        x += self.noise * self.rng.standard_normal(x.shape, dtype=np.float32)
        return x


def _brute_force(scorer: WeightedL1Scorer, query: np.ndarray, templates: np.ndarray,
                 top_k: int) -> np.ndarray:
    out = np.empty(len(templates), np.float64)
    block = max(1, _BLOCK_ELEMENTS // templates.shape[1])
    for start in range(0, len(templates), block):
        out[start : start + block] = scorer.distances_compact(query, templates[start : start + block])
    return np.argpartition(out, top_k)[:top_k]


def _median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times))


def measure(sizes: tuple[int, ...] = (1_000, 10_000, 100_000), repeats: int = 50,
            recall_queries: int = 100, key_dim: int = 256, candidates: int = 128,
            top_k: int = 5, seed: int = 0) -> dict[str, Any]:
    weights = default_weights()
    d = len(weights)
    scorer = WeightedL1Scorer(weights.astype(np.float64))
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "numpy": np.__version__},
        "d": d, "key_dim": key_dim, "candidates": candidates, "top_k": top_k, "sizes": [],
    }
    for n in sizes:
        drive = SyntheticDrive(d, seed=seed)
        row: dict[str, Any] = {"n": n}
        for storage in ("float32", "float16"):
            drive = SyntheticDrive(d, seed=seed)
            index = KeyframeIndex(weights, key_dim=key_dim, candidates=candidates, storage=storage)
            index.reserve(n + repeats + 8)
            start = time.perf_counter()
            for chunk in range(0, n, 5_000):
                index.add_batch(drive.next_batch(min(5_000, n - chunk)))
            build_s = time.perf_counter() - start
            rng = np.random.default_rng(seed + 1)
            queries = [drive.revisit(int(i)) for i in rng.integers(0, n, repeats)]
            fresh = drive.next_batch(repeats)  # new places, inserted after their query
            index.search(queries[0], top_k)  # JIT warm-up
            search_t, insert_t, both_t = [], [], []
            for q, x in zip(queries, fresh):
                allowed = np.ones(len(index), bool)
                allowed[-50:] = False  # the node's recency exclusion
                t0 = time.perf_counter()
                index.search(q, top_k, allowed)
                t1 = time.perf_counter()
                index.add(x)
                t2 = time.perf_counter()
                search_t.append(t1 - t0)
                insert_t.append(t2 - t1)
                both_t.append(t2 - t0)
            # Recall@1 of the index against exact search, same stored data
            n_recall = recall_queries if n <= 10_000 else max(10, recall_queries // 5)
            picks = rng.integers(0, n, n_recall)
            agree_stored = agree_f32 = 0
            for i in picks:
                q = drive.revisit(int(i))
                got = index.search(q, 1)[0][0]
                agree_stored += got == index.exact_search(q, 1)[0][0]
                if storage == "float16":
                    # against exact float32 search on the original descriptors
                    exact32 = _brute_force(scorer, q, index.descriptors().astype(np.float32), 1)[0]
                    agree_f32 += got == exact32
            row[storage] = {
                "query_ms": _median_ms(search_t), "insert_ms": _median_ms(insert_t),
                "query_insert_ms": _median_ms(both_t),
                "p95_query_insert_ms": 1e3 * float(np.percentile(both_t, 95)),
                "recall_at_1_vs_exact": agree_stored / n_recall, "recall_queries": n_recall,
                "bytes_per_keyframe": index.bytes_per_keyframe(),
                "allocated_mb": index.nbytes() / 2**20, "build_s": build_s,
            }
            if storage == "float16":
                row[storage]["recall_at_1_vs_float32_exact"] = agree_f32 / n_recall
            if storage == "float32":
                templates = index.descriptors()
                reps = max(3, min(repeats, 200_000 // n))
                times = []
                for q in queries[:reps]:
                    t0 = time.perf_counter()
                    _brute_force(scorer, q, templates, top_k)
                    times.append(time.perf_counter() - t0)
                row["brute_force_query_ms"] = _median_ms(times)
            del index
        results["sizes"].append(row)
    results["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return results


def format_table(results: dict[str, Any]) -> str:
    header = ("keyframes", "brute force", "index f32 q+i (p95)", "index f16 q+i (p95)",
              "R@1 f32", "R@1 f16 (vs f32 exact)", "B/kf f32", "B/kf f16", "build f32")
    rows = []
    for r in results["sizes"]:
        a, b = r["float32"], r["float16"]
        rows.append((
            f"{r['n']:,}", f"{r['brute_force_query_ms']:.1f} ms",
            f"{a['query_insert_ms']:.2f} ms ({a['p95_query_insert_ms']:.2f})",
            f"{b['query_insert_ms']:.2f} ms ({b['p95_query_insert_ms']:.2f})",
            f"{a['recall_at_1_vs_exact']:.3f}/{a['recall_queries']}",
            f"{b['recall_at_1_vs_exact']:.3f} ({b['recall_at_1_vs_float32_exact']:.3f})",
            str(a["bytes_per_keyframe"]), str(b["bytes_per_keyframe"]), f"{a['build_s']:.1f} s",
        ))
    widths = [max(len(str(x[i])) for x in (header, *rows)) for i in range(len(header))]
    line = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    foot = (f"d={results['d']}, key_dim={results['key_dim']}, candidates={results['candidates']}, "
            f"top_k={results['top_k']}, peak RSS {results['peak_rss_mb']:.0f} MB")
    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows), foot])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--json", help="also write the figures as JSON")
    args = parser.parse_args(argv)
    results = measure(tuple(args.sizes), repeats=args.repeats)
    print(format_table(results))
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
