"""``vbrl train SOURCE... --out MODEL.npz``: learn W from bags or KITTI-style folders.

Besides MODEL.npz it writes, next to it (see :mod:`.ablations`):

- the paper's ablations MODEL.concatenation/voxel-only/modality-only.npz
  (same data; ``--no-ablations`` skips them);
- MODEL.modalities.png, MODEL.voxels.png, MODEL.layers.png (:mod:`.plots`);
- with ``--cv K``, MODEL.cv.png: held-out Recall@1 over the λ grid (:mod:`.cv`).

``model.metadata["distance_threshold"]`` is the max-F1 acceptance threshold
on the training keyframes (lower distance = more similar; :func:`.threshold.recommend_threshold`).
With ``--stream`` (automatic when n·d·4 bytes exceed ``--max-memory-gb``) the
descriptors are never held: :mod:`.streaming`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from vbrl_ros.config import GRID_KINDS, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.tools.options import add_keyframe_arguments, add_source_arguments, float_list
from vbrl_ros.training import cv as cv_module
from vbrl_ros.training import streaming
from vbrl_ros.training.ablations import ABLATIONS, ablation_lambdas, ablation_path, sibling_path
from vbrl_ros.training.fit import TrainingResult, fit_model, fit_pairs
from vbrl_ros.training.presets import DESCRIPTORS, RECOGNITION_TRANSLATION_SEARCH_M, recognition_config
from vbrl_ros.training.report import importance_report
from vbrl_ros.training.targets import TARGETS, place_labels
from vbrl_ros.training.threshold import recommend_threshold
from vbrl_ros.training.training_data import TrainingData, load_training_data, source_labels


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train", help="learn the VBRL weight matrix W from recordings",
        description="Featurize keyframes of each SOURCE (bag or KITTI-style folder), build the "
                    "scenario matrix Y (each SOURCE is one scenario unless --labels says "
                    "otherwise), solve the structured-sparsity objective and write a model file, "
                    "its three ablations and figures of what it learned next to it.",
    )
    parser.add_argument("sources", nargs="+", type=Path, metavar="SOURCE",
                        help="recordings to learn from: ROS 1/2 bags or KITTI-style folders; each is "
                             "one scenario unless --labels says otherwise")
    parser.add_argument("--out", type=Path, required=True, metavar="MODEL.npz",
                        help="model file to write; the ablations and figures go next to it")
    parser.add_argument("--labels", help="comma-separated scenario label per SOURCE")
    parser.add_argument("--targets", choices=TARGETS, default="scenarios",
                        help="what Y labels: the scenario of each source (the paper's, default); "
                             "places, cells of --place-size metres (needs poses); or pairs: rows are "
                             "same-place / different-place scan pairs (needs poses)")
    parser.add_argument("--place-size", type=float, default=6.0, metavar="M",
                        help="place cell size for --targets places (6 m)")
    parser.add_argument("--frames", choices=("shared", "per-source"), default="shared",
                        help="--targets places: the sources' poses share one world frame (sessions of "
                             "one map; default) or each source has its own (different recordings)")
    parser.add_argument("--lambda1", type=float, default=10.0, help="voxel group norm weight (10)")
    parser.add_argument("--lambda2", type=float, default=0.1,
                        help="modality group + row norm weight (0.1)")
    add_keyframe_arguments(parser)
    add_source_arguments(parser)
    grid = parser.add_argument_group("voxel grid (recorded in the model file)")
    grid.add_argument("--descriptor", choices=DESCRIPTORS, default="paper",
                      help="paper: the paper's five modalities on --grid (default); recognition: "
                           "the built-in model's descriptor for any sensor — scans levelled on their "
                           "ground, the height modality on a 20 x 30 polar grid, normalised, with "
                           "translation search (--rings/--sectors/--max-range still apply)")
    grid.add_argument("--grid", choices=GRID_KINDS, default="cartesian",
                      help="cartesian: the paper's grid, fixed to the sensor axes (default); "
                           "polar: rings x sectors, robust to the heading of a revisit")
    grid.add_argument("--rings", type=int, metavar="N",
                      help=f"polar: rings over [0, --max-range) ({VoxelGridConfig.rings})")
    grid.add_argument("--sectors", type=int, metavar="N",
                      help=f"polar: angular sectors ({VoxelGridConfig.sectors})")
    grid.add_argument("--max-range", type=float, metavar="M",
                      help=f"polar: grid radius in metres ({VoxelGridConfig.max_range:g})")
    parser.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=True,
                        help="also write MODEL.concatenation/voxel-only/modality-only.npz (default: on)")
    cv = parser.add_argument_group("cross-validation of (λ1, λ2)")
    cv.add_argument("--cv", type=int, metavar="K",
                    help="choose (λ1, λ2) by K-fold place-disjoint cross-validation (overrides "
                         "--lambda1/--lambda2; needs poses in one world frame)")
    cv.add_argument("--lambda1-grid", type=float_list, default=cv_module.DEFAULT_LAMBDA1_GRID,
                    metavar="A,B,...", help="λ1 values to try (0,1,10,100)")
    cv.add_argument("--lambda2-grid", type=float_list, default=cv_module.DEFAULT_LAMBDA2_GRID,
                    metavar="A,B,...", help="λ2 values to try (0,0.01,0.1,1)")
    cv.add_argument("--radius", type=float, default=3.0,
                    help="revisit radius in metres for cross-validation and the threshold (3)")
    cv.add_argument("--exclude", type=int, default=50,
                    help="P1: scans excluded before each query, for the threshold (50)")
    memory = parser.add_argument_group("memory")
    memory.add_argument("--stream", action="store_true",
                        help="never hold the descriptors: accumulate Gram statistics in one pass")
    memory.add_argument("--max-memory-gb", type=float, default=4.0,
                        help="stream automatically when n·d·4 bytes exceed this (4)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=run)


def _should_stream(args: argparse.Namespace, d: int) -> tuple[bool, int | None]:
    """(stream?, keyframe count if it was counted)."""
    if args.stream:
        return True, None
    if args.poses == "kiss-icp" and args.keyframe_distance is not None:
        return False, None  # counting would run KISS-ICP twice; assume it fits
    # Counting with poses only when keyframes depend on them (reading poses can be slow).
    poses = args.poses if args.keyframe_distance is not None else "none"
    n = streaming.count_keyframes(args.sources, topic=args.topic, poses=poses,
                                  keyframe_distance=args.keyframe_distance, every=args.every)
    return n * d * 4 > args.max_memory_gb * 1e9, n


#: IRLS iterations the solver may take (its stopping rule usually ends it far sooner).
SOLVER_MAX_ITER = 100

OnIteration = Callable[[int, float], None]


def _summary(result: TrainingResult) -> str:
    converged = "" if result.solver.converged else " (did not converge)"
    return (f"solver {result.solver.path}, {result.solver.iterations} iterations{converged}, "
            f"{result.seconds:.1f} s")


@contextmanager
def solver_progress(description: str, quiet: bool) -> Iterator[OnIteration | None]:
    """A bar over the solver's iterations, with the objective: a large solve takes minutes."""
    if quiet:
        yield None
        return
    with tqdm(total=SOLVER_MAX_ITER, desc=description, unit="it", leave=False) as bar:
        def on_iteration(iteration: int, objective: float) -> None:
            # redrawn every iteration: an iteration is a d x d or n x n solve, never too quick
            bar.update(iteration - bar.n)
            bar.set_postfix(objective=f"{objective:.6g}")

        yield on_iteration


