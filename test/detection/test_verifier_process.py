"""Verification in a child process: the same closures as in-process, and a dead or stuck child replaced."""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import replace

import numpy as np
import pytest

from vbrl_ros.detection.candidate_verification import verify_candidates
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.verifier_process import VerifierError, VerifierProcess
from vbrl_ros.model.builtin import load_default_model

sim = pytest.importorskip("vbrl_ros.simulator")
LIDAR = sim.LidarConfig(beams=32, columns=512)
SETTINGS = DetectorSettings(verify=True, exclude_recent_s=0.0, top_k=3)


@pytest.fixture(scope="module")
def retrievals():
    """A revisit (scan 40 of the second loop against the first) and a first-seen place."""
    town = sim.generate_town(sim.TownConfig(blocks_x=1, blocks_y=1), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=4.0))
    run = sim.simulate_run(town, route, LIDAR, "summer_clear", seed=1)
    model = load_default_model()
    detector = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()), SETTINGS)
    half = len(run) // 2
    out = [detector.retrieve(run.scan(k).points, float(k), run.scan(k).pose) for k in range(0, half, 3)]
    out.append(detector.retrieve(run.scan(half + 6).points, float(half + 6), run.scan(half + 6).pose))
    return [r for r in out if r.candidates][-3:]


def test_the_child_s_closures_and_rejections_are_the_in_process_ones(retrievals):
    verifier = VerifierProcess(SETTINGS)
    try:
        remote = [verifier.verify(r) for r in retrievals]
    finally:
        verifier.stop()
    local = [verify_candidates(r, SETTINGS) for r in retrievals]
    assert any(result.closures for result in local) and any(result.rejections for result in local)
    for a, b in zip(remote, local):
        assert (a.keyframe_id, a.rejections, a.rejected_by_verification) == (b.keyframe_id, b.rejections,
                                                                             b.rejected_by_verification)
        assert [(c.match_id, c.fitness) for c in a.closures] == [(c.match_id, c.fitness) for c in b.closures]
        assert [(c.match_id, c.fitness) for c in a.weak] == [(c.match_id, c.fitness) for c in b.weak]
        for c, d in zip(a.closures, b.closures):  # KISS-ICP's parallel sums: rounding may differ
            np.testing.assert_allclose(c.T_query_match, d.T_query_match, rtol=0, atol=1e-9)
            np.testing.assert_allclose(c.covariance, d.covariance, rtol=1e-6, atol=1e-15)


def test_a_child_killed_mid_verification_fails_that_call_and_the_next_starts_a_new_one(retrievals):
    slow = replace(retrievals[-1], candidates=retrievals[-1].candidates * 20,  # seconds of registrations
                   candidate_clouds=retrievals[-1].candidate_clouds * 20,
                   candidate_frames=retrievals[-1].candidate_frames * 20)
    verifier = VerifierProcess(replace(SETTINGS, max_closures=1000))
    try:
        verifier.start()
        threading.Timer(0.3, os.kill, (verifier.pid, signal.SIGKILL)).start()  # as the OOM killer would
        with pytest.raises(VerifierError, match="the verification process ended"):
            verifier.verify(slow)
        assert verifier.verify(retrievals[0]).keyframe_id == retrievals[0].keyframe_id
        assert verifier.starts == 2
    finally:
        verifier.stop()


def test_a_child_that_stops_answering_is_killed_and_the_next_call_starts_a_new_one(retrievals):
    verifier = VerifierProcess(SETTINGS, answer_timeout=2.0)
    try:
        verifier.start()
        stuck = verifier.pid
        os.kill(stuck, signal.SIGSTOP)  # as a deadlocked registration would: alive, silent
        with pytest.raises(VerifierError, match="gave no answer in 2 s and was killed"):
            verifier.verify(retrievals[0])
        with pytest.raises(ProcessLookupError):  # killed, not left behind
            os.kill(stuck, 0)
        assert verifier.verify(retrievals[0]).keyframe_id == retrievals[0].keyframe_id
        assert verifier.starts == 2
    finally:
        verifier.stop()


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "stopped"])
def test_a_child_lost_while_it_starts_fails_the_start_in_one_line_and_the_next_call_starts_a_new_one(
        retrievals, how):
    verifier = VerifierProcess(SETTINGS, start_timeout=5.0)
    hit = []

    def strike() -> None:  # once the child runs, before it has warmed up (imports take seconds)
        pid = verifier.pid
        if pid is None:
            threading.Timer(0.01, strike).start()
            return
        os.kill(pid, how)
        hit.append(pid)

    try:
        strike()
        with pytest.raises(VerifierError, match="ended|gave no answer in 5 s"):
            verifier.start()
        assert hit and verifier.pid is None
        assert verifier.verify(retrievals[0]).keyframe_id == retrievals[0].keyframe_id
        assert verifier.starts == 2
    finally:
        verifier.stop()
