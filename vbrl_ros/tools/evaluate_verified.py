"""``vbrl eval --verify``: the verified output of the full model and of Scan Context, side by side.

Both methods' top-k go through the node's own verification
(:mod:`vbrl_ros.evaluation.verified`); the verified closures are scored by the same protocol
as retrieval, swept over fitness and at the node's settings.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vbrl_ros.detection.settings import DetectorSettings, SettingsError
from vbrl_ros.evaluation.methods import ScanContextMethod, SourceDescriptors
from vbrl_ros.evaluation.metrics import RetrievalMetrics
from vbrl_ros.evaluation.missed import MISSED_REASONS, missed_revisits
from vbrl_ros.evaluation.retrieval import RetrievalResults
from vbrl_ros.evaluation.verified import Candidates, OperatingPoint, VerifiedCandidates
from vbrl_ros.evaluation.verified_output import Score, VerificationInputs, VerifiedOutput, verified_output
from vbrl_ros.tools.evaluate_output import cell
from vbrl_ros.training.ablations import FULL_NAME

VERIFIED_SUFFIX = ", verified"
SCAN_CONTEXT = ScanContextMethod.name
NODE_DEFAULTS = DetectorSettings()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``vbrl eval``'s --verify options, defaulting to the node's own settings."""
    verify = parser.add_argument_group(
        "verified output", "--verify registers the full model's and Scan Context's top-k candidates "
        "with KISS-ICP as the node does and reports the verified closures beside retrieval: swept "
        "over fitness (best verified candidate per query), and at the node's settings")
    verify.add_argument("--verify", action="store_true", help="evaluate the verified output too")
    verify.add_argument("--verify-top-k", type=int, default=NODE_DEFAULTS.top_k, metavar="K",
                        help="candidates verified per query, as the node's top_k")
    verify.add_argument("--min-fitness", type=float, nargs="+", default=[NODE_DEFAULTS.min_fitness],
                        metavar="F", help="the node's min_fitness: an operating point for each value")
    verify.add_argument("--distance-threshold", type=float, default=None, metavar="D",
                        help="VBRL: verify only candidates at or below this distance, for the "
                             "operating point (default: every one of the top-k, as the node)")
    verify.add_argument("--max-closure-distance", type=float,
                        default=NODE_DEFAULTS.max_closure_distance, metavar="M",
                        help="the node's max_closure_distance, metres")
    verify.add_argument("--submap-keyframes", type=int, default=NODE_DEFAULTS.submap_keyframes, metavar="N",
                        help="the node's submap_keyframes: neighbours merged into each verified cloud by the "
                             "source's poses (0: single scans)")
    verify.add_argument("--odometry-drift", type=float, default=NODE_DEFAULTS.odometry_drift, metavar="S",
                        help="the node's odometry_drift: P1 candidates the source's poses place farther than "
                             "max_closure_distance + 5 m + S x the path between them are rejected unverified, "
                             "the rest registered at headings within 45 degrees of the poses' (0: off)")


@dataclass
class VerifiedOutputs:
    """Per method: the operating points at the node's settings (by min_fitness, then radius), the
    distance threshold it used, and the best verified candidate per query (for the matches dump)."""

    settings: DetectorSettings
    min_fitness: tuple[float, ...]
    points: dict[str, dict[float, dict[float, OperatingPoint]]] = field(default_factory=dict)
    thresholds: dict[str, float] = field(default_factory=dict)
    best: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    checked: dict[str, tuple[Candidates, VerifiedCandidates]] = field(default_factory=dict)
    # per method, min_fitness and radius: the revisits it did not publish, by cause (evaluation.missed)
    missed: dict[str, dict[float, dict[float, dict[str, int]]]] = field(default_factory=dict)

    def summary(self, metrics: dict[str, dict[float, RetrievalMetrics]]) -> dict[str, Any]:
        return {
            "settings": {"top_k": self.settings.top_k, "min_fitness": list(self.min_fitness),
                         "max_closure_distance": self.settings.max_closure_distance,
                         "verification_voxel": self.settings.verification_voxel,
                         "odometry_drift": self.settings.odometry_drift},
            "distance_threshold": self.thresholds,
            "fitness_at_max_f1": {name: {f"{r:g}": 1.0 - m.threshold_at_max_f1 for r, m in by_r.items()}
                                  for name, by_r in metrics.items() if name.endswith(VERIFIED_SUFFIX)},
            "at_node_settings": {name: {f"{f:g}": {f"{r:g}": p.summary() for r, p in by_r.items()}
                                        for f, by_r in by_fitness.items()}
                                 for name, by_fitness in self.points.items()},
            "missed_revisits": {name: {f"{f:g}": {f"{r:g}": counts for r, counts in by_r.items()}
                                       for f, by_r in by_fitness.items()}
                                for name, by_fitness in self.missed.items()},
        }


def check_arguments(args: argparse.Namespace) -> None:
    if args.distance_threshold is not None and not (math.isfinite(args.distance_threshold)
                                                    and args.distance_threshold >= 0):
        raise ValueError("--distance-threshold must be a number >= 0")
    for fitness in args.min_fitness:
        settings(args, fitness)  # the detector's own checks name the setting


def settings(args: argparse.Namespace, min_fitness: float) -> DetectorSettings:
    """The node's acceptance rule from the options; a bad one is named with the detector's rule."""
    options = {"top_k": ("--verify-top-k", args.verify_top_k), "min_fitness": ("--min-fitness", min_fitness),
               "max_closure_distance": ("--max-closure-distance", args.max_closure_distance),
               "submap_keyframes": ("--submap-keyframes", args.submap_keyframes),
               "odometry_drift": ("--odometry-drift", args.odometry_drift)}
    for name, (option, value) in options.items():
        try:
            DetectorSettings(**{name: value})
        except SettingsError as error:
            raise ValueError(f"{option}: {error}") from None
    return DetectorSettings(**{name: value for name, (_, value) in options.items()})


