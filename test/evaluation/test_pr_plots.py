"""PR-curve and leave-one-recording-out PNG output."""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation import evaluate_retrieval
from vbrl_ros.evaluation.plots import leave_one_out_figure, plot_leave_one_out, plot_pr_curves


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


def loo_row(name: str, revisits: int, vbrl: tuple, sc: tuple) -> dict:
    def result(values: tuple) -> dict:
        max_f1, r1, verified, precision, recall, accepted = values
        return {"max_f1": max_f1, "recall_at_1": r1, "revisits": revisits, "verified_max_f1": verified,
                "node": {"accepted": accepted, "precision": precision, "recall": recall, "f1": 0.0}}
    return {"recording": name, "vbrl": result(vbrl), "scan_context": result(sc)}


def test_leave_one_out_chart_draws_each_method_beside_the_other(tmp_path) -> None:
    rows = [loo_row("hand_held", 20, (0.6, 0.9, 0.95, 1.0, 0.85, 17), (0.5, 0.75, 0.9, 0.94, 0.8, 17)),
            loo_row("car", 0, (None, None, None, None, None, 0), (None, None, None, None, None, 3))]
    fig = leave_one_out_figure(rows)
    revisits, none = fig.axes
    heights = [bar.get_height() for bar in revisits.patches]
    # VBRL's four bars, then Scan Context's: retrieval max F1, Recall@1, verified max F1, node recall
    assert heights == [0.6, 0.9, 0.95, 0.85, 0.5, 0.75, 0.9, 0.8]
    texts = [t.get_text() for t in revisits.texts]
    assert texts == ["P 1.00", "P 0.94"]
    shown = none.texts[0].get_text()  # no revisits: the closures each method would publish, no bars
    assert not none.patches and "VBRL: 0 closures" in shown and "Scan Context: 3 closures" in shown
    data = plot_leave_one_out(rows, tmp_path / "loo.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
