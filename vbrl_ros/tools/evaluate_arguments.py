"""``vbrl eval``'s arguments and their checks, made before minutes of describing."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from vbrl_ros.config import MAX_FORWARD_TRAIL_M, MAX_TRAIL_M
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.tools import evaluate_mounting, evaluate_scan_context, evaluate_verified
from vbrl_ros.tools.options import add_keyframe_arguments, add_source_arguments

DETECTOR_DEFAULTS = DetectorSettings()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("query", type=Path, metavar="QUERY_SOURCE",
                        help="recording whose keyframes are the queries (bag or KITTI-style folder); "
                             "alone, also the database (P1)")
    parser.add_argument("--against", type=Path, metavar="DATABASE_SOURCE",
                        help="P2: database session (queries come from QUERY_SOURCE)")
    parser.add_argument("--model", type=Path, default=None, metavar="MODEL.npz",
                        help="the model to evaluate (default: the built-in model the node uses)")
    parser.add_argument("--translation-search", type=float, default=None, metavar="M",
                        help="VBRL: also describe each query from viewpoints M metres around it, as "
                             "the node does (default: the model's own setting; 0: off)")
    parser.add_argument("--trail", type=float, default=None, metavar="M",
                        help="VBRL: describe each keyframe with the keyframes of the last M metres merged "
                             "in by the source's poses, as the node does with odometry (default: the "
                             "model's own setting; 0: each keyframe alone)")
    parser.add_argument("--trail-ahead", type=float, default=None, metavar="M",
                        help="VBRL: also merge into each keyframe with a trail the keyframes of the next M "
                             "metres, as the node does once the sensor has passed the keyframe by M metres "
                             "(default: the model's own setting; 0: none)")
    parser.add_argument("--forward-trail", type=float, default=None, metavar="M",
                        help="VBRL: describe each forward-looking keyframe with the keyframes of the "
                             "last M metres that looked at where it stands, as the node does with "
                             "odometry (default: the model's own setting; 0: alone)")
    parser.add_argument("--fill-blind-wedges", action=argparse.BooleanOptionalAction, default=None,
                        help="VBRL: also describe a keyframe with a blind wedge all round where its "
                             "forward trail saw into the wedge, compared only with keyframes described so, "
                             "as the node does with odometry (default: the model's own setting)")
    parser.add_argument("--sequence-length", type=int, default=DETECTOR_DEFAULTS.sequence_length, metavar="N",
                        help="VBRL: score each candidate over this many keyframes, the query and the "
                             "ones before it, as the node's sequence_length (default "
                             f"{DETECTOR_DEFAULTS.sequence_length}; 1: each query alone)")
    parser.add_argument("--align", type=Path, metavar="T.txt",
                        help="P2: 4x4 transform, query world frame -> database world frame "
                             "(ground truth only)")
    parser.add_argument("--exclude", type=int, default=50,
                        help="P1: keyframes excluded before each query (50; = scans by default)")
    parser.add_argument("--radius", type=float, default=3.0,
                        help="revisit radius, metres (3); 5 m is always reported too")
    add_keyframe_arguments(parser)
    add_source_arguments(parser)
    evaluate_mounting.add_arguments(parser)
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the metrics as JSON")
    parser.add_argument("--plot", type=Path, metavar="FILE",
                        help="PR-curve PNG (default: next to --json, else OUT_DIR/pr.png)")
    parser.add_argument("--out-dir", type=Path, default=Path("."), help="for the default plot (.)")
    parser.add_argument("--dump-matches", type=Path, metavar="FILE",
                        help="per-query top matches of the full VBRL model as JSON (with --verify, the "
                             "best verified candidate, published to the keyframe nearest the query as "
                             "the node publishes it)")
    parser.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=True,
                        help="also evaluate MODEL.<ablation>.npz found next to the model (on)")
    parser.add_argument("--exact", action="store_true",
                        help="VBRL: brute-force retrieval over every keyframe (and every sector shift) "
                             "instead of the keyframe index the node uses")
    parser.add_argument("--check-exact", action="store_true",
                        help="also run the full model by unpruned brute force (an extra table row) "
                             "and report how often its top-1 equals the retrieval's")
    parser.add_argument("--prune", type=float, default=0.0001,
                        help="VBRL: rows weighing < PRUNE x the largest row weight are not stored "
                             "or scored, as the node's weight_prune (0.0001)")
    evaluate_scan_context.add_arguments(parser)
    evaluate_verified.add_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def check_arguments(args: argparse.Namespace) -> None:
    if not (math.isfinite(args.radius) and args.radius > 0):
        raise ValueError("--radius must be a positive number of metres")
    if args.exclude < 1:
        raise ValueError("--exclude must be >= 1 (a scan must not match itself)")
    if not 0.0 <= args.prune < 1.0:
        raise ValueError("--prune must be in [0, 1)")
    if args.align is not None and args.against is None:
        raise ValueError("--align only applies to P2 (--against)")
    if args.translation_search is not None and not 0 <= args.translation_search <= 10:
        raise ValueError("--translation-search must be a step in [0, 10] metres")
    if args.trail is not None and not (math.isfinite(args.trail) and 0 <= args.trail <= MAX_TRAIL_M):
        raise ValueError(f"--trail must be a number of metres in [0, {MAX_TRAIL_M:g}]")
    if args.trail_ahead is not None and not (math.isfinite(args.trail_ahead) and 0 <= args.trail_ahead <= MAX_TRAIL_M):
        raise ValueError(f"--trail-ahead must be a number of metres in [0, {MAX_TRAIL_M:g}]")
    if args.forward_trail is not None and not (math.isfinite(args.forward_trail)
                                               and 0 <= args.forward_trail <= MAX_FORWARD_TRAIL_M):
        raise ValueError(f"--forward-trail must be a number of metres in [0, {MAX_FORWARD_TRAIL_M:g}]")
    for flag, length in (("--sequence-length", args.sequence_length),
                         ("--sc-sequence-length", args.sc_sequence_length)):
        if not 1 <= length <= 20:
            raise ValueError(f"{flag} must be an integer in [1, 20]")
    evaluate_mounting.check_arguments(args)
    evaluate_scan_context.check_arguments(args)
    evaluate_verified.check_arguments(args)
    for name, path in (("QUERY_SOURCE", args.query), ("--against", args.against), ("--model", args.model)):
        if path is not None and not Path(path).exists():  # before minutes of describing
            raise ValueError(f"{name} {path} does not exist")
