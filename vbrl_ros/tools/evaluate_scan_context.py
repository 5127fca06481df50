"""``vbrl eval``'s Scan Context options: the baseline as published (Kim & Kim 2018), or given
VBRL's sequence matching and trail for a like-for-like comparison, and its matches dump."""

from __future__ import annotations

import argparse
from pathlib import Path

from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scan-context", action=argparse.BooleanOptionalAction, default=True,
                        help="also evaluate the Scan Context baseline (on)")
    parser.add_argument("--sc-lidar-height", type=float, default=2.0,
                        help="Scan Context: sensor height above ground, m (2.0)")
    parser.add_argument("--sc-max-range", type=float, default=80.0, help="Scan Context range, m (80)")
    parser.add_argument("--sc-candidates", type=int, default=10,
                        help="Scan Context: ring-key prefilter candidates (10)")
    parser.add_argument("--sc-sequence-length", type=int, default=1, metavar="N",
                        help="Scan Context: rank with VBRL's sequence matching over N keyframes, "
                             "for a like-for-like comparison (default 1: Scan Context as published)")
    parser.add_argument("--sc-trail", action="store_true",
                        help="Scan Context: read each keyframe with the same trail as VBRL, for a "
                             "like-for-like comparison (default: the scan alone, as published)")
    parser.add_argument("--dump-sc-matches", type=Path, metavar="FILE",
                        help="Scan Context's per-query matches in --dump-matches' format (with --verify, "
                             "its verified output)")


def check_arguments(args: argparse.Namespace) -> None:
    if args.dump_sc_matches is not None and not args.scan_context:
        raise ValueError("--dump-sc-matches needs Scan Context: drop --no-scan-context")


def config(args: argparse.Namespace) -> ScanContextConfig:
    return ScanContextConfig(max_range=args.sc_max_range, lidar_height=args.sc_lidar_height)
