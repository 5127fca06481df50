"""PR-curve PNG output."""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation import evaluate_retrieval
from vbrl_ros.evaluation.plots import plot_pr_curves


def test_pr_plot_written(tmp_path) -> None:
    rng = np.random.default_rng(0)
    db = rng.uniform(0, 100, (50, 3))
    q = db + rng.normal(0, 0.5, db.shape)
    good = evaluate_retrieval(q, db, np.arange(50)[:, None], rng.uniform(0, 1, (50, 1)), 3.0)
    noisy = evaluate_retrieval(q, db, rng.integers(0, 50, (50, 1)), rng.uniform(0, 1, (50, 1)), 3.0)
    out = plot_pr_curves({"oracle": good, "random": noisy}, tmp_path / "pr.png", title="test")
    data = out.read_bytes()
    assert len(data) > 1000
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
