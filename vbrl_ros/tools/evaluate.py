"""``vbrl eval``: full VBRL, its three ablations and Scan Context, side by side (docs/design.md §3).

- one source: P1, online loop closure (query i against keyframes 0..i−E);
- ``--against DB``: P2, queries from the first source, database from DB;
  ``--align T.txt`` (4×4, query world frame -> database world frame) is used
  for the ground truth only.

Each source is read and described once (VBRL raw descriptor + Scan Context);
every VBRL variant re-uses the raw descriptors with its own standardisation
and weights. Matching uses poses only as the node uses odometry (a keyframe's trail,
sequences matched by place in P1); otherwise they are the ground truth.
Indices (JSON dump) are keyframe ordinals in source order; with the default
keyframe selection (every scan) they are the scan indices, otherwise each
entry also carries ``query_scan`` / ``match_scan``. Distances: lower = more similar.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vbrl_ros.evaluation.by_heading import HeadingRecall, format_heading_recall, recalls_by_heading
from vbrl_ros.evaluation.matches_json import matches_to_json
from vbrl_ros.evaluation.metrics import (
    RetrievalMetrics,
    apply_transform,
    correct_mask,
    evaluate_cross_session,
    evaluate_online,
)
from vbrl_ros.evaluation.retrieval import RetrievalResults, cross_session_retrieval, online_retrieval
from vbrl_ros.evaluation.verified import TOP_K_RETRIEVED, retrieval_width
from vbrl_ros.io.atomic import atomic_write
from vbrl_ros.model.model_file import VBRLModel, load_model
from vbrl_ros.tools import evaluate_arguments, evaluate_mounting, evaluate_scan_context, evaluate_verified
from vbrl_ros.tools.evaluate_arguments import DETECTOR_DEFAULTS
from vbrl_ros.tools.evaluate_output import format_table, json_safe, write_matches
from vbrl_ros.tools.evaluate_verified import SCAN_CONTEXT, VerifiedOutputs, verify_outputs
from vbrl_ros.training.ablations import FULL_NAME, discover_ablations

if TYPE_CHECKING:
    from vbrl_ros.evaluation.methods import SourceDescriptors

REPORT_RADII = (3.0, 5.0)  # docs/design.md §3: report 3 m and 5 m


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "eval", help="evaluate a model, its ablations and Scan Context (P1 / P2)",
        description="P1 (one SOURCE: online loop closure) or P2 (--against: cross-session) for the "
                    "full VBRL model, its ablations found next to it (MODEL.<ablation>.npz) and "
                    "Scan Context. Prints a table, writes JSON metrics, a PR-curve PNG and "
                    "optionally the per-query matches.",
    )
    evaluate_arguments.add_arguments(parser)
    parser.set_defaults(func=run)


def load_alignment(path: Path) -> np.ndarray:
    """A 4×4 homogeneous transform from a text file (16 numbers, 4 rows)."""
    try:
        T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise ValueError(f"--align {path}: not a numeric matrix ({' '.join(str(error).split())})") from None
    if T.shape != (4, 4):
        raise ValueError(f"--align {path}: expected a 4x4 matrix, got shape {T.shape[0]}x{T.shape[1]}")
    if not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"--align {path}: must be finite with last row 0 0 0 1")
    return T


def load_models(path: Path, with_ablations: bool) -> tuple[dict[str, VBRLModel], list[str]]:
    """The full model and its sibling ablations (same configuration required); notes on skips."""
    model = load_model(path)
    models, notes = {FULL_NAME: model}, []
    if with_ablations:
        found, missing = discover_ablations(path)
        for name, sibling in found.items():
            # Featurized once with the full model's configuration: a sibling of another
            # configuration cannot share the descriptors (stale file from another run?).
            models[name] = load_model(sibling, expected_config=model.config)
        notes += [f"ablation {name} skipped: no file next to the model" for name in missing]
    return models, notes


@dataclass
class Evaluation:
    """What ``vbrl eval`` compares: the methods, on the described sources, by the protocol."""

    protocol: str  # "P1" or "P2"
    queries: SourceDescriptors
    database: SourceDescriptors  # the queries themselves for P1
    models: dict[str, VBRLModel]
    methods: list[Any]
    notes: list[str]
    alignment: np.ndarray | None
    radii: list[float]
    trail_m: float = 0.0  # metres of keyframes merged into each one before VBRL describes it
    width: int = TOP_K_RETRIEVED  # candidates retrieved per query: enough for --verify-top-k's spares
    trail_ahead_m: float = 0.0  # metres of keyframes after each one merged in as well

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The queries' and the stored keyframes' true positions, in the stored keyframes' frame."""
        queries, database = self.queries.positions, self.database.positions
        if queries is None or database is None:
            return None
        return (queries if self.alignment is None else apply_transform(queries, self.alignment)), database

    def title(self, exclude: int) -> str:
        if self.protocol == "P1":
            return f"P1 {self.queries.name} (exclude {exclude})"
        return f"P2 {self.queries.name} -> {self.database.name}"


