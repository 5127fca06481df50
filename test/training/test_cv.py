"""Place-disjoint cross-validation of (λ1, λ2) and the recommended threshold."""

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.training.cv import cross_validate, format_cv_table, place_folds, plot_cv
from vbrl_ros.training.fit import fit_model
from vbrl_ros.training.threshold import recommend_threshold

SMALL = VBRLConfig(grid=VoxelGridConfig(extent_xy=20.0, cells_xy=2, z_edges=(-2.0, 0.0, 3.0)))


def _route(n_per_loop=60, loops=2):
    """A square loop (160 m) driven twice: the second loop revisits every place."""
    s = np.linspace(0, 160, n_per_loop, endpoint=False)
    side = np.minimum(s // 40, 3)
    t = s - 40 * side
    corners = np.array([[0, 0], [40, 0], [40, 40], [0, 40], [0, 0]], float)
    xy = corners[side.astype(int)] + (corners[side.astype(int) + 1] - corners[side.astype(int)]) * (t / 40)[:, None]
    xy = np.tile(xy, (loops, 1))
    return np.column_stack([xy, np.zeros(len(xy))])


def _data(seed=0, scenarios=2):
    """Descriptors = smooth function of position + scenario change + noise."""
    rng = np.random.default_rng(seed)
    d = Featurizer(SMALL).dimension
    pos = _route()
    freq = rng.uniform(0.05, 0.3, d)
    rows, labels, positions, sources, keyframes = [], [], [], [], []
    for k in range(scenarios):
        place = np.sin(pos[:, :1] * freq + pos[:, 1:2] * freq[::-1]) * 3
        shift = rng.standard_normal(d) * 0.5
        rows.append(place + shift + 0.3 * rng.standard_normal((len(pos), d)))
        labels.append(np.full(len(pos), k))
        positions.append(pos)
        sources.append(np.full(len(pos), k))
        keyframes.append(np.arange(len(pos)))
    cat = np.concatenate
    return (cat(rows).astype(np.float32), cat(labels), [f"s{k}" for k in range(scenarios)],
            cat(positions), cat(sources), cat(keyframes))


def test_place_folds_are_place_disjoint():
    X, labels, names, pos, src, kf = _data()
    folds = place_folds(pos, src, 3, radius=3.0)
    assert set(folds) == {0, 1, 2}
    # the second loop (revisits) and the other scenario land in the fold of the first visit
    np.testing.assert_array_equal(folds[:60], folds[60:120])
    np.testing.assert_array_equal(folds[:120], folds[120:])
    # contiguous stretches along the first loop
    assert np.all(np.diff(folds[:59]) >= 0)  # (the last one closes the loop: fold 0)


def test_place_folds_need_poses_and_enough_route():
    X, labels, names, pos, src, kf = _data()
    bad = pos.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="poses"):
        place_folds(bad, src, 3)
    with pytest.raises(ValueError, match="too short"):
        place_folds(np.zeros((10, 3)), np.zeros(10, int), 3)


@pytest.mark.parametrize("scenarios,protocol", [(2, "P2"), (1, "P1")])
def test_cross_validate_grid(tmp_path, scenarios, protocol):
    X, labels, names, pos, src, kf = _data(scenarios=scenarios)
    result = cross_validate(X, labels, names, pos, src, kf, SMALL, folds=2,
                            lambda1_grid=(0.0, 10.0), lambda2_grid=(0.0, 0.1), progress=False)
    assert result.protocol == protocol
    assert result.recall_at_1.shape == (2, 2)
    assert np.all((result.recall_at_1 >= 0) & (result.recall_at_1 <= 1))
    assert result.recall_at_1.max() > 0.5  # the places are recognisable
    a = result.lambda1_grid.index(result.best[0])
    b = result.lambda2_grid.index(result.best[1])
    assert result.recall_at_1[a, b] == result.recall_at_1.max()
    table = format_cv_table(result)
    assert "chosen" in table and "*" in table
    meta = result.metadata()
    assert meta["best_lambda1"] == result.best[0] and len(meta["recall_at_1"]) == 2
    png = plot_cv(result, tmp_path / "m.cv.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_recommended_threshold_is_a_max_f1_distance():
    X, labels, names, pos, src, kf = _data()
    model = fit_model(X, labels, names, SMALL, lambda1=1.0, lambda2=0.1).model
    info = recommend_threshold(model, X, labels, pos, src, kf, radius=3.0, exclude=50)
    assert info is not None and info["protocol"] == "P1"
    assert info["distance_threshold"] > 0 and 0 < info["max_f1"] <= 1
    no_poses = recommend_threshold(model, X, labels, np.full_like(pos, np.nan), src, kf)
    assert no_poses is None
