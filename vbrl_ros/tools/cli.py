"""``vbrl``: one command, thin subcommands over the library.

Each subcommand lives in its own module exposing ``register(subparsers)``,
which adds its parser and sets ``func`` to a ``run(args) -> int``. Modules are
imported only when listed here, so ``vbrl --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
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


class Terminated(KeyboardInterrupt):
    """SIGTERM (a service manager, a CI timeout, ``kill``), raised where the main thread is, so it
    takes Ctrl-C's path: open files close and worker pools shut their processes down (killed
    outright, a pool's fork server and workers were left running)."""


def _terminate(signum: int, frame: object) -> None:
    raise Terminated


def run_parsed(args: argparse.Namespace) -> int:
    """Run a parsed subcommand: user errors print one line and exit 2, Ctrl-C exits 130, SIGTERM
    143."""
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if in_main else None
    try:
        return int(args.func(args) or 0)
    except Terminated:
        print("terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as error:
        # Bad input (files, parameters, data) is the user's to fix: one line, no traceback.
        print(f"vbrl {args.command}: error: {error}", file=sys.stderr)
        return 2
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