def run(args: argparse.Namespace) -> int:
    evaluate_arguments.check_arguments(args)
    evaluation = load(args)
    metrics, retrieved = evaluate_methods(args, evaluation)
    full_results = retrieved[FULL_NAME][1] if FULL_NAME in retrieved else None
    agreement = None
    if args.check_exact and full_results is not None:
        agreement = exact_agreement(args, evaluation, metrics, full_results)
    verified = None
    if args.verify:
        verified = verify_outputs(args, evaluation.queries, evaluation.database,
                                  lambda results: score(args, evaluation, results), metrics, retrieved,
                                  truth=evaluation.ground_truth())
    indices = {name: results.indices for name, (_, results) in retrieved.items()}
    exclude = args.exclude if evaluation.protocol == "P1" else None
    by_heading = {r: recalls_by_heading(indices, evaluation.queries.recorded_poses, evaluation.database.recorded_poses,
                                        r, exclude=exclude, alignment=evaluation.alignment) for r in evaluation.radii}
    report(args, evaluation, metrics, agreement, {name: r for name, (_, r) in retrieved.items()}, verified,
           by_heading)
    return 0


def in_sample_warnings(model: VBRLModel, sources: list[Path]) -> list[str]:
    """A warning per evaluated source the model was trained on (its metadata lists them)."""
    trained = {Path(p).resolve() for p in model.metadata.get("sources", [])}
    return [f"the model was trained on {source}: these results are in-sample, not a test"
            for source in sources if source is not None and Path(source).resolve() in trained]


def load(args: argparse.Namespace) -> Evaluation:
    """The models, the sources described once each, and the methods to compare."""
    from vbrl_ros.evaluation.methods import ScanContextMethod, VBRLMethod, describe_source
    from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH

    alignment = load_alignment(args.align) if args.align is not None else None
    models, notes = load_models(args.model or DEFAULT_MODEL_PATH, args.ablations)
    full = models[FULL_NAME]
    config = full.config
    # describing only: every variant keeps its weights. Set together: a model's trail ahead needs
    # a trail behind, and none behind takes none ahead
    trail = config.features.trail_m if args.trail is None else float(args.trail)
    ahead = config.features.trail_ahead_m if args.trail_ahead is None else float(args.trail_ahead)
    config = replace(config, features=replace(config.features, trail_m=trail,
                                              trail_ahead_m=ahead if trail > 0 else 0.0))
    if args.forward_trail is not None:
        config = replace(config, features=replace(config.features, forward_trail_m=float(args.forward_trail),
                                                  fill_blind_wedges=config.features.fill_blind_wedges
                                                  and args.forward_trail > 0))  # fills from the forward trail
    if args.fill_blind_wedges is not None:
        config = replace(config, features=replace(config.features, fill_blind_wedges=args.fill_blind_wedges))
    notes += in_sample_warnings(full, [args.query, args.against])
    notes += evaluate_mounting.notes(args)
    sc_config = evaluate_scan_context.config(args)
    step = full.translation_search() if args.translation_search is None else args.translation_search
    options = {"topic": args.topic, "poses": args.poses, "keyframe_distance": args.keyframe_distance,
               "every": args.every, "workers": args.workers, "progress": not args.quiet,
               "translation_search": step,
               "verification_voxel": DETECTOR_DEFAULTS.verification_voxel if args.verify else None,
               "blocked_azimuth": args.blocked_azimuth, "sc_trail": args.sc_trail,
               "odometry_drift_deg": args.simulate_drift,
               # P1's trails stop short of what the protocol lets a query match; P2's as the node's
               "exclude": args.exclude if args.against is None else None}
    queries = describe_source(args.query, config, sc_config, mount_tilt=args.mount_tilt, **options)
    database = queries if args.against is None else describe_source(args.against, config, sc_config,
                                                                     **options)
    for source in {id(queries): queries, id(database): database}.values():
        if source.positions is None or not np.isfinite(source.positions).all():
            raise ValueError(f"{source.name}: every keyframe needs a pose for the ground truth "
                             "(--poses kiss-icp or file:poses.txt); matching uses them only as the node "
                             "uses odometry")
    width = retrieval_width(args.verify_top_k)
    methods: list[Any] = [VBRLMethod(name, m, exact=args.exact, prune=args.prune,
                                     sequence_length=args.sequence_length, top_k=width) for name, m in models.items()]
    if args.scan_context:
        methods.append(ScanContextMethod(sc_config, args.sc_candidates, args.sc_sequence_length))
    return Evaluation("P1" if args.against is None else "P2", queries, database, models, methods,
                      notes, alignment, sorted({float(args.radius), *REPORT_RADII}), config.features.trail_m, width,
                      trail_ahead_m=config.features.trail_ahead_m)


