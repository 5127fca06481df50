"""Command-line options several ``vbrl`` subcommands share, and their argument types."""

from __future__ import annotations

import argparse
import re


def add_keyframe_arguments(parser: argparse.ArgumentParser) -> None:
    """--keyframe-distance / --every, shared by the commands that select keyframes."""
    selection = parser.add_mutually_exclusive_group()
    selection.add_argument("--keyframe-distance", type=float, metavar="M",
                           help="one keyframe every M metres of travel (needs poses)")
    selection.add_argument("--every", type=int, metavar="N", help="one keyframe every N scans")


def add_source_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by every command that reads scan sources."""
    parser.add_argument("--topic", help="PointCloud2 topic in bags (default: the only one)")
    parser.add_argument(
        "--poses", default="auto",
        help="where poses come from: auto | none | kiss-icp | odom:/topic | pose:/topic | "
             "tf:parent:child | file:poses.txt (default: auto = the data's own)",
    )
    parser.add_argument("--workers", type=int, default=None,
                        help="featurization processes (default: one per CPU)")


def float_list(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not values or any(v < 0 or v != v for v in values):
        raise argparse.ArgumentTypeError(f"expected non-negative numbers, got {text!r}")
    return values


def plain_text(docstring: str | None) -> str:
    """A module docstring as a help text: reST markup out (``x`` -> x, :func:`~a.b.f` -> f).

    The docstrings are written for the API docs; argparse prints them verbatim.
    """
    text = re.sub(r":[a-z]+:`(~?)([^`]*)`",
                  lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), docstring or "")
    return text.replace("``", "")


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends "(default: X)" only where there is a default worth reading.

    argparse's own prints "(default: None)" for every option without one and
    "(default: False)" for every flag, and lists as Python reprs.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        default, help_text = action.default, action.help or ""
        if (default is None or default is False or default is argparse.SUPPRESS
                or isinstance(action, argparse._StoreTrueAction) or "default" in help_text):
            return action.help
        if isinstance(default, (list, tuple)):
            return f"{help_text} (default: {' '.join(map(str, default))})"
        return f"{help_text} (default: {default})"
