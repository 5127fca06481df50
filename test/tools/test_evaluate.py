"""``vbrl eval`` end to end: P1 and P2, five methods, JSON + PNG + matches dump, poses unused."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.evaluation import evaluate_matches_file
from vbrl_ros.model.model_file import load_model
from vbrl_ros.tools import cli
from vbrl_ros.training.ablations import ablation_path

sim = pytest.importorskip("vbrl_ros.simulator")
METHODS = ["VBRL", "concatenation", "voxel-only", "modality-only", "Scan Context"]
METRICS = ("max_f1", "average_precision", "recall_at_100_precision", "recall_at_1", "recall_at_5",
           "num_queries", "num_revisits")


def vbrl(monkeypatch: pytest.MonkeyPatch, *argv) -> int:
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("vbrl_ros.tools.train", "vbrl_ros.tools.evaluate"))
    return cli.main([str(a) for a in argv])


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[list[Path], Path]:
    """Two simulated scenarios (~60 scans each) and a model + ablations trained on them."""
    from vbrl_ros.datasets.kitti_style import write_kitti_style

    folder = tmp_path_factory.mktemp("eval")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=10.0))
    lidar = sim.LidarConfig(beams=16, columns=360)
    sources = []
    for seed, name in enumerate(("summer_clear", "winter_snow"), start=1):
        run = sim.simulate_run(town, route, lidar, name, seed=seed)
        sources.append(Path(write_kitti_style(folder / name, run.point_clouds(progress=False),
                                              run.poses, run.stamps)))
    model = folder / "model.npz"
    with pytest.MonkeyPatch.context() as mp:
        assert vbrl(mp, "train", *sources, "--out", model, "--quiet", "--workers", "1") == 0
    return sources, model


def _read(path: Path) -> dict:
    return json.loads(path.read_text())


def _as_json(summary: dict) -> dict:
    """What the JSON holds: undefined (NaN/inf) metrics are null."""
    return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in summary.items()}


def _positions(folder: Path) -> np.ndarray:
    return np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)[:, :, 3]


def test_p1_all_methods_json_png_and_matches(trained, tmp_path, monkeypatch):
    (summer, _), model = trained
    out = tmp_path / "p1.json"
    dump, sc_dump = tmp_path / "p1.matches.json", tmp_path / "p1.sc_matches.json"
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--json", out, "--dump-matches", dump,
                "--dump-sc-matches", sc_dump, "--exclude", "20", "--quiet", "--workers", "1") == 0
    report = _read(out)
    assert report["protocol"] == "P1" and report["methods"] == METHODS
    for name in METHODS:
        for radius in ("3", "5"):
            assert set(METRICS) <= set(report["metrics"][name][radius])
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"
    for radius in ("3", "5"):  # every revisit is in one heading class
        for name in METHODS:
            split, metrics = report["recall_at_1_by_heading"][radius][name], report["metrics"][name][radius]
            assert sum(c["revisits"] for c in split.values()) == metrics["num_revisits"] > 0
            assert sum(c["hits"] for c in split.values()) == round(metrics["recall_at_1"] * metrics["num_revisits"])
    entries = _read(dump)
    assert {"query", "match", "distance"} <= set(entries[0])
    # each dump recomputes its method's metrics in the JSON exactly
    for path, name in ((dump, "VBRL"), (sc_dump, "Scan Context")):
        for radius in (3.0, 5.0):
            again = _as_json(evaluate_matches_file(path, _positions(summer), radius=radius,
                                                   exclude=20).summary())
            assert again == pytest.approx(report["metrics"][name][f"{radius:g}"], nan_ok=True)
    assert _read(sc_dump) != entries


def test_p2_with_alignment(trained, tmp_path, monkeypatch):
    (summer, winter), model = trained
    align = tmp_path / "T.txt"
    np.savetxt(align, np.eye(4))
    out, dump = tmp_path / "p2.json", tmp_path / "p2.matches.json"
    plot = tmp_path / "curves.png"
    assert vbrl(monkeypatch, "eval", winter, "--against", summer, "--model", model, "--align", align,
                "--json", out, "--plot", plot, "--dump-matches", dump, "--quiet", "--workers", "1") == 0
    report = _read(out)
    assert report["protocol"] == "P2" and report["methods"] == METHODS and plot.is_file()
    assert report["metrics"]["VBRL"]["3"]["num_revisits"] > 0
    again = _as_json(evaluate_matches_file(dump, _positions(winter), radius=3.0,
                                           database_positions=_positions(summer)).summary())
    assert again == pytest.approx(report["metrics"]["VBRL"]["3"], nan_ok=True)


def test_check_exact_adds_brute_force_agreement_and_key_headroom(trained, tmp_path, monkeypatch,
                                                                 capsys):
    (summer, winter), model = trained
    out = tmp_path / "p2.json"
    assert vbrl(monkeypatch, "eval", winter, "--against", summer, "--model", model, "--check-exact",
                "--no-ablations", "--no-scan-context", "--json", out, "--quiet", "--workers",
                "1") == 0
    report = _read(out)
    assert report["methods"] == ["VBRL", "VBRL, exact"]
    agreement = report["exact_agreement"]
    n = report["num_query_keyframes"]
    assert agreement["queries"] == n and agreement["same_top1"] >= n - 1  # tiny database
    headroom = agreement["key_rank"]  # over the correct brute-force matches
    exact_recall = report["metrics"]["VBRL, exact"]["3"]
    assert headroom["queries"] == round(exact_recall["recall_at_1"] * exact_recall["num_revisits"])
    assert headroom["queries"] > 0 and headroom["radius"] == 3.0
    within = headroom["within"]
    assert within["0.005"] <= within["0.01"] <= within["0.05"] <= headroom["queries"]
    assert 0.0 <= headroom["median_share"] < 1.0
    printed = capsys.readouterr().out
    assert "top-1 equals the unpruned brute-force top-1" in printed and "key headroom" in printed


def test_matching_uses_poses_only_as_the_node_uses_odometry(trained, tmp_path, monkeypatch):
    """Poses are the ground truth; matching uses them only as the node uses odometry: to match the
    earlier keyframes of a sequence by place (and to merge a trail, which this model has not).
    Each query alone (``--sequence-length 1``), zeroed poses change nothing; in sequences they do."""
    (summer, _), model = trained
    zeroed = tmp_path / "zeroed"
    zeroed.mkdir()
    (zeroed / "velodyne").symlink_to(summer / "velodyne")
    shutil.copy(summer / "times.txt", zeroed / "times.txt")
    n = len(_positions(summer))
    np.savetxt(zeroed / "poses.txt", np.tile([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], (n, 1)))
    dumps = {}
    for length in ("1", "4"):
        for folder in (summer, zeroed):
            dumps[length, folder] = tmp_path / f"m{length}{folder.name}.json"
            assert vbrl(monkeypatch, "eval", folder, "--model", model, "--dump-matches", dumps[length, folder],
                        "--exclude", "20", "--no-ablations", "--no-scan-context", "--quiet", "--sequence-length",
                        length, "--workers", "1", "--out-dir", tmp_path) == 0
    assert _read(dumps["1", summer]) == _read(dumps["1", zeroed])
    assert _read(dumps["4", summer]) != _read(dumps["4", zeroed])


def test_missing_ablation_is_skipped_with_a_note(trained, tmp_path, monkeypatch, capsys):
    (summer, _), model = trained
    lone = tmp_path / "lone.npz"
    shutil.copy(model, lone)
    shutil.copy(ablation_path(model, "voxel-only"), ablation_path(lone, "voxel-only"))
    assert vbrl(monkeypatch, "eval", summer, "--model", lone, "--json", tmp_path / "r.json",
                "--exclude", "20", "--quiet", "--workers", "1", "--no-scan-context") == 0
    report = _read(tmp_path / "r.json")
    assert report["methods"] == ["VBRL", "voxel-only"]
    assert "skipped" in capsys.readouterr().out


def test_bad_inputs_exit_2_with_one_line(trained, tmp_path, monkeypatch, capsys):
    (summer, winter), model = trained
    base = ["--quiet", "--workers", "1"]
    assert vbrl(monkeypatch, "eval", summer, "--model", tmp_path / "missing.npz", *base) == 2
    # an ablation of another configuration cannot share the descriptors
    other = tmp_path / "other.npz"
    shutil.copy(model, other)
    m = load_model(model)
    m.config = VBRLConfig(grid=VoxelGridConfig(cells_xy=4))
    m.W = np.zeros((m.config.grid.n_voxels * 41, 2))
    d = len(m.W)
    from vbrl_ros.model.model_file import VBRLModel

    VBRLModel(config=m.config, W=m.W, feature_mean=np.zeros(d), feature_scale=np.ones(d),
              lambda1=0, lambda2=0, scenarios=m.scenarios).save(ablation_path(other, "concatenation"))
    assert vbrl(monkeypatch, "eval", summer, "--model", other, *base) == 2
    bad = tmp_path / "T.txt"
    np.savetxt(bad, np.eye(3))
    assert vbrl(monkeypatch, "eval", winter, "--against", summer, "--model", model, "--align", bad,
                *base) == 2
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--align", bad, *base) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 4
    assert "missing.npz" in errors[0] and "another configuration" in errors[1]
    assert "4x4" in errors[2] and "--against" in errors[3]


@pytest.mark.parametrize("flag, length", [("--sequence-length", "0"), ("--sequence-length", "21"),
                                          ("--sc-sequence-length", "0")])
def test_a_bad_sequence_length_is_named(trained, tmp_path, monkeypatch, capsys, flag, length):
    (summer, _), model = trained
    assert vbrl(monkeypatch, "eval", summer, "--model", model, flag, length, "--quiet") == 2
    assert capsys.readouterr().err.strip() == f"vbrl eval: error: {flag} must be an integer in [1, 20]"


def test_a_trail_changes_what_vbrl_describes_and_is_reported(trained, tmp_path, monkeypatch, capsys):
    (summer, _), model = trained  # keyframes 10 m apart: a 12 m trail merges the one before
    dumps = {}
    for trail in (None, "12"):
        out, dumps[trail] = tmp_path / f"t{trail}.json", tmp_path / f"t{trail}.matches.json"
        assert vbrl(monkeypatch, "eval", summer, "--model", model, "--json", out, "--dump-matches", dumps[trail],
                    "--exclude", "20", "--no-ablations", "--no-scan-context", "--quiet", "--workers", "1",
                    *(["--trail", trail] if trail else [])) == 0
        assert _read(out)["trail_m"] == (0.0 if trail is None else 12.0)  # the paper model has none
    alone, trailed = ([row["distance"] for row in _read(dumps[t])] for t in (None, "12"))
    assert alone != pytest.approx(trailed)
    # Scan Context reads the scan alone unless told to read the same trail, like for like
    reports = {}
    for extra in ([], ["--sc-trail"]):
        reports[bool(extra)] = out = tmp_path / f"sc{bool(extra)}.json"
        assert vbrl(monkeypatch, "eval", summer, "--model", model, "--json", out, "--exclude", "20",
                    "--no-ablations", "--quiet", "--workers", "1", "--trail", "12", *extra) == 0
    plain, trailed_sc = (_read(reports[k]) for k in (False, True))
    assert (plain["sc_trail"], trailed_sc["sc_trail"]) == (False, True)
    assert plain["metrics"]["VBRL"] == trailed_sc["metrics"]["VBRL"]
    assert plain["metrics"]["Scan Context"] != trailed_sc["metrics"]["Scan Context"]
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--trail", "-1", "--quiet") == 2
    assert capsys.readouterr().err.strip() == "vbrl eval: error: --trail must be a number of metres in [0, 20]"
    # the trail reaching ahead too merges the keyframe after each one as well; a model that was
    # described so is evaluated so without being told
    out, ahead = tmp_path / "ahead.json", tmp_path / "ahead.matches.json"
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--json", out, "--dump-matches", ahead,
                "--exclude", "20", "--no-ablations", "--no-scan-context", "--quiet", "--workers", "1",
                "--trail", "12", "--trail-ahead", "12") == 0
    assert _read(out)["trail_ahead_m"] == 12.0
    assert [row["distance"] for row in _read(ahead)] != pytest.approx(trailed)
    loaded = load_model(model)
    both_ways = replace(loaded, config=replace(loaded.config, features=replace(
        loaded.config.features, trail_m=12.0, trail_ahead_m=12.0))).save(tmp_path / "both_ways.npz")
    out, own = tmp_path / "own.json", tmp_path / "own.matches.json"
    assert vbrl(monkeypatch, "eval", summer, "--model", both_ways, "--json", out, "--dump-matches", own,
                "--exclude", "20", "--no-ablations", "--no-scan-context", "--quiet", "--workers", "1") == 0
    assert _read(out)["trail_ahead_m"] == 12.0
    assert [row["distance"] for row in _read(own)] == pytest.approx([row["distance"] for row in _read(ahead)])
    # --trail 0 on such a model: no trail behind, so none ahead either (not a refused configuration)
    assert vbrl(monkeypatch, "eval", summer, "--model", both_ways, "--json", out, "--dump-matches", own,
                "--exclude", "20", "--no-ablations", "--no-scan-context", "--quiet", "--workers", "1",
                "--trail", "0") == 0
    assert (_read(out)["trail_m"], _read(out)["trail_ahead_m"]) == (0.0, 0.0)
    assert [row["distance"] for row in _read(own)] == pytest.approx([row["distance"] for row in _read(dumps[None])])
    assert _read(tmp_path / "tNone.json")["trail_ahead_m"] == 0.0
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--trail-ahead", "nan", "--quiet") == 2
    assert capsys.readouterr().err.strip().endswith("--trail-ahead must be a number of metres in [0, 20]")


@pytest.mark.parametrize("missing", ["query", "--against", "--model"])
def test_a_missing_path_fails_before_any_source_is_described(missing, tmp_path, monkeypatch, capsys):
    import vbrl_ros.evaluation.methods as methods

    def describe_source(*args, **kwargs):
        raise AssertionError("described a source before checking the paths")

    monkeypatch.setattr(methods, "describe_source", describe_source)
    source, absent = tmp_path / "source", tmp_path / "nonexistent"
    source.mkdir()
    argv = {"query": [absent, "--against", source], "--against": [source, "--against", absent],
            "--model": [source, "--model", absent]}[missing]
    assert vbrl(monkeypatch, "eval", *argv, "--quiet") == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and f"{absent} does not exist" in error
    assert error.startswith("vbrl eval: error: " + ("QUERY_SOURCE" if missing == "query" else missing))


def test_a_hidden_wedge_reaches_both_methods_and_the_report(trained, tmp_path, monkeypatch, capsys):
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source

    (summer, _), model = trained
    config, sc = load_model(model).config, ScanContextConfig()
    plain, hidden = (describe_source(summer, config, sc, progress=False, workers=1, verification_voxel=1.0,
                                     blocked_azimuth=wedge) for wedge in (None, (90.0, -90.0)))
    # the half behind the sensor (Scan Context's sectors 15-44 start at +x, counter-clockwise) is gone
    assert np.abs(plain.scan_context[:, :, 16:44]).sum() > 0
    assert not hidden.scan_context[:, :, 16:44].any() and hidden.scan_context[:, :, :14].any()
    assert not np.allclose(plain.vbrl, hidden.vbrl)
    assert sum(map(len, hidden.clouds.clouds)) < 0.7 * sum(map(len, plain.clouds.clouds))

    out = tmp_path / "hidden.json"
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--no-ablations", "--no-scan-context",
                "--blocked-azimuth", "90", "-90", "--json", out, "--quiet", "--workers", "1") == 0
    report = _read(out)
    assert report["blocked_azimuth"] == [90.0, -90.0]
    assert any("-90 degrees" in note for note in report["notes"])
    capsys.readouterr()
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--blocked-azimuth", "30", "30", "--quiet") == 2
    assert capsys.readouterr().err.strip() == ("vbrl eval: error: --blocked-azimuth must be (start, end) in "
                                               "[-180, 180] degrees spanning less than a full turn, got [30.0, 30.0]")


def test_a_tilted_mount_turns_scans_and_poses_and_the_ground_frame_undoes_it(trained, tmp_path, monkeypatch,
                                                                           capsys):
    """``--mount-tilt``: the same points, turned as a sensor held at 20 and 35 degrees would see
    them. The built-in model levels every scan on its own ground, so its descriptors barely move
    (far less than to any other keyframe); Scan Context's, read in the sensor's frame, change."""
    from vbrl_ros.datasets.mount_tilt import mount_rotation
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source
    from vbrl_ros.model.builtin import DEFAULT_MODEL_PATH

    def apart(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        axes = tuple(range(1, a.ndim))
        return np.abs(a - b).sum(axis=axes) / (np.abs(a).sum(axis=axes) + np.abs(b).sum(axis=axes))

    (summer, _), _ = trained
    config, sc = load_model(DEFAULT_MODEL_PATH).config, ScanContextConfig()
    # the levelling alone: turned this far, the simulated narrow field would also be mirrored, which
    # drops what a sensor so tilted would not see turned round (test/features/test_field_of_view.py)
    config = replace(config, features=replace(config.features, mirror_field_of_view=False))
    plain = describe_source(summer, config, sc, progress=False, workers=1, verification_voxel=1.0)
    nearest_other = min(apart(plain.vbrl[i:i + 1], np.delete(plain.vbrl, i, 0)).min() for i in range(len(plain.vbrl)))
    for tilt in ((0.0, 20.0), (10.0, 35.0), (-35.0, 0.0)):
        tilted = describe_source(summer, config, sc, progress=False, workers=1, verification_voxel=1.0,
                                 mount_tilt=tilt)
        np.testing.assert_allclose(tilted.positions, plain.positions)
        np.testing.assert_allclose(tilted.poses[:, :3, :3], plain.poses[:, :3, :3] @ mount_rotation(*tilt),
                                   atol=1e-12)
        assert apart(plain.vbrl, tilted.vbrl).max() < 0.25 * nearest_other, tilt
        assert np.median(apart(plain.scan_context, tilted.scan_context)) > 0.5, tilt

    out = tmp_path / "tilted.json"
    assert vbrl(monkeypatch, "eval", summer, "--model", trained[1], "--no-ablations", "--no-scan-context",
                "--mount-tilt", "0", "20", "--json", out, "--quiet", "--workers", "1") == 0
    report = _read(out)
    assert report["mount_tilt"] == [0.0, 20.0] and report["blocked_azimuth"] is None
    assert any("pitch 20 degrees" in note for note in report["notes"])
    capsys.readouterr()
    assert vbrl(monkeypatch, "eval", summer, "--model", trained[1], "--mount-tilt", "0", "50", "--quiet") == 2
    assert capsys.readouterr().err.strip() == ("vbrl eval: error: --mount-tilt must be (roll, pitch) in "
                                               "[-45, 45] degrees, got [0.0, 50.0]")


def test_simulated_drift_reaches_odometry_and_leaves_the_ground_truth(trained, tmp_path, monkeypatch, capsys):
    """``--simulate-drift``: sequences matched by place read drifting poses, while the revisits,
    the heading split and the metrics' ground truth read the recorded ones."""
    (summer, _), model = trained
    reports, dumps = [], []
    for drift in ("0", "20"):
        reports.append(tmp_path / f"d{drift}.json")
        dumps.append(tmp_path / f"d{drift}.matches.json")
        assert vbrl(monkeypatch, "eval", summer, "--model", model, "--no-ablations", "--no-scan-context",
                    "--simulate-drift", drift, "--exclude", "20", "--json", reports[-1], "--dump-matches",
                    dumps[-1], "--quiet", "--workers", "1", "--out-dir", tmp_path) == 0
    plain, drifted = _read(reports[0]), _read(reports[1])
    assert drifted["simulate_drift_deg"] == 20.0 and plain["simulate_drift_deg"] == 0.0
    assert any("--simulate-drift" in note for note in drifted["notes"])
    for radius in ("3", "5"):
        assert drifted["metrics"]["VBRL"][radius]["num_revisits"] == plain["metrics"]["VBRL"][radius]["num_revisits"]
        assert {k: v["revisits"] for k, v in drifted["recall_at_1_by_heading"][radius]["VBRL"].items()} == \
               {k: v["revisits"] for k, v in plain["recall_at_1_by_heading"][radius]["VBRL"].items()}
    assert _read(dumps[0]) != _read(dumps[1])  # the sequences' places moved
    capsys.readouterr()
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--simulate-drift", "-1", "--quiet") == 2
    assert capsys.readouterr().err.strip() == ("vbrl eval: error: --simulate-drift must be in [0, 45] degrees "
                                               "per sqrt(100 m), got -1.0")