def retrieve(args: argparse.Namespace, evaluation: Evaluation, method: Any) -> RetrievalResults:
    """Top-K of every query by ``method``, under the protocol."""
    queries, database = evaluation.queries, evaluation.database
    fn = method.distances_fn(queries, database)
    if evaluation.protocol == "P1":
        return online_retrieval(len(queries), args.exclude, evaluation.width, fn, progress=not args.quiet)
    return cross_session_retrieval(len(queries), len(database), evaluation.width, fn, progress=not args.quiet)


def score(args: argparse.Namespace, evaluation: Evaluation,
          results: RetrievalResults) -> dict[float, RetrievalMetrics]:
    """The metrics of ``results`` at every reported radius."""
    queries, database = evaluation.queries, evaluation.database
    if evaluation.protocol == "P1":
        return {r: evaluate_online(queries.positions, results.indices, results.distances, r,
                                   args.exclude) for r in evaluation.radii}
    return {r: evaluate_cross_session(queries.positions, database.positions, results.indices,
                                      results.distances, r, evaluation.alignment)
            for r in evaluation.radii}


def evaluate_methods(args: argparse.Namespace, evaluation: Evaluation
                     ) -> tuple[dict[str, dict[float, RetrievalMetrics]], dict[str, tuple[Any, RetrievalResults]]]:
    """Metrics of every method by name, and each method with its retrieval results."""
    metrics: dict[str, dict[float, RetrievalMetrics]] = {}
    retrieved: dict[str, tuple[Any, RetrievalResults]] = {}
    for method in evaluation.methods:
        results = retrieve(args, evaluation, method)
        metrics[method.name] = score(args, evaluation, results)
        retrieved[method.name] = (method, results)
    return metrics, retrieved


def exact_agreement(args: argparse.Namespace, evaluation: Evaluation,
                    metrics: dict[str, dict[float, RetrievalMetrics]],
                    full_results: RetrievalResults) -> dict[str, Any]:
    """How often the full model's top-1 is unpruned brute force's, and the key-rank headroom.

    Adds the brute-force reference's row to ``metrics``.
    """
    from vbrl_ros.evaluation import headroom
    from vbrl_ros.evaluation.methods import VBRLMethod

    queries, database = evaluation.queries, evaluation.database
    # the reference: brute force over every keyframe and shift, nothing pruned
    reference_name = f"{FULL_NAME}, exact"
    exact = retrieve(args, evaluation, VBRLMethod(reference_name, evaluation.models[FULL_NAME],
                                                  exact=True, prune=0.0, sequence_length=args.sequence_length,
                                                  top_k=evaluation.width))
    metrics[reference_name] = score(args, evaluation, exact)
    asked = full_results.database_limit > 0
    same = full_results.indices[asked, 0] == exact.indices[asked, 0]
    agreement: dict[str, Any] = {"queries": int(asked.sum()), "same_top1": int(same.sum()),
                                 "retrieval": "exact" if args.exact else "index", "prune": args.prune}
    # headroom of the matches that count: brute-force top-1s within the radius
    query_positions, database_positions = evaluation.ground_truth()
    correct = correct_mask(query_positions, database_positions, exact.indices[:, :1],
                           args.radius, exact.database_limit)[:, 0]
    full = next(m for m in evaluation.methods if m.name == FULL_NAME)
    shares = headroom.key_rank_shares(full.new_index(), full.compact(queries.vbrl),
                                      full.compact(database.vbrl),
                                      np.where(correct, exact.indices[:, 0], -1),
                                      exact.database_limit)
    agreement["key_rank"] = {"radius": float(args.radius), **headroom.summary(shares)}
    return agreement


