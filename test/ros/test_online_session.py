"""Stopping the processes of a node session: a clean exit on SIGINT, or a kill when it does not come."""

from __future__ import annotations

import signal
import subprocess
import sys

from vbrl_ros.ros.online_session import stop_process

EXITS_ON_SIGINT = ("import signal, sys, time\n"
                   "signal.signal(signal.SIGINT, lambda *a: (print('saved', flush=True), sys.exit(0)))\n"
                   "print('up', flush=True); time.sleep(60)")
IGNORES_SIGINT = ("import signal, time\n"
                  "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                  "print('up', flush=True); time.sleep(60)")


def started(code: str) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
    assert process.stdout.readline().strip() == "up"  # its handler is in place
    return process


def test_a_process_that_exits_on_sigint_is_waited_for():
    process = started(EXITS_ON_SIGINT)
    output, killed = stop_process(process, signal.SIGINT, 30)
    assert (output.strip(), killed, process.returncode) == ("saved", False, 0)


def test_a_process_stuck_in_its_shutdown_is_killed_and_does_not_outlive_the_session():
    process = started(IGNORES_SIGINT)
    output, killed = stop_process(process, signal.SIGINT, 1.0)
    assert killed and process.returncode == -signal.SIGKILL
    assert process.poll() is not None