def warn_if_not_converged(result: TrainingResult, what: str) -> None:
    """Say so when the solver stopped at its iteration limit: W is then not the optimum."""
    solver = result.solver
    if solver.converged:
        return
    history = solver.objective_history
    decrease = (history[-2] - history[-1]) / abs(history[-2]) if len(history) > 1 and history[-2] else 0.0
    tqdm.write(f"warning: the solver did not converge for {what}: it stopped at {solver.iterations} "
               f"iterations with the objective still falling by {decrease:.2g} of itself per "
               "iteration; W is the best iterate so far, not the optimum", file=sys.stderr)


def grid_config(args: argparse.Namespace) -> VBRLConfig:
    """The configuration --descriptor/--grid/--rings/--sectors/--max-range ask for (paper
    defaults otherwise)."""
    polar = {name: value for name, value in (("rings", args.rings), ("sectors", args.sectors),
                                             ("max_range", args.max_range)) if value is not None}
    if getattr(args, "descriptor", "paper") == "recognition":
        return recognition_config(**polar)
    if args.grid != "polar":
        if polar:
            raise ValueError(f"--{'/--'.join(k.replace('_', '-') for k in polar)} only apply to "
                             "--grid polar")
        return VBRLConfig()
    return VBRLConfig(grid=VoxelGridConfig(kind="polar", **polar))


