"""``vbrl bench`` index section: query + insert at 1k / 10k / 100k keyframes (docs/design.md §5).

For the Cartesian descriptor (the shipped paper-configuration model, d ~ 7.9k, S = 1) and a polar one
(S = 24, d ~ 15.7k active; see :mod:`vbrl_ros.bench.descriptors` for how it
is made without a trained polar model) and both storages, a database is grown
to each size from real simulated descriptors (:func:`replicate`) and timed:

- ``query_insert_ms``: median (and p95) of one indexed query (top 5, the
  node's recency mask) followed by one insert, on one core;
- ``brute_force_query_ms``: the linear scan the index replaces (every
  keyframe, every shift), timed on at most ``_BRUTE_FORCE_ROWS`` keyframes and
  scaled linearly to n;
- ``recall_at_1_vs_exact``: how often the indexed top-1 is the brute-force
  top-1, for queries that revisit a stored keyframe with fresh noise (polar:
  also rotated by a random number of sectors; ``yaw_correct`` is how often the
  returned shift undoes that rotation) — easy queries, an upper bound;
- ``cross_season`` (float32): the same for real winter queries of the drive
  against the grown summer database — top-1 agreement and Recall@1 (within
  3 m) of index and brute force; the hard, realistic case (the same 40
  queries at every size; skipped where brute force would scan more than
  ``_CROSS_SEASON_WORK`` descriptor values x shifts per query), and the
  agreement among the padding alone (:func:`winter_comparison`);
- bytes per keyframe (descriptor, key, yaw key, metadata, place).

``drive`` repeats the comparison on the real drive itself (winter queries
against the summer database, the paper's cross-season protocol): top-1
agreement and Recall@1 (match within 3 m) of index and brute force, and for
polar the error of the yaw against the poses. ``pruning`` reports what a
near-zero prune of the paper model's learned weights saves and what it
costs in Recall@1 against unpruned brute force.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from typing import Any

import numpy as np

from vbrl_ros.bench import descriptors as bd
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.model.scoring import WeightedL1Scorer

DEFAULT_SIZES = (1_000, 10_000, 100_000)
STORAGES = ("float32", "float16")
PRUNE = 0.0001
REVISIT_RADIUS_M = 3.0
_BRUTE_FORCE_ROWS = 10_000  # brute force is timed on at most this many keyframes, then scaled
_EXACT_BUDGET = 1.5e10  # descriptor values x shifts the recall check may scan per size
_CROSS_SEASON_QUERIES = 40
# per-query brute-force work (n x d x S) up to which the real queries are checked: a
# fixed rule, not a time budget, so the same queries are checked on any machine
# (~0.7-1.3 s per query at 10k polar / 100k Cartesian; 100k polar, 8-9 s, is skipped)
_CROSS_SEASON_WORK = 6e9


def measure(sizes: tuple[int, ...] = DEFAULT_SIZES, repeats: int = 50, seed: int = 0,
            polar_model: Any = None, polar_model_name: str | None = None) -> dict[str, Any]:
    """All figures of the index section as a JSON-ready dict.

    ``polar_model``: a trained polar model for the polar rows (default: the
    stand-in of :func:`bd.polar_set`); ``polar_model_name`` labels it.
    """
    scans = bd.simulated_scans(spacing_m=3.0)
    sets = {"cartesian": bd.cartesian_set(scans),
            # a trained model's rows as the node stores them (its default weight_prune)
            "polar": bd.polar_set(scans, seed=seed, model=polar_model,
                                  prune=PRUNE if polar_model is not None else 0.0)}
    label = ("stand-in (no trained model)" if polar_model is None
             else f"{polar_model_name or 'trained model'} (weight_prune {PRUNE}, as the node stores it)")
    results: dict[str, Any] = {"sizes": list(sizes), "repeats": repeats, "drive_scans": len(scans),
                               "polar_model": label,
                               "shapes": {}}
    for name, data in sets.items():
        params = asdict(KeyframeIndex(data.weights, IndexParameters(sectors=data.sectors)).parameters)
        results["shapes"][name] = {
            "d_active": data.descriptors.shape[1], "sectors": data.sectors, "params": params,
            "memory": {s: _memory(data.scorer, s) for s in STORAGES},
            "drive": drive_comparison(data, data),
            "scale": _scale(data, sizes, repeats, seed),
        }
    results["pruning"] = _pruning(scans, sets["cartesian"])
    return results


def _memory(scorer: WeightedL1Scorer, storage: str) -> dict[str, int]:
    database = KeyframeDatabase(scorer, "bench", IndexParameters(storage=storage))
    parts = database.bytes_breakdown()
    return {**parts, "total": sum(parts.values()), "all_round": database.all_round_bytes_per_keyframe()}


def drive_comparison(data: bd.DescriptorSet, reference: bd.DescriptorSet) -> dict[str, Any]:
    """Winter queries against the summer drive: index on ``data`` vs brute force on ``reference``."""
    database, queries = np.flatnonzero(data.session == 0), np.flatnonzero(data.session == 1)
    index = KeyframeIndex(data.weights, IndexParameters(sectors=data.sectors))
    index.add_batch(data.descriptors[database])
    exact = (index if reference is data
             else KeyframeIndex(reference.weights, IndexParameters(sectors=reference.sectors)))
    if exact is not index:
        exact.add_batch(reference.descriptors[database])
    positions = data.poses[:, :2, 3]
    agree = correct_index = correct_exact = 0
    yaw_errors = []
    for q in queries:
        got = index.search_with_yaw(data.descriptors[q], 1)
        ref = exact.search_with_yaw(reference.descriptors[q], 1, exact=True)
        agree += got.indices[0] == ref.indices[0]
        match = database[got.indices[0]]
        correct_index += np.linalg.norm(positions[match] - positions[q]) < REVISIT_RADIUS_M
        correct_exact += np.linalg.norm(positions[database[ref.indices[0]]] - positions[q]) < REVISIT_RADIUS_M
        if data.sectors > 1 and np.linalg.norm(positions[match] - positions[q]) < REVISIT_RADIUS_M:
            truth = bd.relative_yaw(data.poses, q, match)
            yaw_errors.append(abs(math.remainder(got.yaws[0] - truth, 2 * math.pi)))
    out = {"database": len(database), "queries": len(queries),
           "top1_agreement": agree / len(queries),
           "recall_at_1_index": correct_index / len(queries),
           "recall_at_1_exact": correct_exact / len(queries)}
    if yaw_errors:
        out["yaw_error_deg_median"] = math.degrees(float(np.median(yaw_errors)))
        out["yaw_error_deg_p95"] = math.degrees(float(np.percentile(yaw_errors, 95)))
    return out


def _queries(data: bd.DescriptorSet, index: KeyframeIndex, count: int,
             rng: np.random.Generator) -> list[tuple[int, np.ndarray, int]]:
    """(stored keyframe, query, sector roll) revisits: fresh noise, polar rotated by whole sectors."""
    out = []
    for target in rng.integers(0, len(index), count):
        x = index.descriptor(int(target)) + 0.1 * rng.standard_normal(index.dimension).astype(np.float32)
        roll = int(rng.integers(0, data.sectors))
        out.append((int(target), np.roll(x.reshape(data.sectors, -1), roll, axis=0).ravel(), roll))
    return out


class _Feed:
    """Hands out the rows of :func:`bd.replicate` in any batch sizes."""

    def __init__(self, base: np.ndarray, total: int, seed: int) -> None:
        self._chunks = bd.replicate(base, total, seed=seed)
        self._pending = np.empty((0, base.shape[1]), np.float32)

    def take(self, count: int, copy: bool = True) -> np.ndarray:
        """``count`` rows; ``copy=False`` may return a view the next call overwrites."""
        if not len(self._pending):
            self._pending = next(self._chunks)  # a view of the generator's reused buffer
        if count <= len(self._pending) and not copy:
            out, self._pending = self._pending[:count], self._pending[count:]
            return out
        parts = []
        while count > 0:
            if not len(self._pending):
                self._pending = next(self._chunks)
            parts.append(self._pending[:count].copy())
            count -= len(parts[-1])
            self._pending = self._pending[len(parts[-1]) :]
        return np.concatenate(parts)


def _scale(data: bd.DescriptorSet, sizes: tuple[int, ...], repeats: int, seed: int) -> list[dict]:
    rows: list[dict[str, Any]] = [{"n": n} for n in sorted(sizes)]
    base = data.descriptors[data.session == 0]
    for storage in STORAGES:
        index = KeyframeIndex(data.weights, IndexParameters(sectors=data.sectors, storage=storage))
        total = max(sizes) + repeats * len(sizes)
        index.reserve(total)
        feed, rng = _Feed(base, total, seed), np.random.default_rng([seed, 7])
        for row in rows:
            start = time.perf_counter()
            while len(index) < row["n"]:
                index.add_batch(feed.take(min(4096, row["n"] - len(index)), copy=False))
            build_s = time.perf_counter() - start
            row[storage] = {**_time_and_recall(data, index, feed.take(repeats), rng),
                            "build_s": build_s}
            if storage == "float32":
                row.update(_brute_force(index, rng))
                row["cross_season"] = _cross_season(data, index)
        del index
    return rows


def _time_and_recall(data: bd.DescriptorSet, index: KeyframeIndex, inserts: np.ndarray,
                     rng: np.random.Generator) -> dict[str, Any]:
    queries = _queries(data, index, len(inserts), rng)
    index.search_with_yaw(queries[0][1], 5)  # compile outside the timing
    both, query_t, insert_t = [], [], []
    for (_, q, _), x in zip(queries, inserts):
        allowed = np.ones(len(index), bool)
        allowed[-50:] = False  # the node's recency exclusion
        t0 = time.perf_counter()
        index.search_with_yaw(q, 5, allowed)
        t1 = time.perf_counter()
        index.add(x)
        t2 = time.perf_counter()
        both.append(t2 - t0), query_t.append(t1 - t0), insert_t.append(t2 - t1)
    # exact search abandons most keyframes after one sector here: ~n * d per query
    n_recall = int(min(len(queries), max(5, _EXACT_BUDGET // (len(index) * index.dimension))))
    agree = yaw_ok = 0
    for target, q, roll in queries[:n_recall]:
        got = index.search_with_yaw(q, 1)
        ref = index.search_with_yaw(q, 1, exact=True)
        agree += got.indices[0] == ref.indices[0]
        yaw_ok += got.indices[0] == target and got.shifts[0] == roll
    ms = lambda t: 1e3 * float(np.median(t))  # noqa: E731
    return {"query_ms": ms(query_t), "insert_ms": ms(insert_t), "query_insert_ms": ms(both),
            "p95_query_insert_ms": 1e3 * float(np.percentile(both, 95)),
            "recall_at_1_vs_exact": agree / n_recall, "recall_queries": n_recall,
            "yaw_correct": yaw_ok / n_recall}


def _cross_season(data: bd.DescriptorSet, index: KeyframeIndex) -> dict[str, Any] | None:
    """:func:`winter_comparison` on the bench's fixed winter queries; ``None`` where brute
    force is too slow (``_CROSS_SEASON_WORK``)."""
    if len(index) * index.dimension * index.sectors > _CROSS_SEASON_WORK:
        return None
    count = _CROSS_SEASON_QUERIES
    winter = np.flatnonzero(data.session == 1)
    return winter_comparison(data, index, winter[:: max(1, len(winter) // count)][:count])


def winter_comparison(data: bd.DescriptorSet, index: KeyframeIndex,
                      picks: np.ndarray) -> dict[str, Any]:
    """Winter scans ``picks`` queried against ``index``, grown from the summer drive by
    :func:`bd.replicate` (keyframe i is mostly summer scan i % B and gets its position):
    top-1 agreement and Recall@1 (within 3 m) of the index and of brute force.

    On a grown database the nearest keyframe is almost always one of the B drive
    scans themselves, which carry no noise. ``top1_agreement_padding`` is the
    agreement with those masked out: the nearest of a place's noisy copies, which
    differ from one another only in noise and in which sectors were swapped — the
    hard case for a rotation-invariant key (``None`` without padding).
    """
    summer = np.flatnonzero(data.session == 0)
    positions = data.poses[:, :2, 3]
    where = positions[summer][np.arange(len(index)) % len(summer)]
    padding = np.arange(len(index)) >= len(summer)
    agree = right = right_exact = agree_padding = 0
    for q in picks:
        got = index.search(data.descriptors[q], 1)[0][0]
        ref = index.exact_search(data.descriptors[q], 1)[0][0]
        agree += got == ref
        right += np.linalg.norm(where[got] - positions[q]) < REVISIT_RADIUS_M
        right_exact += np.linalg.norm(where[ref] - positions[q]) < REVISIT_RADIUS_M
        if padding.any():
            agree_padding += (index.search(data.descriptors[q], 1, padding)[0][0]
                              == index.exact_search(data.descriptors[q], 1, padding)[0][0])
    return {"queries": len(picks), "top1_agreement": agree / len(picks),
            "top1_agreement_padding": agree_padding / len(picks) if padding.any() else None,
            "recall_at_1_index": right / len(picks), "recall_at_1_exact": right_exact / len(picks)}


def _brute_force(index: KeyframeIndex, rng: np.random.Generator) -> dict[str, Any]:
    """The plain linear scan over every keyframe and shift (what the index replaces)."""
    from vbrl_ros.model.distance_kernels import min_over_shifts

    n = len(index)
    rows = np.arange(min(n, _BRUTE_FORCE_ROWS), dtype=np.int64)
    distances = np.empty(len(rows), np.float32)
    shifts = np.empty(len(rows), np.int64)
    store = index.descriptors()
    # compile outside the timing: on a fresh install the first call is JIT
    # compilation (seconds), which would dwarf the brute-force timing
    min_over_shifts(store, rows[:1], index.descriptor(0), index.column_weights, index.sectors,
                    distances, shifts)
    times = []
    for _ in range(3):
        q = index.descriptor(int(rng.integers(0, n)))
        t0 = time.perf_counter()
        min_over_shifts(store, rows, q, index.column_weights, index.sectors, distances, shifts)
        np.argpartition(distances, min(5, len(rows) - 1))
        times.append(time.perf_counter() - t0)
    return {"brute_force_query_ms": 1e3 * float(np.median(times)) * n / len(rows),
            "brute_force_timed_rows": len(rows)}


def _pruning(scans: list, full: bd.DescriptorSet) -> dict[str, Any]:
    pruned = bd.cartesian_set(scans, prune=PRUNE)
    return {
        "prune": PRUNE,
        "active_rows": {"0": full.descriptors.shape[1], str(PRUNE): pruned.descriptors.shape[1]},
        "bytes_per_keyframe": {
            "0": {s: _memory(full.scorer, s)["total"] for s in STORAGES},
            str(PRUNE): {s: _memory(pruned.scorer, s)["total"] for s in STORAGES},
        },
        "drive_vs_unpruned_exact": drive_comparison(pruned, full),
    }


def format_table(results: dict[str, Any]) -> str:
    """The index section as text tables."""
    header = ("shape", "keyframes", "storage", "query+insert (p95)", "brute force",
              "top-1 = brute (revisits)", "yaw ok", "real queries: top-1 = brute, R@1 (brute)",
              "same, padding only", "B/keyframe")
    rows = []
    for name, shape in results["shapes"].items():
        for row in shape["scale"]:
            for storage in STORAGES:
                r = row[storage]
                rows.append((
                    name, f"{row['n']:,}", storage,
                    f"{r['query_insert_ms']:.2f} ms ({r['p95_query_insert_ms']:.2f})",
                    f"{row['brute_force_query_ms']:.0f} ms" if storage == "float32" else "",
                    f"{r['recall_at_1_vs_exact']:.3f}/{r['recall_queries']}",
                    f"{r['yaw_correct']:.3f}" if shape["sectors"] > 1 else "",
                    _cross_cell(row.get("cross_season")) if storage == "float32" else "",
                    _padding_cell(row.get("cross_season")) if storage == "float32" else "",
                    str(shape["memory"][storage]["total"]),
                ))
    lines = _render(header, rows)
    lines.append(f"polar weights: {results.get('polar_model', 'stand-in (no trained model)')}")
    for name, shape in results["shapes"].items():
        m, d = shape["memory"]["float32"], shape["drive"]
        yaw = (f", yaw error median {d['yaw_error_deg_median']:.1f} deg"
               if "yaw_error_deg_median" in d else "")
        lines.append(
            f"{name}: d={shape['d_active']} S={shape['sectors']}; bytes/keyframe float32 = "
            f"{m['descriptor']} descriptor + {m['key']} key + {m['yaw_key']} yaw key + "
            f"{m['metadata']} metadata + {m['place']} place + {m['sees_all_round']} flag "
            f"(+ {m['all_round']} if also described all round); "
            f"drive ({d['queries']} winter queries vs {d['database']}): "
            f"top-1 = brute force {d['top1_agreement']:.3f}, Recall@1 {d['recall_at_1_index']:.3f} "
            f"(brute force {d['recall_at_1_exact']:.3f}){yaw}")
    p = results["pruning"]
    b, d = p["bytes_per_keyframe"], p["drive_vs_unpruned_exact"]
    lines.append(
        f"prune {p['prune']} of the paper model's weights: {p['active_rows']['0']} -> "
        f"{p['active_rows'][str(p['prune'])]} rows, bytes/keyframe float32 {b['0']['float32']} -> "
        f"{b[str(p['prune'])]['float32']}, float16 {b['0']['float16']} -> "
        f"{b[str(p['prune'])]['float16']}; drive top-1 = unpruned brute force "
        f"{d['top1_agreement']:.3f}, Recall@1 {d['recall_at_1_index']:.3f} "
        f"(unpruned {d['recall_at_1_exact']:.3f})")
    return "\n".join(lines)


def _cross_cell(c: dict[str, Any] | None) -> str:
    if c is None:
        return "(too slow to check)"
    return (f"{c['top1_agreement']:.2f}, {c['recall_at_1_index']:.2f} "
            f"({c['recall_at_1_exact']:.2f}) /{c['queries']}")


def _padding_cell(c: dict[str, Any] | None) -> str:
    if c is None or c["top1_agreement_padding"] is None:
        return ""
    return f"{c['top1_agreement_padding']:.2f}"


def _render(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(str(r[i])) for r in (header, *rows)) for i in range(len(header))]
    line = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return [line(header), "  ".join("-" * w for w in widths), *map(line, rows)]
