"""``vbrl loo FOLDER``: leave-one-recording-out, the honest test of a place recogniser.

For each recording in FOLDER (any source ``vbrl train`` reads: KITTI-style folders, bags),
train the built-in model's recipe (:func:`~vbrl_ros.training.builtin_model.fit_recognition_model`)
on the simulated towns plus every *other* recording, and evaluate P1 on the one left out,
Scan Context beside it in the same run. Prints one table; ``--json`` writes it and a bar chart
(PNG) draws it. A recording without revisits counts the false positives among accepted
closures at the model's own distance threshold.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from vbrl_ros.datasets.odometry_drift import checked_drift
from vbrl_ros.io.atomic import atomic_write
from vbrl_ros.tools.evaluate_mounting import add_drift_argument, drift_note
from vbrl_ros.tools.evaluate_output import json_safe

RADIUS_M = 5.0  # the targets' radius; the protocol's own is 3 m (--radius 3)
EXCLUDE = 50


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "loo", help="leave-one-recording-out: train on the others (+ simulated towns), test on each",
        description=(
            "Leave-one-recording-out, the honest test of a place recogniser. For each recording in "
            "FOLDER (any source vbrl train reads: KITTI-style folders, bags), train the built-in "
            "model's recipe on the simulated towns plus every other recording, and evaluate P1 on "
            "the one left out, Scan Context beside it in the same run: retrieval, the verified output "
            "swept over fitness, and what the node publishes at its default settings (both methods' "
            "candidates verified by the node's own code). Prints one table; --json writes it, --plot "
            "draws it. On a recording without revisits every published closure is a false one."
        ),
    )
    parser.add_argument("folder", type=Path, metavar="FOLDER",
                        help="a folder whose entries are recordings (KITTI-style folders or bags)")
    parser.add_argument("--out-dir", type=Path, default=Path("runs/loo"),
                        help="where the models trained without each recording go (runs/loo)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the table as JSON")
    parser.add_argument("--plot", type=Path, metavar="FILE",
                        help="the table as a bar chart PNG (default: next to --json, else OUT_DIR/loo.png)")
    parser.add_argument("--simulated-towns", action=argparse.BooleanOptionalAction, default=True,
                        help="train on the built-in model's simulated towns too, as its recipe does (on)")
    parser.add_argument("--submap-keyframes", type=int, default=None, metavar="N",
                        help="the node's submap_keyframes for verification (default: the node's, 2; "
                             "0: single scans)")
    add_drift_argument(parser)
    parser.add_argument("--radius", type=float, default=RADIUS_M, metavar="M",
                        help=f"revisit radius, metres: a query whose match lies within it is right "
                             f"({RADIUS_M:g}; the P1 protocol's own is 3)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=run)


def recordings_in(folder: Path) -> list[Path]:
    from vbrl_ros.datasets.registry import detect_source_kind

    if not folder.is_dir():
        raise ValueError(f"{folder} is not a folder of recordings")
    found = []
    for entry in sorted(folder.iterdir()):
        try:
            detect_source_kind(entry)
        except ValueError:
            continue  # READMEs, sidecars: not recordings
        found.append(entry)
    if len(found) < 2:
        raise ValueError(f"{folder} holds {len(found)} recording(s); leave-one-out needs at least 2")
    return found


def run(args: argparse.Namespace) -> int:
    from vbrl_ros.detection.settings import DetectorSettings
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source
    from vbrl_ros.evaluation.plots import plot_leave_one_out
    from vbrl_ros.training.builtin_model import (
        BUILTIN_TOWNS,
        fit_recognition_model,
        simulated_recognition_data,
    )
    from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config

    rule = DetectorSettings() if args.submap_keyframes is None else checked_rule(args.submap_keyframes)
    drift = checked_drift(args.simulate_drift, "--simulate-drift")
    radius = args.radius
    if not (math.isfinite(radius) and 0 < radius <= 100):
        raise ValueError(f"--radius must be in (0, 100] metres, got {radius:g}")
    recordings = recordings_in(args.folder)
    progress = not args.quiet
    config = recognition_config()
    towns = simulated_recognition_data(BUILTIN_TOWNS, config, progress) if args.simulated_towns else []
    # each recording is described once: its first view is what training reads
    voxel = DetectorSettings().verification_voxel
    sources = [describe_source(path, config, ScanContextConfig(), progress=progress,
                               translation_search=RECOGNITION_TRANSLATION_SEARCH_M, verification_voxel=voxel,
                               odometry_drift_deg=drift)
               for path in recordings]
    for path, source in zip(recordings, sources):
        if source.positions is None or not np.isfinite(source.positions).all():
            raise ValueError(f"{path}: every scan needs a pose for the ground truth")
    parts = [(path.name, source.vbrl, source.positions) for path, source in zip(recordings, sources)]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, held in enumerate(recordings):
        others = [p for j, p in enumerate(parts) if j != k]
        model = fit_recognition_model(towns + others, [str(r.resolve()) for j, r in enumerate(recordings)
                                                       if j != k]).model
        path = model.save(args.out_dir / f"without_{held.name}.npz")
        print(f"[{k + 1}/{len(recordings)}] {held.name}: model trained without it -> {path}")
        rows.append({"recording": held.name, "radius_m": radius, **evaluate(sources[k], model, rule, progress, radius)})
    if drift > 0:
        print(drift_note(drift))
    print(format_rows(rows, radius))
    if args.json is not None:
        text = json.dumps(json_safe(rows), indent=1, allow_nan=False)
        atomic_write(args.json, lambda handle: handle.write(text.encode()))
        print(f"table written to {args.json}")
    plot = args.plot or (args.json.with_suffix(".png") if args.json is not None else args.out_dir / "loo.png")
    plot.parent.mkdir(parents=True, exist_ok=True)
    plot_leave_one_out(rows, plot, title=f"leave-one-recording-out, P1, R = {radius:g} m, E = {EXCLUDE}")
    print(f"bar chart written to {plot}")
    return 0


def checked_rule(submap_keyframes: int):
    """The node's default settings with ``submap_keyframes``; a bad value names the option."""
    from vbrl_ros.detection.settings import DetectorSettings, SettingsError

    try:
        return DetectorSettings(submap_keyframes=submap_keyframes)
    except SettingsError as error:
        raise ValueError(f"--submap-keyframes: {error}") from None


