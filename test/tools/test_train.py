"""``vbrl train`` end to end on two small simulated scenarios (KITTI-style folders)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vbrl_ros.model.model_file import load_model
from vbrl_ros.tools import cli
from vbrl_ros.training.ablations import ABLATIONS, ablation_path

sim = pytest.importorskip("vbrl_ros.simulator")
SCENARIOS = ("summer_clear", "winter_snow")


def simulate(folder: Path, spacing: float = 6.0) -> list[Path]:
    """Two scenarios of a 2x2-block town, 2 loops, a 16x360 LiDAR: ~120 scans each, seconds."""
    from vbrl_ros.datasets.kitti_style import write_kitti_style

    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=spacing))
    lidar = sim.LidarConfig(beams=16, columns=360)
    out = []
    for seed, name in enumerate(SCENARIOS, start=1):
        run = sim.simulate_run(town, route, lidar, name, seed=seed)
        out.append(Path(write_kitti_style(folder / name, run.point_clouds(progress=False), run.poses,
                                          run.stamps)))
    return out


def vbrl(monkeypatch: pytest.MonkeyPatch, *argv: str) -> int:
    """``vbrl`` (the real main, its error handling) with only the subcommands under test."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("vbrl_ros.tools.train", "vbrl_ros.tools.evaluate"))
    return cli.main([str(a) for a in argv])


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> list[Path]:
    return simulate(tmp_path_factory.mktemp("sim"))


def test_train_writes_model_ablations_and_figures(sources, tmp_path, monkeypatch, capsys):
    out = tmp_path / "town.npz"
    assert vbrl(monkeypatch, "train", *sources, "--out", out, "--every", "2", "--quiet",
                "--workers", "1") == 0
    text = capsys.readouterr().out
    model = load_model(out)
    assert model.scenarios == list(SCENARIOS)
    assert model.metadata["distance_threshold"] > 0  # the online node's default
    assert model.metadata["distance_threshold_info"]["protocol"] in ("P1", "P2")
    for name, (keep1, keep2) in ABLATIONS.items():
        ablation = load_model(ablation_path(out, name))
        assert (ablation.lambda1, ablation.lambda2) == (10.0 * keep1, 0.1 * keep2)
        assert ablation.config == model.config and ablation.metadata["ablation"] == name
        np.testing.assert_array_equal(ablation.feature_mean, model.feature_mean)  # same data
    for figure in ("modalities", "voxels", "layers"):
        assert (tmp_path / f"town.{figure}.png").read_bytes()[:4] == b"\x89PNG"
    assert "modality shares" in text and "layer shares" in text
    assert "did not converge" not in text + capsys.readouterr().err


def test_streamed_moments_equal_the_loaded_data(sources):
    """``--stream`` featurizes the same keyframes into the same moments as the in-memory path.

    (The solve itself is compared in test_streaming.py on a small grid: a Gram-path solve at
    the default d = 7872 takes minutes.)
    """
    from vbrl_ros.config import VBRLConfig
    from vbrl_ros.training.streaming import RawMoments, stream_moments
    from vbrl_ros.training.training_data import load_training_data, source_labels

    config = VBRLConfig()
    names = source_labels(sources, None)
    options = dict(topic=None, poses="auto", keyframe_distance=None, every=3, workers=1,
                   progress=False)
    moments, info = stream_moments(sources, names, config, chunk=16, **options)
    data = load_training_data(sources, config, labels=names, **options)
    reference = RawMoments(data.descriptors.shape[1], len(data.scenario_names))
    reference.add(data.descriptors, data.labels)
    assert info.scenario_names == data.scenario_names
    assert sum(info.keyframes_per_source) == moments.n == len(data.descriptors)
    np.testing.assert_allclose(np.concatenate(info.positions), data.positions)
    np.testing.assert_allclose(moments.column_sum, reference.column_sum, rtol=1e-12)
    np.testing.assert_array_equal(moments.label_count, reference.label_count)
    np.testing.assert_allclose(moments.gram.stats().G, reference.gram.stats().G, rtol=1e-10, atol=1e-6)


def test_cv_chooses_from_the_grid(sources, tmp_path, monkeypatch, capsys):
    out = tmp_path / "cv.npz"
    assert vbrl(monkeypatch, "train", *sources, "--out", out, "--every", "3", "--quiet",
                "--workers", "1", "--no-ablations", "--cv", "2",
                "--lambda1-grid", "0,10", "--lambda2-grid", "0.1") == 0
    model = load_model(out)
    cv = model.metadata["cv"]
    assert (model.lambda1, model.lambda2) == (cv["best_lambda1"], cv["best_lambda2"])
    assert cv["lambda1_grid"] == [0.0, 10.0] and np.shape(cv["recall_at_1"]) == (2, 1)
    assert (tmp_path / "cv.cv.png").is_file()
    assert "chosen" in capsys.readouterr().out


