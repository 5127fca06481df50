"""``vbrl eval`` with the built-in model and ``vbrl train --descriptor recognition``, end to end.

Sources are KITTI-style folders written by ``vbrl simulate``: a short drive (30 scans) and a
two-loop drive that comes back along its streets the other way (175 scans).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH
from vbrl_ros.model.model_file import load_model
from vbrl_ros.tools.cli import main
from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config

pytest.importorskip("vbrl_ros.simulator")

SMALL = ["--format", "kitti", "--blocks", "2", "2", "--spacing", "4", "--beams", "16", "--columns", "360",
         "--quiet"]
QUICK = ["--quiet", "--workers", "1"]


def vbrl(*argv) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("recognition")
    assert vbrl("simulate", folder / "short", "--loops", "1", "--scans", "30", *SMALL) == 0
    assert vbrl("simulate", folder / "loops", "--loops", "2", *SMALL) == 0
    return {"short": folder / "short" / "summer_clear", "loops": folder / "loops" / "summer_clear",
            "folder": folder}


@pytest.fixture(scope="module")
def places_model(sources) -> Path:
    """A recognition-descriptor model trained on the short drive (place targets)."""
    out = sources["folder"] / "places.npz"
    assert vbrl("train", sources["short"], "--out", out, "--descriptor", "recognition", "--targets", "places",
                "--no-ablations", *QUICK) == 0
    return out


def test_eval_without_a_model_uses_the_built_in_one(sources, tmp_path, capsys):
    out = tmp_path / "metrics.json"
    assert vbrl("eval", sources["short"], "--exclude", "5", "--no-scan-context", "--json", out, *QUICK) == 0
    text = capsys.readouterr().out
    assert "P1 summer_clear (exclude 5): 30 query keyframes" in text
    assert "in-sample" not in text  # the built-in model was not trained on this folder
    report = json.loads(out.read_text())
    assert report["methods"] == ["VBRL"]
    assert Path(report["model"]) == DEFAULT_MODEL_PATH
    assert report["grid"] == load_model(DEFAULT_MODEL_PATH).config.grid.kind == "polar"
    assert report["metrics"]["VBRL"]["3"]["num_queries"] == 25


def test_the_built_in_model_is_todays_recognition_descriptor():
    # a preset changed without `vbrl demo --rebuild-default-model` would ship a stale model
    model = load_model(DEFAULT_MODEL_PATH)
    assert model.config == recognition_config() and model.config.features.mirror_blind_wedges
    assert model.translation_search() == RECOGNITION_TRANSLATION_SEARCH_M


def test_the_trained_model_is_the_recognition_descriptor_with_translation_search(places_model):
    model = load_model(places_model)
    assert model.config == recognition_config()
    assert model.metadata["translation_search"] == RECOGNITION_TRANSLATION_SEARCH_M == 1.5
    assert model.translation_search() == 1.5
    assert model.metadata["targets"].startswith("places")


def test_eval_on_the_training_source_says_it_is_in_sample(sources, places_model, tmp_path, capsys):
    assert vbrl("eval", sources["short"], "--model", places_model, "--exclude", "5", "--no-scan-context",
                "--no-ablations", "--out-dir", tmp_path, *QUICK) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert notes == [f"note: the model was trained on {sources['short']}: these results are in-sample, not a test"]
    # another source is a test: no note
    assert vbrl("eval", sources["loops"], "--model", places_model, "--exclude", "10", "--no-scan-context",
                "--no-ablations", "--out-dir", tmp_path, *QUICK) == 0
    assert (tmp_path / "pr.png").is_file()
    assert "in-sample" not in capsys.readouterr().out


@pytest.mark.parametrize("which", ["QUERY_SOURCE", "--against", "--model"])
def test_a_missing_path_fails_fast_with_one_line_naming_it(sources, tmp_path, capsys, which):
    missing = tmp_path / "nowhere"
    argv = {"QUERY_SOURCE": [missing], "--against": [sources["short"], "--against", missing],
            "--model": [sources["short"], "--model", missing]}[which]
    assert vbrl("eval", *argv, "--out-dir", tmp_path, *QUICK) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert lines == [f"vbrl eval: error: {which} {missing} does not exist"]
    assert "keyframes" not in captured.out  # nothing was described


def test_train_with_pair_targets(sources, tmp_path):
    out = tmp_path / "pairs.npz"
    assert vbrl("train", sources["loops"], "--out", out, "--descriptor", "recognition", "--targets", "pairs",
                "--rings", "10", "--sectors", "12", "--no-ablations", *QUICK) == 0
    model = load_model(out)
    assert model.scenarios == ["same_place", "different_place"]
    assert model.config == recognition_config(rings=10, sectors=12)
    assert model.metadata["targets"] == "pairs" and model.metadata["translation_search"] == 1.5
    assert model.metadata["pairs"]["same_place"] > 0 and model.metadata["pairs"]["different_place"] > 0
    assert model.metadata["distance_threshold"] > 0