@dataclass
class LoadedTraining:
    """The loaded training set and how to fit W on it, in memory or from streamed moments."""

    fit: Callable[[float, float, dict, OnIteration | None], TrainingResult]  # (λ1, λ2, metadata, progress)
    keyframes: int
    scenario_names: list[str]
    lambdas: tuple[float, float]  # the given pair, or the one cross-validation chose
    metadata: dict
    data: TrainingData | None = None  # None when streamed


def run(args: argparse.Namespace) -> int:
    check_arguments(args)
    config = grid_config(args)
    names = source_labels(args.sources, args.labels.split(",") if args.labels else None)
    training = load(args, config, names)
    with solver_progress("solving W", args.quiet) as on_iteration:
        result = training.fit(*training.lambdas, dict(training.metadata), on_iteration)
    warn_if_not_converged(result, "the model")
    calibrate_threshold(args, result.model, training.data)
    path = save_model(args, result, training)
    if args.ablations:
        save_ablations(path, training, args.quiet)
    return 0


def check_arguments(args: argparse.Namespace) -> None:
    if args.lambda1 < 0 or args.lambda2 < 0:
        raise ValueError("--lambda1 and --lambda2 must be >= 0")
    if args.max_memory_gb <= 0:
        raise ValueError("--max-memory-gb must be positive")


def load(args: argparse.Namespace, config: VBRLConfig, names: list[str]) -> LoadedTraining:
    """Stream the sources into Gram moments or load their descriptors, as the data size asks."""
    d = Featurizer(config).layout.dimension
    stream, counted = _should_stream(args, d)
    metadata = {"sources": [str(p) for p in args.sources], "labels": names}
    if args.targets != "scenarios" and (stream or args.cv):
        raise ValueError(f"--targets {args.targets} works with in-memory training without --cv for now")
    if stream:
        if args.cv:
            raise ValueError("--cv needs the training descriptors in memory; run it on a subset "
                             "without --stream (or raise --max-memory-gb), then train with "
                             "--stream --lambda1/--lambda2 set to the chosen pair")
        if counted is not None:
            print(f"{counted} keyframes x {d} features = {counted * d * 4 / 1e9:.1f} GB > "
                  f"--max-memory-gb {args.max_memory_gb:g}: streaming into the Gram matrix")
        return load_streamed(args, config, names, metadata)
    return load_in_memory(args, config, names, metadata)


def load_streamed(args: argparse.Namespace, config: VBRLConfig, names: list[str],
                  metadata: dict) -> LoadedTraining:
    moments, info = streaming.stream_moments(
        args.sources, names, config, topic=args.topic, poses=args.poses,
        keyframe_distance=args.keyframe_distance, every=args.every, workers=args.workers,
        progress=not args.quiet,
    )
    standardized = moments.standardized(Featurizer(config).layout.tie_of_row)

    def fit(l1: float, l2: float, meta: dict, on_iteration: OnIteration | None = None) -> TrainingResult:
        return streaming.fit_from_moments(moments, info.scenario_names, config, l1, l2,
                                          metadata=meta, standardized=standardized,
                                          max_iter=SOLVER_MAX_ITER, on_iteration=on_iteration)

    return LoadedTraining(fit, moments.n, info.scenario_names, (args.lambda1, args.lambda2), metadata)


