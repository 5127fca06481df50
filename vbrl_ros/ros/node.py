"""``vbrl_node``: start, run and stop the online loop-closure detector (:mod:`vbrl_ros.ros.detector_node`).

Only the standard library is imported here: numpy, rclpy, numba and the model take
a second or two to load, and a Ctrl-C meanwhile must stop the start as quietly as
one later, not with a KeyboardInterrupt traceback from an import.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

from vbrl_ros.ros.startup import params_file_problem, rcl_error_line, usage


def main(argv: list[str] | None = None) -> int:
    interrupted = record_interrupts()
    try:
        return run(list(sys.argv if argv is None else argv), interrupted)
    except KeyboardInterrupt:  # before rclpy's own signal handling is in place
        print("vbrl_node: interrupted", file=sys.stderr, flush=True)
        # CPython records a KeyboardInterrupt raised inside exec() (dataclasses run one per
        # generated method while a module loads) as unhandled even once caught, and would end
        # the process by SIGINT (exit -2); nothing runs yet, so leave directly
        sys.stdout.flush()
        os._exit(0)


def record_interrupts() -> threading.Event:
    """Until rclpy handles signals, a Ctrl-C is recorded, not raised: raised inside a library's
    import it can be swallowed by that library, and the node would start and never stop."""
    interrupted = threading.Event()
    signal.signal(signal.SIGINT, lambda signum, frame: interrupted.set())
    return interrupted


def run(argv: list[str], interrupted: threading.Event | None = None) -> int:
    """0 after a clean shutdown, 2 when the start is refused, 1 when the final save failed.
    ``interrupted``: set by a Ctrl-C that came before rclpy's own handling."""
    interrupted = interrupted or threading.Event()
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in user_args or "--help" in user_args:
        print(usage())
        return 0
    problem = params_file_problem(argv)
    if problem is not None:
        print(f"vbrl_node: cannot start: {problem}", file=sys.stderr)
        return 2

    from vbrl_ros.ros.transport import use_large_data_profile

    use_large_data_profile()  # before rclpy: whole clouds through shared memory
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from vbrl_ros.detection.database_file import DatabaseFileError
    from vbrl_ros.detection.settings import SettingsError
    from vbrl_ros.model.model_file import ModelFileError
    from vbrl_ros.ros.detector_node import VbrlNode

    if interrupted.is_set():
        raise KeyboardInterrupt
    try:
        rclpy.init(args=argv)
    except RuntimeError as error:  # rcl's RCLError, e.g. a parameter file that is not valid YAML
        print(f"vbrl_node: cannot start: {rcl_error_line(error)}", file=sys.stderr)
        return 2
    node, code = None, 0
    try:
        if interrupted.is_set():  # between the check above and rclpy's handlers
            raise KeyboardInterrupt
        node = VbrlNode()
        if interrupted.is_set():
            raise KeyboardInterrupt
        rclpy.spin(node)
    except (SettingsError, ModelFileError, DatabaseFileError) as error:
        print(f"vbrl_node: cannot start: {error}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # SIGINT / SIGTERM: fall through to a clean shutdown
    except Exception:
        if rclpy.ok():
            raise
        # a signal shut the context down while the executor was mid-wait;
        # rclpy then raises whatever that wait hit: still a clean shutdown
    finally:
        if node is not None:
            code = code if node.shutdown() else 1
            node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RuntimeError:  # rclpy's signal handler shut the context down meanwhile
            pass
    return code


if __name__ == "__main__":
    sys.exit(main())
