"""``vbrl loo``: each recording scored by a model that never saw it, retrieval and verified output,
Scan Context beside it; a recording without revisits counts the closures it would publish."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vbrl_ros.model.model_file import load_model
from vbrl_ros.tools.cli import main

pytest.importorskip("vbrl_ros.simulator")


def vbrl(*argv) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """Three recordings: two towns driven twice round (revisits the other way) and a straight
    one-way drive through a third (none), plus a file that is not a recording."""
    root = tmp_path_factory.mktemp("loo")
    small = ["--format", "kitti", "--blocks", "2", "2", "--spacing", "4", "--beams", "16", "--columns", "360",
             "--no-progress"]
    for name, seed, loops, scans in (("town_a", 1, 2, None), ("town_b", 2, 2, None), ("one_way", 3, 1, 25)):
        extra = ["--scans", str(scans)] if scans else []
        assert vbrl("simulate", root / "tmp" / name, "--town-seed", seed, "--loops", loops, *extra, *small) == 0
        (root / "tmp" / name / "summer_clear").rename(root / name)
    (root / "README.md").write_text("not a recording")
    return root


def test_every_recording_is_scored_by_a_model_trained_without_it(folder, tmp_path, capsys):
    out = tmp_path / "loo.json"
    assert vbrl("loo", folder, "--out-dir", tmp_path / "models", "--json", out, "--no-simulated-towns",
                "--quiet") == 0
    text = capsys.readouterr().out
    rows = {row["recording"]: row for row in json.loads(out.read_text())}
    assert set(rows) == {"town_a", "town_b", "one_way"}
    for name in rows:
        model = load_model(tmp_path / "models" / f"without_{name}.npz")
        trained = {Path(p).name for p in model.metadata["sources"]}
        assert name not in trained and len(trained) == 2  # never the one it is scored on
    for name in ("town_a", "town_b"):
        for method in ("vbrl", "scan_context"):
            row = rows[name][method]
            assert row["revisits"] > 0 and 0 <= row["verified_max_f1"] <= 1
            assert {"accepted", "precision", "recall", "f1"} == set(row["node"])
        # the published closures are right: verification rejects what retrieval gets wrong
        assert rows[name]["vbrl"]["node"]["precision"] >= 0.9, rows[name]
    assert rows["one_way"]["vbrl"]["revisits"] == 0
    assert rows["one_way"]["vbrl"]["node"]["accepted"] == 0  # nothing to close, nothing published
    assert "one_way" in text and "closures" in text and "Scan Context" in text
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the table as a chart, beside it
    # the same figures as vbrl eval --verify with the model trained without it: one protocol
    evaluated = tmp_path / "eval.json"
    assert vbrl("eval", folder / "town_a", "--model", tmp_path / "models" / "without_town_a.npz", "--no-ablations",
                "--verify", "--json", evaluated, "--quiet") == 0
    report = json.loads(evaluated.read_text())
    for method, name in (("vbrl", "VBRL"), ("scan_context", "Scan Context")):
        assert rows["town_a"][method]["verified_max_f1"] == report["metrics"][f"{name}, verified"]["5"]["max_f1"]
        assert rows["town_a"][method]["node"] == report["verified"]["at_node_settings"][name]["0.2"]["5"]


def test_the_protocols_own_3_m_radius_scores_as_vbrl_eval_does(folder, tmp_path, capsys):
    out = tmp_path / "loo.json"
    assert vbrl("loo", folder, "--out-dir", tmp_path / "models", "--json", out, "--no-simulated-towns",
                "--radius", "3", "--quiet") == 0
    assert "R = 3 m" in capsys.readouterr().out
    rows = {row["recording"]: row for row in json.loads(out.read_text())}
    assert {row["radius_m"] for row in rows.values()} == {3.0}
    evaluated = tmp_path / "eval.json"
    assert vbrl("eval", folder / "town_b", "--model", tmp_path / "models" / "without_town_b.npz", "--no-ablations",
                "--verify", "--json", evaluated, "--quiet") == 0
    report = json.loads(evaluated.read_text())
    for method, name in (("vbrl", "VBRL"), ("scan_context", "Scan Context")):
        row, metrics = rows["town_b"][method], report["metrics"]
        assert row["revisits"] == metrics[name]["3"]["num_revisits"] != metrics[name]["5"]["num_revisits"]
        assert (row["max_f1"], row["recall_at_1"]) == (metrics[name]["3"]["max_f1"], metrics[name]["3"]["recall_at_1"])
        assert row["verified_max_f1"] == metrics[f"{name}, verified"]["3"]["max_f1"]
        assert row["node"] == report["verified"]["at_node_settings"][name]["0.2"]["3"]


def test_a_bad_radius_is_refused_before_any_work(folder, tmp_path, capsys):
    assert vbrl("loo", folder, "--out-dir", tmp_path / "models", "--radius", "0") == 2
    assert "--radius must be in (0, 100] metres, got 0" in capsys.readouterr().err
    assert not (tmp_path / "models").exists()


def test_a_folder_with_fewer_than_two_recordings_is_refused(tmp_path, capsys):
    assert vbrl("loo", tmp_path) == 2
    assert "leave-one-out needs at least 2" in capsys.readouterr().err


def test_a_bad_submap_setting_is_refused_before_any_work(folder, capsys):
    assert vbrl("loo", folder, "--submap-keyframes", "-1") == 2
    assert "--submap-keyframes: 'submap_keyframes' must be an integer in [0, 10]" in capsys.readouterr().err


def test_drifting_odometry_reaches_every_recording_as_in_vbrl_eval(folder, tmp_path, capsys):
    out = tmp_path / "loo.json"
    assert vbrl("loo", folder, "--out-dir", tmp_path / "models", "--json", out, "--no-simulated-towns",
                "--simulate-drift", "20", "--quiet") == 0
    assert "(--simulate-drift)" in capsys.readouterr().out
    rows = {row["recording"]: row for row in json.loads(out.read_text())}
    evaluated = tmp_path / "eval.json"
    assert vbrl("eval", folder / "town_a", "--model", tmp_path / "models" / "without_town_a.npz", "--no-ablations",
                "--verify", "--simulate-drift", "20", "--json", evaluated, "--quiet") == 0
    report = json.loads(evaluated.read_text())
    assert rows["town_a"]["vbrl"]["max_f1"] == report["metrics"]["VBRL"]["5"]["max_f1"]
    assert rows["town_a"]["vbrl"]["node"] == report["verified"]["at_node_settings"]["VBRL"]["0.2"]["5"]


def test_a_bad_drift_is_refused_before_any_work(folder, capsys):
    assert vbrl("loo", folder, "--simulate-drift", "-2") == 2
    assert "--simulate-drift must be in [0, 45]" in capsys.readouterr().err