def load_in_memory(args: argparse.Namespace, config: VBRLConfig, names: list[str],
                   metadata: dict) -> LoadedTraining:
    data = load_training_data(
        args.sources, config, labels=names, topic=args.topic, poses=args.poses,
        keyframe_distance=args.keyframe_distance, every=args.every,
        workers=args.workers, progress=not args.quiet,
    )
    lambdas = (args.lambda1, args.lambda2)
    if args.cv:
        lambdas = cross_validated_lambdas(args, data, config, metadata)
    targets, target_names = data.labels, data.scenario_names
    if args.targets == "places":
        frames = data.source_of_row if args.frames == "per-source" else None
        targets, target_names = place_labels(data.positions, args.place_size, frames)
        metadata["targets"] = f"places ({len(target_names)} cells of {args.place_size:g} m)"
        print(f"Y labels {len(target_names)} places ({args.place_size:g} m cells)")
    if args.descriptor == "recognition":
        metadata["translation_search"] = RECOGNITION_TRANSLATION_SEARCH_M

    def fit(l1: float, l2: float, meta: dict, on_iteration: OnIteration | None = None) -> TrainingResult:
        solver = dict(lambda1=l1, lambda2=l2, metadata=meta, max_iter=SOLVER_MAX_ITER,
                      on_iteration=on_iteration)
        if args.targets == "pairs":
            return fit_pairs(data.descriptors, data.positions, data.source_of_row, config, **solver)
        return fit_model(data.descriptors, targets, target_names, config, **solver)

    return LoadedTraining(fit, len(data.descriptors), data.scenario_names, lambdas, metadata, data)


def cross_validated_lambdas(args: argparse.Namespace, data: TrainingData, config: VBRLConfig,
                            metadata: dict) -> tuple[float, float]:
    """(λ1, λ2) chosen by --cv; prints the table, writes the heat map, records both in ``metadata``."""
    result_cv = cv_module.cross_validate(
        data.descriptors, data.labels, data.scenario_names, data.positions,
        data.source_of_row, data.keyframe_index, config, folds=args.cv,
        lambda1_grid=args.lambda1_grid, lambda2_grid=args.lambda2_grid,
        radius=args.radius, exclude=args.exclude, progress=not args.quiet,
    )
    print(cv_module.format_cv_table(result_cv))
    metadata["cv"] = result_cv.metadata()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    print(f"cross-validation heat map: {cv_module.plot_cv(result_cv, sibling_path(args.out, 'cv.png'))}")
    return result_cv.best


def calibrate_threshold(args: argparse.Namespace, model: VBRLModel, data: TrainingData | None) -> None:
    """Record the recommended acceptance threshold in the model's metadata, when it can be measured."""
    if data is None:
        print("distance_threshold: not computed with --stream (it needs the descriptors); "
              "measure one with vbrl eval")
        return
    threshold = recommend_threshold(
        model, data.descriptors, data.labels, data.positions, data.source_of_row,
        data.keyframe_index, radius=args.radius, exclude=args.exclude)
    if threshold is None:
        print("distance_threshold: not computed (no poses or no revisits in the training data)")
        return
    model.metadata["distance_threshold"] = threshold.pop("distance_threshold")
    model.metadata["distance_threshold_info"] = threshold
    print(f"recommended acceptance threshold (max F1 {threshold['max_f1']:.3f}, "
          f"{threshold['protocol']} on the training keyframes, {threshold['radius']:g} m): "
          f"distance <= {model.metadata['distance_threshold']:.6g}")


def save_model(args: argparse.Namespace, result: TrainingResult, training: LoadedTraining) -> Path:
    """Write the model and its figures; print what was learned."""
    model = result.model
    path = model.save(args.out)
    lambda1, lambda2 = training.lambdas
    print(f"trained on {training.keyframes} keyframes from {len(args.sources)} source(s), "
          f"{len(training.scenario_names)} scenario(s), λ1 = {lambda1:g}, λ2 = {lambda2:g}: "
          f"{_summary(result)}")
    print(importance_report(model))
    from vbrl_ros.training.plots import save_importance_plots  # matplotlib: only when needed

    for kind, png in save_importance_plots(model, path).items():
        print(f"{kind} figure: {png}")
    print(f"model written to {path}")
    return path


def save_ablations(path: Path, training: LoadedTraining, quiet: bool = False) -> None:
    """The paper's three ablations, fitted on the same data, next to the model.

    Three more solves of the model's size: a bar over them, and one over each solve.
    """
    for name in tqdm(ABLATIONS, desc="ablations", unit="fit", disable=quiet):
        l1, l2 = ablation_lambdas(name, *training.lambdas)
        with solver_progress(f"solving {name}", quiet) as on_iteration:
            ablation = training.fit(l1, l2, {**training.metadata, "ablation": name,
                                             "full_model": path.name}, on_iteration)
        out = ablation.model.save(ablation_path(path, name))
        tqdm.write(f"ablation {name:<14s} (λ1 = {l1:g}, λ2 = {l2:g}): {_summary(ablation)} -> {out}")
        warn_if_not_converged(ablation, f"ablation {name}")