def report(args: argparse.Namespace, evaluation: Evaluation,
           metrics: dict[str, dict[float, RetrievalMetrics]], agreement: dict[str, Any] | None,
           retrieved: dict[str, RetrievalResults], verified: VerifiedOutputs | None = None,
           by_heading: dict[float, dict[str, HeadingRecall] | None] | None = None) -> None:
    """Print the tables; write the JSON metrics, the PR curves and the matches asked for."""
    from vbrl_ros.evaluation import headroom

    queries, database = evaluation.queries, evaluation.database
    for note in evaluation.notes:
        print(f"note: {note}")
    title = evaluation.title(args.exclude)
    print(f"{title}: {len(queries)} query keyframes, {len(database)} database keyframes")
    for source in (queries,) if database is queries else (queries, database):
        if (summary := source.all_round_summary()) is not None:
            print(f"all round, {summary}")
    print(format_table(metrics, evaluation.radii))
    for radius, recalls in (by_heading or {}).items():
        if recalls is not None:
            print(format_heading_recall(recalls, radius))
    if agreement is not None:
        print(f"{FULL_NAME} ({agreement['retrieval']}, prune {args.prune:g}): top-1 equals the "
              f"unpruned brute-force top-1 on {agreement['same_top1']} of {agreement['queries']} "
              "queries")
        print(headroom.describe(agreement["key_rank"]))
    if verified is not None:
        print(evaluate_verified.format_points(verified, evaluation.radii))
    if args.json is not None:
        print(f"metrics written to {write_metrics(args, evaluation, metrics, agreement, verified, by_heading)}")
    plot = args.plot or (args.json.with_suffix(".png") if args.json else args.out_dir / "pr.png")
    from vbrl_ros.evaluation.plots import plot_pr_curves  # matplotlib: only when plotting

    plot.parent.mkdir(parents=True, exist_ok=True)
    plot_pr_curves({name: by_r[float(args.radius)] for name, by_r in metrics.items()}, plot,
                   title=f"{title}, {args.radius:g} m")
    print(f"PR curves written to {plot}")
    for path, name in ((args.dump_matches, FULL_NAME), (args.dump_sc_matches, SCAN_CONTEXT)):
        if path is None or name not in retrieved:
            continue
        results = retrieved[name]
        entries = (matches_to_json(results, include_top_k=True) if verified is None
                   else evaluate_verified.matches_entries(verified, name, results.database_limit))
        out = write_matches(path, entries, queries.keyframe_index, database.keyframe_index)
        print(f"{'verified ' if verified else ''}matches of {name} written to {out}")


def write_metrics(args: argparse.Namespace, evaluation: Evaluation,
                  metrics: dict[str, dict[float, RetrievalMetrics]],
                  agreement: dict[str, Any] | None, verified: VerifiedOutputs | None = None,
                  by_heading: dict[float, dict[str, HeadingRecall] | None] | None = None) -> Path:
    from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH

    protocol, alignment = evaluation.protocol, evaluation.alignment
    report = {
        "protocol": protocol, "query_source": str(args.query),
        "database_source": None if args.against is None else str(args.against),
        "model": str(args.model or DEFAULT_MODEL_PATH),  # the built-in one without --model
        "radius": float(args.radius), "radii": evaluation.radii,
        "exclude": args.exclude if protocol == "P1" else None,
        "align": None if alignment is None else alignment.tolist(),
        **evaluate_mounting.summary(args),
        "num_query_keyframes": len(evaluation.queries),
        "num_database_keyframes": len(evaluation.database),
        "methods": list(metrics), "notes": evaluation.notes,
        "retrieval": "exact" if args.exact else "index", "prune": args.prune,
        "grid": evaluation.models[FULL_NAME].config.grid.kind, "exact_agreement": agreement,
        "trail_m": evaluation.trail_m, "trail_ahead_m": evaluation.trail_ahead_m, "sc_trail": bool(args.sc_trail),
        "metrics": {name: {f"{r:g}": m.summary() for r, m in by_r.items()}
                    for name, by_r in metrics.items()},
        "verified": None if verified is None else verified.summary(metrics),
        "recall_at_1_by_heading": {f"{r:g}": None if recalls is None else {
            name: recall.summary() for name, recall in recalls.items()} for r, recalls in (by_heading or {}).items()},
    }
    text = json.dumps(json_safe(report), indent=2, allow_nan=False)
    return atomic_write(args.json, lambda h: h.write(text.encode()))
