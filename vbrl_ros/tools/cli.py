"""``vbrl``: one command, thin subcommands over the library.

Each subcommand lives in its own module exposing ``register(subparsers)``,
which adds its parser and sets ``func`` to a ``run(args) -> int``. Modules are
imported only when listed here, so ``vbrl --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# Order is the order ``vbrl --help`` lists them.
SUBCOMMANDS: tuple[str, ...] = (
    "vbrl_ros.tools.demo",
    "vbrl_ros.tools.train",
    "vbrl_ros.tools.evaluate",
    "vbrl_ros.tools.leave_one_out",
    "vbrl_ros.tools.simulate",
    "vbrl_ros.tools.replay",
    "vbrl_ros.tools.bench",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vbrl",
        description="VBRL LiDAR place recognition: simulate, train, evaluate, replay, benchmark.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                       help="what to run; vbrl COMMAND --help tells more")
    for module_name in SUBCOMMANDS:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_parsed(build_parser().parse_args(argv))


def run_parsed(args: argparse.Namespace) -> int:
    """Run a parsed subcommand: user errors print one line and exit 2, Ctrl-C exits 130."""
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as error:
        # Bad input (files, parameters, data) is the user's to fix: one line, no traceback.
        print(f"vbrl {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
