"""Candidate verification in a child process, so that KISS-ICP does not hold the caller's interpreter.

KISS-ICP keeps the GIL for most of a registration (measured: the node's main
thread got ~9 % of its Python time while a thread verified), so a thread frees
nothing; a process does. :class:`VerifierProcess` starts one with the *spawn*
method (a fork of a process running DDS threads is not safe), sends it one
:class:`~vbrl_ros.detection.candidate_verification.Retrieval` at a time (the query's and the
candidates' clouds travel with it, ~50 kB each at 1 m voxels) and gets the
:class:`~vbrl_ros.detection.candidate_verification.KeyframeResult` back. The child imports no
ROS, ignores SIGINT (Ctrl-C reaches the whole process group; the parent stops
it) and exits when the parent's end of the pipe closes, even after a kill -9 of
the parent. As with any spawned process, a script that starts one must guard
its entry point with ``if __name__ == "__main__":``.
"""

from __future__ import annotations

import multiprocessing
import signal
import traceback
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

from vbrl_ros.detection.settings import DetectorSettings

if TYPE_CHECKING:
    from vbrl_ros.detection.candidate_verification import KeyframeResult, Retrieval

# The child imports this module before it can run serve(): nothing heavy here (numpy, KISS-ICP and
# the verification come inside serve), so that it ignores Ctrl-C within milliseconds of its start.

#: Seconds a child may take to finish its registration and exit before it is killed.
STOP_TIMEOUT_S = 10.0
#: Seconds a child may take to start (imports, KISS-ICP's first call) and to answer one keyframe
#: (a few registrations: well under a second) before it is taken for stuck and killed.
START_TIMEOUT_S = 120.0
ANSWER_TIMEOUT_S = 30.0


class VerifierError(RuntimeError):
    """Verification failed in the child, or the child died; the message says which, in one line."""


class VerifierProcess:
    """A child process that runs :func:`verify_candidates` with fixed settings.

    :meth:`verify` blocks (without the GIL) until the answer comes. A child that died, or gave
    no answer within ``answer_timeout`` seconds (stopped, deadlocked), is killed and started
    again at the next call; the call that found it so raises :class:`VerifierError`.
    One caller at a time.
    """

    def __init__(self, settings: DetectorSettings, answer_timeout: float = ANSWER_TIMEOUT_S,
                 start_timeout: float = START_TIMEOUT_S) -> None:
        self.settings = settings
        self.answer_timeout, self.start_timeout = answer_timeout, start_timeout
        self._context = multiprocessing.get_context("spawn")
        self._process: multiprocessing.process.BaseProcess | None = None
        self._connection: Connection | None = None
        self.starts = 0

    @property
    def pid(self) -> int | None:
        """The child's process id while it runs."""
        return self._process.pid if self._process is not None and self._process.is_alive() else None

    def start(self) -> None:
        """Start the child (if it is not running) and wait until it has verified a first pair:
        its imports and KISS-ICP's first call take seconds, which no keyframe should wait for."""
        if self._process is not None and self._process.is_alive():
            return
        self.stop()
        parent, child = self._context.Pipe()
        self._process = self._context.Process(target=serve, args=(child, self.settings),
                                              name="vbrl-verifier", daemon=True)
        self._process.start()
        child.close()  # the child's copy: once the child exits, a read here sees the end
        self._connection = parent
        self.starts += 1
        try:
            self._receive(self.start_timeout)  # ("ok", None) once warm
        except BaseException:
            # e.g. Ctrl-C while the child starts: end it now, before it reads from a closed pipe
            # and prints a traceback of its own
            self.stop(at_once=True)
            raise

    def _receive(self, timeout: float):
        assert self._connection is not None
        try:
            if not self._connection.poll(timeout):
                self.stop(at_once=True)  # a stopped or stuck child: a new one serves the next call
                raise VerifierError(f"the verification process gave no answer in {timeout:g} s and was killed")
            status, payload = self._connection.recv()
        except (EOFError, OSError) as error:
            code = self._process.exitcode if self._process is not None else None
            self.stop()
            raise VerifierError(f"the verification process ended (exit code {code}): {error!r}") from None
        if status != "ok":
            raise VerifierError(payload)
        return payload

    def verify(self, retrieval: Retrieval) -> KeyframeResult:
        self.start()
        assert self._connection is not None
        try:
            self._connection.send(retrieval)
        except OSError as error:
            self.stop()
            raise VerifierError(f"the verification process is gone: {error!r}") from None
        return self._receive(self.answer_timeout)

    def stop(self, *, at_once: bool = False) -> None:
        """Ask the child to exit after its current registration; kill it if it does not (``at_once``:
        kill it now, as one that is stuck or that must not read from a closed pipe)."""
        if at_once and self._process is not None:
            self._process.kill()
        if self._connection is not None:
            try:
                self._connection.send(None)
            except OSError:
                pass
            self._connection.close()
            self._connection = None
        if self._process is not None:
            self._process.join(STOP_TIMEOUT_S)
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
            self._process = None


def serve(connection: Connection, settings: DetectorSettings) -> None:
    """The child's loop: a Retrieval in, ("ok", KeyframeResult) or ("error", one line) out; None ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group
    from vbrl_ros.detection.candidate_verification import verify_candidates

    warm_up(settings)
    connection.send(("ok", None))
    while True:
        try:
            retrieval = connection.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if retrieval is None:
            return
        try:
            connection.send(("ok", verify_candidates(retrieval, settings)))
        except Exception as error:  # one keyframe's failure must not end verification
            where = traceback.extract_tb(error.__traceback__)[-1]
            connection.send(("error", f"{error!r} at {where.filename}:{where.lineno}"))


def warm_up(settings: DetectorSettings) -> None:
    """One verification of a synthetic pair: loads and compiles what the first real one needs."""
    import numpy as np

    from vbrl_ros.detection.candidate_verification import Retrieval, verify_candidates
    from vbrl_ros.detection.database import Candidate

    rng = np.random.default_rng(0)
    walls = rng.uniform(-20, 20, (2000, 3)) * [1, 1, 0.1] + [0, 0, 1]
    cloud = np.round(walls / 2) * 2 + rng.normal(0, 0.05, walls.shape)
    verify_candidates(Retrieval(
        keyframe_id=1, stamp=1.0, session="warm-up", candidates=[Candidate(0, 0, 0.0, 0.0, "warm-up")],
        candidates_scored=1, frame=np.eye(4), cloud=cloud.astype(np.float32),
        candidate_clouds=[cloud.astype(np.float32)], candidate_frames=[np.eye(4)]), settings)