def verify_outputs(args: argparse.Namespace, queries: SourceDescriptors, database: SourceDescriptors,
                   score: Score, metrics: dict[str, dict[float, RetrievalMetrics]],
                   retrieved: dict[str, tuple[Any, RetrievalResults]],
                   truth: tuple[np.ndarray, np.ndarray] | None = None) -> VerifiedOutputs:
    """Verify the full model's and Scan Context's candidates; adds a ``"<method>, verified"``
    row (swept over fitness) to ``metrics`` for each. ``database`` is ``queries`` for P1;
    ``score``: the protocol's metrics at every radius; ``truth``: the queries' and the stored
    keyframes' true positions, in the stored keyframes' frame, to tell why revisits were missed."""
    rule = settings(args, args.min_fitness[0])
    outputs = VerifiedOutputs(rule, tuple(sorted(set(args.min_fitness))))
    inputs = VerificationInputs.of(queries, database, rule)  # merged once, verified for every method
    for name, (_, results) in retrieved.items():
        if name not in (FULL_NAME, SCAN_CONTEXT):
            continue  # ablations: retrieval only
        # as the node: with verification, no distance threshold unless one is given
        threshold = args.distance_threshold if name == FULL_NAME and args.distance_threshold else math.inf
        output = verified_output(inputs, results, rule, score, min_fitness=outputs.min_fitness,
                                 distance_threshold=threshold, workers=args.workers, progress=not args.quiet,
                                 description=f"verifying {name}")
        outputs.checked[name] = (output.candidates, output.verified)
        metrics[name + VERIFIED_SUFFIX] = output.swept
        outputs.best[name] = best_entries(output)
        outputs.points[name] = output.points
        outputs.thresholds[name] = threshold
        if truth is not None:
            outputs.missed[name] = {
                fitness: {r: missed_revisits(*truth, results.database_limit, output.candidates, output.verified,
                                             output.published[fitness], r, fitness) for r in by_radius}
                for fitness, by_radius in output.points.items()}
    return outputs


def best_entries(output: VerifiedOutput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query the best verified candidate's (keyframe published to, distance, fitness): the
    keyframe nearest the query along the registered one's path, and the registered one's
    distance and fitness; without one, retrieval's own top-1 and fitness NaN."""
    candidates, (indices, _) = output.candidates, output.best
    fallback = candidates.indices[:, 0]
    rows = np.arange(len(indices))
    position = np.argmax(candidates.indices == indices, axis=1)
    fitness = output.verified.fitness[rows, position]
    found = indices[:, 0] >= 0
    return (np.where(found, output.best_nearest[:, 0], fallback),
            np.where(found, candidates.distances[rows, position], candidates.distances[:, 0]),
            np.where(found, fitness, math.nan))


def format_points(outputs: VerifiedOutputs, radii: list[float]) -> str:
    rule = outputs.settings
    fitness = ", ".join(f"{f:g}" for f in outputs.min_fitness)
    lines = [(f"at the node's settings (top {rule.top_k}, min_fitness {fitness}, "
              f"max_closure_distance {rule.max_closure_distance:g} m, odometry_drift {rule.odometry_drift:g})")]
    for r in radii:
        lines.append(f"radius {r:g} m")
        lines.append(f"  {'method':<24s} {'min_fitness':>11s} {'accepted':>8s} {'precision':>9s} {'recall':>7s} "
                     f"{'F1':>7s}")
        for name, by_fitness in outputs.points.items():
            for min_fitness, by_radius in by_fitness.items():
                p = by_radius[r]
                lines.append(f"  {name:<24s} {min_fitness:>11g} {p.accepted:>8d} {cell(p.precision, 9)} "
                             f"{cell(p.recall)} {cell(p.f1)}")
    if outputs.missed:
        lines.append("revisits not published there, by why (evaluation/missed.py)")
        for r in radii:
            lines.append(f"radius {r:g} m")
            lines.append(f"  {'method':<24s} {'min_fitness':>11s} {'missed':>6s} "
                         + " ".join(f"{reason:>{len(reason)}s}" for reason in MISSED_REASONS))
            for name, by_fitness in outputs.missed.items():
                for min_fitness, by_radius in by_fitness.items():
                    counts = by_radius[r]
                    lines.append(f"  {name:<24s} {min_fitness:>11g} {sum(counts.values()):>6d} "
                                 + " ".join(f"{counts[reason]:>{len(reason)}d}" for reason in MISSED_REASONS))
    return "\n".join(lines)


def matches_entries(outputs: VerifiedOutputs, name: str, database_limit: np.ndarray) -> list[dict[str, Any]]:
    """``[{"query", "match", "distance", "fitness", ...}]`` of the best verified candidate (fitness
    NaN when none was verified: match and distance are then retrieval's top-1), and every
    verified candidate with its fitness and the rule's verdict (null: accepted at fitness 0)."""
    match, distance, fitness = outputs.best[name]
    candidates, verified = outputs.checked[name]
    entries = []
    for q in np.flatnonzero(database_limit > 0):
        listed = candidates.indices[q] >= 0
        entries.append({
            "query": int(q), "match": int(match[q]),
            "distance": float(distance[q]) if math.isfinite(distance[q]) else None,
            "fitness": float(fitness[q]),
            "candidates": [int(j) for j in candidates.indices[q][listed]],
            "candidate_distances": [float(d) for d in candidates.distances[q][listed]],
            "candidate_fitness": [float(f) for f in verified.fitness[q][listed]],
            "candidate_rejection": [verified.rejection[q, r] for r in np.flatnonzero(listed)],
        })
    return entries
