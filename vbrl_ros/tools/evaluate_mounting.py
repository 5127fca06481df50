"""``vbrl eval``'s mounting options: a recording as another mounting or odometry would give it.

``--blocked-azimuth`` hides a wedge of every scan, as a mast or an operator would;
``--mount-tilt`` turns the query session's scans and poses as if the sensor had been held
tilted (:mod:`vbrl_ros.datasets.mount_tilt`); ``--simulate-drift`` gives what reads
odometry drifting poses (:mod:`vbrl_ros.datasets.odometry_drift`).
"""

from __future__ import annotations

import argparse
from typing import Any

from vbrl_ros.datasets.blocked_wedge import checked_wedge
from vbrl_ros.datasets.mount_tilt import MAX_MOUNT_TILT_DEG, checked_tilt
from vbrl_ros.datasets.odometry_drift import SCALE_ERROR, checked_drift


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--blocked-azimuth", nargs=2, type=float, default=None, metavar=("FROM", "TO"),
                        help="hide this wedge of every scan (sensor-frame azimuth, degrees counter-clockwise "
                             "from FROM to TO, in [-180, 180]) from both methods, as a mast or an operator "
                             "would: what a sensor mounted that way would get here")
    parser.add_argument("--mount-tilt", nargs=2, type=float, default=None, metavar=("ROLL", "PITCH"),
                        help="turn the query session's scans and poses as if the sensor had been held tilted "
                             f"by ROLL and PITCH degrees (each in [-{MAX_MOUNT_TILT_DEG:g}, "
                             f"{MAX_MOUNT_TILT_DEG:g}]; positive roll lifts the left side, positive pitch "
                             "tips the front down, as vbrl simulate --tilt), for both methods: what a sensor "
                             "held that way would get here (P2: the database session keeps its mount)")
    add_drift_argument(parser)


def add_drift_argument(parser: argparse.ArgumentParser) -> None:
    """``--simulate-drift``, shared by ``vbrl eval`` and ``vbrl loo``."""
    parser.add_argument("--simulate-drift", type=float, default=0.0, metavar="DEG",
                        help="what reads odometry (trail, sequences matched by place, submaps, odometry gate) "
                             "reads the poses as drifting odometry would give them: each step turned by a "
                             "random heading error of DEG degrees per sqrt(100 m) driven and stretched by "
                             f"{100 * SCALE_ERROR:g} %%; the ground truth reads them as recorded (default 0)")


def check_arguments(args: argparse.Namespace) -> None:
    """The options in their checked form, in place; ValueError naming the option otherwise."""
    if args.blocked_azimuth is not None:
        args.blocked_azimuth = checked_wedge(args.blocked_azimuth, "--blocked-azimuth")
    if args.mount_tilt is not None:
        args.mount_tilt = checked_tilt(args.mount_tilt, "--mount-tilt")
    args.simulate_drift = checked_drift(args.simulate_drift, "--simulate-drift")


def notes(args: argparse.Namespace) -> list[str]:
    """One line per option in use, for the evaluation's notes."""
    lines = []
    if args.blocked_azimuth is not None:
        lines.append("every scan hidden from {:g} to {:g} degrees azimuth (--blocked-azimuth)".format(
            *args.blocked_azimuth))
    if args.mount_tilt is not None:
        lines.append("the query scans turned as a sensor held at roll {:g}, pitch {:g} degrees "
                     "(--mount-tilt)".format(*args.mount_tilt))
    if args.simulate_drift > 0:
        lines.append(drift_note(args.simulate_drift))
    return lines


def drift_note(degrees: float) -> str:
    """The line ``vbrl eval`` and ``vbrl loo`` print for ``--simulate-drift``."""
    return f"odometry read as drifting {degrees:g} degrees per sqrt(100 m) (--simulate-drift)"


def summary(args: argparse.Namespace) -> dict[str, Any]:
    """The options for the JSON report (None when not used)."""
    return {"blocked_azimuth": None if args.blocked_azimuth is None else list(args.blocked_azimuth),
            "mount_tilt": None if args.mount_tilt is None else list(args.mount_tilt),
            "simulate_drift_deg": args.simulate_drift}
