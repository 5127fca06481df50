"""``vbrl eval --verify``: the verified output beside retrieval, for the model and Scan Context.

The source is a KITTI-style folder written by ``vbrl simulate``: two loops that drive their
streets the other way round, 16 beams (sparse, as a cheap sensor is).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from vbrl_ros.evaluation.metrics import evaluate_online
from vbrl_ros.tools.cli import main

pytest.importorskip("vbrl_ros.simulator")

EXCLUDE = "10"


def vbrl(*argv) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def verified(tmp_path_factory) -> tuple[dict, list[dict], Path, str]:
    folder = tmp_path_factory.mktemp("verified")
    assert vbrl("simulate", folder / "loops", "--format", "kitti", "--loops", "2", "--blocks", "2", "2",
                "--spacing", "4", "--beams", "16", "--columns", "360", "--no-progress") == 0
    source = folder / "loops" / "summer_clear"
    out, dump = folder / "metrics.json", folder / "matches.json"
    import contextlib
    import io

    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert vbrl("eval", source, "--verify", "--exclude", EXCLUDE, "--json", out, "--dump-matches", dump,
                    "--dump-sc-matches", folder / "sc_matches.json", "--no-ablations", "--quiet", "--workers", "2",
                    "--min-fitness", "0.2", "0.1") == 0
    return json.loads(out.read_text()), json.loads(dump.read_text()), source, text.getvalue()


def test_verified_rows_beside_retrieval_for_both_methods(verified):
    report, _, _, text = verified
    assert report["methods"] == ["VBRL", "Scan Context", "VBRL, verified", "Scan Context, verified"]
    assert "at the node's settings (top 3, min_fitness 0.1, 0.2," in text
    points = report["verified"]["at_node_settings"]
    assert set(points) == {"VBRL", "Scan Context"}
    # simulated revisits, reversed on the other lane: what the node publishes is right and plenty
    at_5m = points["VBRL"]["0.2"]["5"]
    assert at_5m["precision"] >= 0.95 and at_5m["recall"] >= 0.5, at_5m
    assert report["metrics"]["VBRL, verified"]["5"]["max_f1"] >= 0.7
    assert report["verified"]["settings"]["top_k"] == 3
    assert report["verified"]["settings"]["odometry_drift"] == 0.1  # the node's, from the source's poses
    # a lower threshold publishes at least as much, and nothing it kept before is lost
    assert points["VBRL"]["0.1"]["5"]["accepted"] >= at_5m["accepted"]
    assert points["VBRL"]["0.1"]["5"]["recall"] >= at_5m["recall"]


def test_the_dump_names_the_best_verified_candidate_and_recomputes_the_swept_metrics(verified):
    report, entries, source, _ = verified
    assert {"query", "match", "distance", "fitness", "candidates", "candidate_fitness",
            "candidate_rejection"} <= set(entries[0])
    unverified = [e for e in entries if math.isnan(e["fitness"])]
    assert unverified and all(e["match"] == e["candidates"][0] for e in unverified if e["candidates"])
    for e in entries:
        accepted = [f for f, why in zip(e["candidate_fitness"], e["candidate_rejection"]) if why is None]
        assert (max(accepted) if accepted else None) == (None if math.isnan(e["fitness"]) else e["fitness"])
    # any tool recomputes the verified row from the dump: score = 1 - fitness, lower = better
    assert _verified_max_f1(entries, source) == pytest.approx(report["metrics"]["VBRL, verified"]["5"]["max_f1"])


def test_a_verified_match_is_the_stored_keyframe_nearest_the_query_along_the_registered_ones_path(verified):
    """As the node publishes it (detection.nearest_keyframe): the dump's match is the registered
    candidate or a keyframe nearer the query next to it, one the query's database holds."""
    _, entries, source, _ = verified
    positions = np.loadtxt(source / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    moved = 0
    for e in entries:
        if math.isnan(e["fitness"]):
            continue
        registered = e["candidates"][e["candidate_fitness"].index(e["fitness"])]
        assert e["match"] <= e["query"] - int(EXCLUDE)
        if e["match"] != registered:
            moved += 1
            near, far = (np.linalg.norm(positions[i] - positions[e["query"]]) for i in (e["match"], registered))
            assert near < far and abs(e["match"] - registered) <= 2, e  # keyframes 4 m apart, 5 m of reach
    assert moved > 0
    # what the node would publish at 3 m reads the moved closures too
    assert _verified_max_f1(entries, source, radius=3.0) == pytest.approx(
        json.loads((source.parent.parent / "metrics.json").read_text())["metrics"]["VBRL, verified"]["3"]["max_f1"])


def test_scan_contexts_dump_recomputes_its_own_verified_row(verified):
    report, entries, source, _ = verified
    sc_entries = json.loads((source.parent.parent / "sc_matches.json").read_text())
    assert [e["query"] for e in sc_entries] == [e["query"] for e in entries]
    assert [e["candidates"] for e in sc_entries] != [e["candidates"] for e in entries]  # its own candidates
    sc_row = report["metrics"]["Scan Context, verified"]["5"]["max_f1"]
    assert _verified_max_f1(sc_entries, source) == pytest.approx(sc_row)


def _verified_max_f1(entries: list[dict], source: Path, radius: float = 5.0) -> float:
    """Max F1 at ``radius`` of a verified dump's best candidates scored 1 - fitness."""
    positions = np.loadtxt(source / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    indices = np.full((len(positions), 1), -1)
    scores = np.full((len(positions), 1), np.inf)
    for e in entries:
        if not math.isnan(e["fitness"]):
            indices[e["query"]], scores[e["query"]] = e["match"], 1.0 - e["fitness"]
    return evaluate_online(positions, indices, scores, radius, int(EXCLUDE)).max_f1


def test_bad_verification_options_say_which(tmp_path, capsys):
    source = tmp_path / "missing"
    for option, value, named in (("--min-fitness", "1.5", "min_fitness"), ("--verify-top-k", "0", "top_k"),
                                 ("--max-closure-distance", "-1", "max_closure_distance"),
                                 ("--submap-keyframes", "11", "submap_keyframes"),
                                 ("--odometry-drift", "2", "--odometry-drift: 'odometry_drift'"),
                                 ("--distance-threshold", "nan", "--distance-threshold")):
        assert vbrl("eval", source, "--verify", option, value) != 0
        assert named in capsys.readouterr().err
    assert vbrl("eval", source, "--no-scan-context", "--dump-sc-matches", tmp_path / "sc.json") != 0
    assert "--dump-sc-matches needs Scan Context" in capsys.readouterr().err


def test_a_wider_verify_top_k_retrieves_the_spares_the_odometry_gate_draws_on(verified):
    from vbrl_ros.detection.odometry_gate import SPARE_FACTOR
    from vbrl_ros.tools import evaluate
    from vbrl_ros.tools.cli import build_parser
    from vbrl_ros.training.ablations import FULL_NAME

    _, _, source, _ = verified
    top_k = 4  # with its spares 12 candidates, more than the node's top_k needs
    args = build_parser().parse_args([str(a) for a in (
        "eval", source, "--verify", "--verify-top-k", top_k, "--exclude", EXCLUDE, "--no-ablations",
        "--no-scan-context", "--quiet", "--workers", "2")])
    evaluation = evaluate.load(args)
    results = evaluate.retrieve(args, evaluation, next(m for m in evaluation.methods if m.name == FULL_NAME))
    spares = top_k * SPARE_FACTOR
    assert results.k >= spares and (results.indices[:, spares - 1] >= 0).any()  # kept, and filled by the model


def test_the_revisits_the_node_missed_are_counted_by_why_and_add_up_to_what_recall_leaves(verified):
    report, _, _, text = verified
    assert "revisits not published there, by why" in text
    for method in ("VBRL", "Scan Context"):
        for fitness in ("0.1", "0.2"):
            for radius in ("3", "5"):
                missed = report["verified"]["missed_revisits"][method][fitness][radius]
                point = report["verified"]["at_node_settings"][method][fitness][radius]
                revisits = report["metrics"][method][radius]["num_revisits"]
                assert all(count >= 0 for count in missed.values())
                assert sum(missed.values()) == round(revisits * (1.0 - point["recall"])), (method, fitness, radius)