def test_filling_blind_wedges_can_be_switched_for_a_like_for_like_comparison(trained, tmp_path, monkeypatch,
                                                                            capsys):
    (summer, _), model = trained
    dumps, printed = {}, {}
    for flag in ("--fill-blind-wedges", "--no-fill-blind-wedges"):  # the built-in model's and without
        dumps[flag] = tmp_path / f"{flag}.matches.json"
        capsys.readouterr()
        assert vbrl(monkeypatch, "eval", summer, "--blocked-azimuth", "135", "-135", "--dump-matches",
                    dumps[flag], "--plot", tmp_path / "pr.png", "--exclude", "6", "--no-ablations",
                    "--no-scan-context", "--quiet", "--workers", "1", flag) == 0
        printed[flag] = [line for line in capsys.readouterr().out.splitlines() if line.startswith("all round, ")]
    filled, hidden = ([row["distance"] for row in _read(dumps[f])] for f in dumps)
    assert filled != pytest.approx(hidden)
    # the report says how many keyframes were compared all round: here some, and none without
    assert len(printed["--fill-blind-wedges"]) == 1 and not printed["--no-fill-blind-wedges"]
    count, total = (int(n) for n in re.search(r"(\d+) of (\d+) keyframes", printed["--fill-blind-wedges"][0]).groups())
    assert 0 < count < total
    # a model that neither mirrors wedges nor has a forward trail cannot fill them: one line
    capsys.readouterr()
    assert vbrl(monkeypatch, "eval", summer, "--model", model, "--fill-blind-wedges", "--quiet") == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("vbrl eval: error:") and "features.fill_blind_wedges" in error
    assert len(error.splitlines()) == 1
