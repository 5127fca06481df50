"""Ablation names, their (λ1, λ2) and the sibling-file rule."""

from pathlib import Path

import pytest

from vbrl_ros.training.ablations import (ABLATIONS, ablation_lambdas, ablation_path,
                                         discover_ablations, sibling_path)


def test_lambdas_follow_the_paper():
    assert ablation_lambdas("concatenation", 10, 0.1) == (0.0, 0.0)
    assert ablation_lambdas("voxel-only", 10, 0.1) == (10, 0.0)
    assert ablation_lambdas("modality-only", 10, 0.1) == (0.0, 0.1)
    with pytest.raises(ValueError, match="unknown ablation"):
        ablation_lambdas("nonsense", 1, 1)


def test_sibling_paths():
    assert ablation_path("runs/town.npz", "voxel-only") == Path("runs/town.voxel-only.npz")
    assert sibling_path("runs/town.npz", "cv.png") == Path("runs/town.cv.png")
    assert sibling_path("runs/town.v2.npz", "layers.png") == Path("runs/town.v2.layers.png")


def test_discovery_reports_missing(tmp_path):
    model = tmp_path / "m.npz"
    ablation_path(model, "concatenation").write_bytes(b"")
    found, missing = discover_ablations(model)
    assert list(found) == ["concatenation"]
    assert missing == [n for n in ABLATIONS if n != "concatenation"]