def evaluate(source, model, rule, progress: bool, radius: float = RADIUS_M) -> dict:
    """P1 metrics at ``radius`` of the model and of Scan Context on one described recording:
    retrieval, verified (swept over fitness) and what the node publishes under ``rule`` (the
    detector's settings)."""
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import ScanContextMethod, VBRLMethod
    from vbrl_ros.evaluation.metrics import evaluate_online
    from vbrl_ros.evaluation.retrieval import online_retrieval
    from vbrl_ros.evaluation.verified import retrieval_width
    from vbrl_ros.evaluation.verified_output import VerificationInputs, verified_output

    def score(results):
        return {radius: evaluate_online(source.positions, results.indices, results.distances, radius, EXCLUDE)}

    out = {}
    inputs = VerificationInputs.of(source, source, rule)  # once for both methods
    width = retrieval_width(rule.top_k)
    for name, method in (("vbrl", VBRLMethod("VBRL", model, prune=0.0001, top_k=width)),
                         ("scan_context", ScanContextMethod(ScanContextConfig()))):
        results = online_retrieval(len(source), EXCLUDE, width, method.distances_fn(source, source), progress)
        m = score(results)[radius]
        # selected, verified and decided as by vbrl eval --verify: the same figures
        verified = verified_output(inputs, results, rule, score, progress=progress,
                                   description=f"verifying {method.name}")
        out[name] = {"max_f1": m.max_f1, "recall_at_1": m.recall_at_1, "revisits": m.num_revisits,
                     "verified_max_f1": verified.swept[radius].max_f1,
                     "node": verified.points[rule.min_fitness][radius].summary()}
    return out


def _cell(x: float) -> str:
    return "   -  " if x is None or not math.isfinite(x) else f"{x:6.3f}"


def format_rows(rows: list[dict], radius: float = RADIUS_M) -> str:
    lines = [(f"leave-one-recording-out, P1, R = {radius:g} m, E = {EXCLUDE}: retrieval max F1 / Recall@1, "
              "verified max F1, and the node's defaults (verified precision / recall; a recording "
              "without revisits: closures published, all false)"),
             (f"  {'recording':<26s} {'revisits':>8s}   {'VBRL retrieval':>15s} {'verified':>8s} {'node P / R':>13s}"
              f"   {'Scan Context':>15s} {'verified':>8s} {'node P / R':>13s}")]
    for row in rows:
        cells = []
        for name in ("vbrl", "scan_context"):
            v = row[name]
            if v["revisits"] == 0:
                cells.append(f"{'':>15s} {'':>8s} {v['node']['accepted']:>6d} closures")
            else:
                cells.append(f"{_cell(v['max_f1'])} / {_cell(v['recall_at_1'])} {_cell(v['verified_max_f1']):>8s} "
                             f"{_cell(v['node']['precision'])} / {_cell(v['node']['recall'])}")
        lines.append(f"  {row['recording']:<26s} {row['vbrl']['revisits']:>8d}   {cells[0]}   {cells[1]}")
    return "\n".join(lines)
