"""``vbrl loo FOLDER``: leave-one-recording-out, the honest test of a place recogniser.

For each recording in FOLDER (any source ``vbrl train`` reads: KITTI-style folders, bags),
train the built-in model's recipe (:func:`~vbrl_ros.training.builtin_model.fit_recognition_model`)
on the simulated towns plus every *other* recording, and evaluate P1 on the one left out,
Scan Context beside it in the same run. Prints one table; ``--json`` writes it. A recording
without revisits counts the false positives among accepted closures at the model's own
distance threshold.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from vbrl_ros.io.atomic import atomic_write

RADIUS_M = 5.0
EXCLUDE = 50


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "loo", help="leave-one-recording-out: train on the others (+ simulated towns), test on each",
        description=(
            "Leave-one-recording-out, the honest test of a place recogniser. For each recording in "
            "FOLDER (any source vbrl train reads: KITTI-style folders, bags), train the built-in "
            "model's recipe on the simulated towns plus every other recording, and evaluate P1 on "
            "the one left out, Scan Context beside it in the same run. Prints one table; --json "
            "writes it. A recording without revisits counts the false positives among accepted "
            "closures at the model's own distance threshold."
        ),
    )
    parser.add_argument("folder", type=Path, metavar="FOLDER",
                        help="a folder whose entries are recordings (KITTI-style folders or bags)")
    parser.add_argument("--out-dir", type=Path, default=Path("runs/loo"),
                        help="where the models trained without each recording go (runs/loo)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the table as JSON")
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
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source
    from vbrl_ros.training.builtin_model import (
        BUILTIN_TOWNS,
        fit_recognition_model,
        simulated_recognition_data,
    )
    from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config

    recordings = recordings_in(args.folder)
    progress = not args.quiet
    config = recognition_config()
    towns = simulated_recognition_data(BUILTIN_TOWNS, config, progress)
    # each recording is described once: its first view is what training reads
    sources = [describe_source(path, config, ScanContextConfig(), progress=progress,
                               translation_search=RECOGNITION_TRANSLATION_SEARCH_M) for path in recordings]
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
        rows.append({"recording": held.name, **evaluate(sources[k], model, progress)})
    print(format_rows(rows))
    if args.json is not None:
        text = json.dumps(rows, indent=1, default=lambda x: None if isinstance(x, float) and not math.isfinite(x) else x)
        atomic_write(args.json, lambda handle: handle.write(text.encode()))
        print(f"table written to {args.json}")
    return 0


def evaluate(source, model, progress: bool) -> dict:
    """P1 metrics at RADIUS_M of the model and of Scan Context on one described recording."""
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import ScanContextMethod, VBRLMethod
    from vbrl_ros.evaluation.metrics import evaluate_online
    from vbrl_ros.evaluation.retrieval import online_retrieval

    out = {}
    for name, method in (("vbrl", VBRLMethod("VBRL", model, prune=0.0001)),
                         ("scan_context", ScanContextMethod(ScanContextConfig()))):
        results = online_retrieval(len(source), EXCLUDE, 5, method.distances_fn(source, source), progress)
        m = evaluate_online(source.positions, results.indices, results.distances, RADIUS_M, EXCLUDE)
        out[name] = {"max_f1": m.max_f1, "recall_at_1": m.recall_at_1, "revisits": m.num_revisits}
        if name == "vbrl":  # what the node accepts at the model's own threshold, before verification
            top1 = results.distances[:, 0]
            out[name]["accepted_at_threshold"] = int(np.sum(top1 <= model.distance_threshold()))
    return out


def _cell(x: float) -> str:
    return "   -  " if x is None or not math.isfinite(x) else f"{x:6.3f}"


def format_rows(rows: list[dict]) -> str:
    lines = [f"leave-one-recording-out, P1, R = {RADIUS_M:g} m, E = {EXCLUDE} "
             "(max F1 / Recall@1; a recording without revisits: closures accepted before verification)",
             f"  {'recording':<28s} {'revisits':>8s}   {'VBRL':>15s}   {'Scan Context':>15s}"]
    for row in rows:
        v, s = row["vbrl"], row["scan_context"]
        if v["revisits"] == 0:
            lines.append(f"  {row['recording']:<28s} {0:>8d}   {v['accepted_at_threshold']:>6d} accepted")
        else:
            lines.append(f"  {row['recording']:<28s} {v['revisits']:>8d}   {_cell(v['max_f1'])} / "
                         f"{_cell(v['recall_at_1'])}   {_cell(s['max_f1'])} / {_cell(s['recall_at_1'])}")
    return "\n".join(lines)
