"""``vbrl bench``: the speed targets of docs/design.md §5, measured and printed as a table.

Figures are medians over repeated runs in one process, so compare ratios
within one run rather than absolute times across machines. The featurizer runs
on one core (a compiled single pass plus numpy; its JIT compile is excluded by
the warm-up runs); the solver uses whatever BLAS threads numpy has (the table
says how many). The keyframe index section (:mod:`vbrl_ros.bench.index`:
query + insert at ``--sizes`` keyframes, indexed vs brute force, Recall@1 vs
brute force, bytes per keyframe, pruning) runs single-threaded kernels; its
figures are under ``"index"`` in the ``--json`` output. The whole run takes
about three minutes at the default sizes (most of it building the 100k
databases and the brute-force references). Its polar rows use a stand-in for
a trained polar model unless ``--polar-model`` names one.

``--verification`` runs instead the verification section
(:mod:`vbrl_ros.bench.verification`, about a minute): it times loop-closure verification stage by stage in
CPU milliseconds per candidate on simulated 64-beam keyframe pairs — revisits, half
of them driven the other way, and unrelated places — and prints what it decided and
how far its poses were from the truth.

``--node`` measures the running node instead (:mod:`vbrl_ros.bench.node_load`):
a simulated 64-beam, 10 Hz drive at 10 m/s replayed into ``vbrl_node`` over
DDS at each of ``--rates`` times real time, one table row per rate (clouds
sent and received, keyframes processed and dropped, closures, latency, the
node's CPU and memory). The first run renders the drive into ``--out-dir``
(about a minute); each rate then takes the drive's length divided by the rate,
plus start-up.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vbrl_ros.bench import speed_targets
from vbrl_ros.tools.options import plain_text


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench", help="measure the speed targets and print a table",
        description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per figure (default 30)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the figures as JSON")
    parser.add_argument(
        "--sizes", type=sizes_list, default=(1_000, 10_000, 100_000), metavar="N,N,...",
        help="keyframe database sizes of the index section (default 1000,10000,100000; "
             "'' skips it)",
    )
    parser.add_argument(
        "--polar-model", type=Path, metavar="MODEL",
        help="a trained polar model (vbrl train --grid polar) for the index section's polar rows; "
             "default: a stand-in derived from the shipped paper-configuration model",
    )
    parser.add_argument("--verification", action="store_true",
                        help="instead: loop-closure verification's cost per candidate, stage by stage, "
                             "and its accuracy")
    node = parser.add_argument_group("the running node (--node)")
    node.add_argument("--node", action="store_true",
                      help="replay a simulated drive into vbrl_node at --rates and print its table instead")
    node.add_argument("--rates", type=rates_list, default=(1.0, 2.0, 4.0), metavar="R,R,...",
                      help="replay speed-ups (default 1,2,4)")
    node.add_argument("--scans", type=int, metavar="N", help="replay only the drive's first N clouds")
    node.add_argument("--beams", type=int, default=64, help="LiDAR beams of the drive (default 64)")
    node.add_argument("--columns", type=int, default=1800, help="LiDAR columns per turn (default 1800)")
    node.add_argument("--vertical-fov", nargs=2, type=float, default=None, metavar=("LOW", "HIGH"),
                      help="the drive's vertical field of view, degrees (default: the simulator's for --beams)")
    node.add_argument("--blocked-azimuth", nargs=2, type=float, default=None, metavar=("FROM", "TO"),
                      help="a wedge the drive's sensor cannot see, degrees swept counter-clockwise "
                           "(35 -35: a forward-looking 70°, as vbrl simulate's)")
    node.add_argument("--node-param", action="append", default=[], metavar="NAME:=VALUE",
                      help="a vbrl_node parameter for every run (repeatable)")
    node.add_argument("--out-dir", type=Path, default=Path("runs/bench-node"),
                      help="where the rendered drive is kept (default runs/bench-node)")
    node.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=run)


def rates_list(text: str) -> tuple[float, ...]:
    try:
        rates = tuple(float(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not rates or not all(0 < r <= 100 for r in rates):
        raise argparse.ArgumentTypeError(f"rates must be in (0, 100], got {text!r}")
    return rates


def sizes_list(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if any(n < 10 for n in sizes):
        raise argparse.ArgumentTypeError(f"sizes must be >= 10 keyframes, got {text!r}")
    return tuple(sorted(set(sizes)))


def run(args: argparse.Namespace) -> int:
    if args.node:
        return run_node(args)
    from vbrl_ros.bench import index as index_bench
    from vbrl_ros.bench import verification

    if args.repeats < 1:
        raise ValueError("--repeats must be >= 1")
    if args.verification:
        results = {"verification": verification.measure(repeats=min(args.repeats, 3))}
        print(verification.format_table(results["verification"]))
        _write_json(args.json, results)
        return 0
    polar_model = None
    if args.polar_model is not None:  # checked before the long first section
        from vbrl_ros.bench.descriptors import require_polar
        from vbrl_ros.model.model_file import load_model

        polar_model = load_model(args.polar_model)
        require_polar(polar_model, f"{args.polar_model}: --polar-model")
    results = speed_targets.measure(repeats=args.repeats)
    print(speed_targets.format_table(results), flush=True)
    if args.sizes:
        results["index"] = index_bench.measure(
            args.sizes, repeats=max(args.repeats, 20), polar_model=polar_model,
            polar_model_name=None if args.polar_model is None else str(args.polar_model))
        print()
        print(index_bench.format_table(results["index"]))
    _write_json(args.json, results)
    return 0


def _write_json(path: Path | None, results: dict) -> None:
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(results, indent=2))


def run_node(args: argparse.Namespace) -> int:
    from vbrl_ros.bench import node_load

    if args.scans is not None and args.scans < 2:
        raise ValueError("--scans must be >= 2")
    drive = node_load.Drive(beams=args.beams, columns=args.columns, scans=args.scans,
                            vertical_fov_deg=None if args.vertical_fov is None else tuple(args.vertical_fov),
                            blocked_azimuth_deg=None if args.blocked_azimuth is None else tuple(args.blocked_azimuth))
    results = node_load.measure(args.rates, drive, args.out_dir, node_params=tuple(args.node_param),
                                progress=not args.quiet)
    print(node_load.format_table(results), flush=True)
    _write_json(args.json, results)
    return 0