def test_progress_during_the_solves_and_a_solver_that_did_not_converge(sources, tmp_path, monkeypatch,
                                                                       capsys):
    from vbrl_ros.tools import train

    monkeypatch.setattr(train, "SOLVER_MAX_ITER", 2)  # the IRLS fits stop before converging
    assert vbrl(monkeypatch, "train", *sources, "--out", tmp_path / "m.npz", "--every", "4",
                "--workers", "1") == 0
    captured = capsys.readouterr()
    for bar in ("solving W", "ablations", "solving voxel-only", "objective="):
        assert bar in captured.err, bar
    warnings = [line for line in captured.err.splitlines() if "did not converge" in line]
    # the model and the two iterative ablations; concatenation is a least-squares solve
    assert [line.split(" for ")[1].split(":")[0] for line in warnings] == [
        "the model", "ablation voxel-only", "ablation modality-only"]
    assert all(line.startswith("warning: ") and "stopped at 2 iterations" in line for line in warnings)
    assert "2 iterations (did not converge)" in captured.out


def test_bad_inputs_exit_2(sources, tmp_path, monkeypatch, capsys):
    assert vbrl(monkeypatch, "train", tmp_path / "nope", "--out", tmp_path / "m.npz") == 2
    assert vbrl(monkeypatch, "train", *sources, "--out", tmp_path / "m.npz", "--stream",
                "--cv", "2", "--quiet") == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2 and "--cv" in errors[1]
    assert json.dumps(errors)  # one plain line each


def test_targets_places_labels_y_by_position(sources, tmp_path, monkeypatch, capsys):
    out = tmp_path / "places.npz"
    assert vbrl(monkeypatch, "train", *sources, "--out", out, "--every", "2", "--quiet",
                "--workers", "1", "--no-ablations", "--targets", "places", "--place-size", "20") == 0
    model = load_model(out)
    assert len(model.scenarios) > 2 and all(name.startswith("place_") for name in model.scenarios)
    assert model.W.shape[1] == len(model.scenarios)
    assert "places" in model.metadata["targets"]
    assert vbrl(monkeypatch, "train", *sources, "--out", out, "--targets", "places", "--cv", "2",
                "--quiet") == 2
    assert "--targets places" in capsys.readouterr().err


def test_polar_grid_is_trained_recorded_and_evaluated(sources, tmp_path, monkeypatch, capsys):
    out = tmp_path / "polar.npz"
    assert vbrl(monkeypatch, "train", *sources, "--out", out, "--every", "3", "--quiet",
                "--workers", "1", "--no-ablations", "--grid", "polar", "--rings", "4",
                "--sectors", "8", "--max-range", "30") == 0
    text = capsys.readouterr().out
    model = load_model(out)
    grid = model.config.grid
    assert (grid.kind, grid.rings, grid.sectors, grid.max_range) == ("polar", 4, 8, 30.0)
    assert model.w_voxel.shape == (4 * grid.n_layers,)
    rows = model.layout.sector_rows
    for values in (model.row_weights(), model.feature_scale):
        np.testing.assert_array_equal(values[rows], np.broadcast_to(values[rows[0]], rows.shape))
    assert "ring/layer columns" in text and (tmp_path / "polar.voxels.png").is_file()
    # vbrl eval reads the grid from the model file
    assert vbrl(monkeypatch, "eval", "--model", out, sources[1], "--against", sources[0],
                "--every", "3", "--quiet", "--workers", "1", "--no-scan-context",
                "--json", tmp_path / "eval.json") == 0
    assert json.loads((tmp_path / "eval.json").read_text())


def test_polar_options_need_the_polar_grid(sources, tmp_path, monkeypatch, capsys):
    assert vbrl(monkeypatch, "train", *sources, "--out", tmp_path / "m.npz", "--rings", "4",
                "--quiet") == 2
    assert "--grid polar" in capsys.readouterr().err
    assert vbrl(monkeypatch, "train", *sources, "--out", tmp_path / "m.npz", "--grid", "polar",
                "--sectors", "1", "--quiet") == 2
    assert "grid.sectors" in capsys.readouterr().err
