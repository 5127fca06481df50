import numpy as np
import pytest

from vbrl_ros.features.featurizer import FeatureLayout
from vbrl_ros.model.scoring import WeightedL1Scorer, importance_weights, row_weights

LAYOUT = FeatureLayout(n_voxels=3, features_per_modality=(2, 1))  # d = 3*2 + 3*1 = 9


def test_importances_are_normalised_group_norms():
    W = np.zeros((LAYOUT.dimension, 2))
    W[LAYOUT.modality_of_row == 0] = 1.0  # 6 rows of modality 0, two columns: norm sqrt(12)
    W[(LAYOUT.modality_of_row == 1) & (LAYOUT.voxel_of_row == 2)] = [3.0, 4.0]  # norm 5
    w_modality, w_voxel = importance_weights(W, LAYOUT)
    np.testing.assert_allclose(w_modality, np.array([12**0.5, 5.0]) / (12**0.5 + 5.0))
    voxel_norms = np.array([2.0, 2.0, np.sqrt(4.0 + 25.0)])  # voxel j: 2 rows of ones (x2 cols) + ...
    np.testing.assert_allclose(w_voxel, voxel_norms / voxel_norms.sum())
    assert w_modality.sum() == pytest.approx(1) and w_voxel.sum() == pytest.approx(1)


def test_zero_W_weighs_everything_equally():
    w_modality, w_voxel = importance_weights(np.zeros((LAYOUT.dimension, 1)), LAYOUT)
    assert np.allclose(w_modality, 0.5) and np.allclose(w_voxel, 1 / 3)


def test_distance_is_eq4_and_lower_means_more_similar():
    rng = np.random.default_rng(0)
    w_modality = np.array([0.7, 0.3])
    w_voxel = np.array([0.5, 0.5, 0.0])  # voxel 2 switched off by the sparsity norm
    weights = row_weights(w_modality, w_voxel, LAYOUT)
    scorer = WeightedL1Scorer(weights)
    assert len(scorer.active_rows) == 6  # voxel 2's rows dropped
    query = rng.normal(size=LAYOUT.dimension)
    templates = rng.normal(size=(5, LAYOUT.dimension))
    templates[3] = query
    templates[4] = query
    templates[4, LAYOUT.voxel_of_row == 2] += 100.0  # differs only where weight is 0
    expected = np.array(
        [
            sum(
                w_modality[i] * w_voxel[j]
                * np.abs(query - t)[(LAYOUT.modality_of_row == i) & (LAYOUT.voxel_of_row == j)].sum()
                for i in range(2)
                for j in range(3)
            )
            for t in templates
        ]
    )
    got = scorer.distances(query, templates)
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert got[3] == 0 and got[4] == 0
    assert got.argmin() in (3, 4)


def test_scorer_rejects_bad_weights_and_lengths():
    with pytest.raises(ValueError):
        WeightedL1Scorer(np.array([1.0, np.nan]))
    with pytest.raises(ValueError):
        WeightedL1Scorer(np.array([1.0, -1.0]))
    with pytest.raises(ValueError, match="descriptor length"):
        WeightedL1Scorer(np.ones(4)).distances(np.ones(3), np.ones((2, 3)))


# -- polar grid: sector shifts -------------------------------------------------------


def polar_case(sectors=6, columns=7, seed=0, off=(2,)):
    """A shuffled sector-major layout with tied column weights (some columns switched off)."""
    rng = np.random.default_rng(seed)
    sector_rows = rng.permutation(sectors * columns).reshape(sectors, columns)
    column_weights = rng.uniform(0.1, 1.0, columns)
    column_weights[list(off)] = 0.0
    weights = np.empty(sectors * columns)
    weights[sector_rows] = column_weights
    return sector_rows, column_weights, weights


def rotate(descriptor, sector_rows, k):
    """The descriptor of the scan rotated counter-clockwise by k sectors (the layout contract)."""
    rotated = np.empty_like(descriptor)
    sectors = len(sector_rows)
    for s in range(sectors):
        rotated[sector_rows[(s + k) % sectors]] = descriptor[sector_rows[s]]
    return rotated


def test_polar_active_rows_are_sector_major_and_pruned_per_column():
    sector_rows, column_weights, weights = polar_case()
    scorer = WeightedL1Scorer(weights, sector_rows=sector_rows)
    assert scorer.sectors == 6 and scorer.sector_angle == pytest.approx(2 * np.pi / 6)
    active_columns = np.flatnonzero(column_weights > 0)
    np.testing.assert_array_equal(scorer.active_rows, sector_rows[:, active_columns].ravel())
    np.testing.assert_allclose(scorer.column_weights, column_weights[active_columns], rtol=1e-6)
    pruned = WeightedL1Scorer(weights, prune=0.5, sector_rows=sector_rows)
    kept = np.flatnonzero(column_weights > 0.5 * column_weights.max())
    np.testing.assert_array_equal(pruned.active_rows, sector_rows[:, kept].ravel())
    cartesian = WeightedL1Scorer(weights)
    assert cartesian.sectors == 1 and np.all(np.diff(cartesian.active_rows) > 0)


def test_polar_scorer_rejects_untied_weights_and_bad_layouts():
    sector_rows, _, weights = polar_case()
    untied = weights.copy()
    untied[sector_rows[3, 4]] *= 1.5
    with pytest.raises(ValueError, match="column 4 differ across sectors"):
        WeightedL1Scorer(untied, sector_rows=sector_rows)
    with pytest.raises(ValueError, match="every one of"):
        WeightedL1Scorer(weights, sector_rows=sector_rows[:, :-1])
    duplicated = sector_rows.copy()
    duplicated[0, 0] = duplicated[0, 1]
    with pytest.raises(ValueError, match="every one of"):
        WeightedL1Scorer(weights, sector_rows=duplicated)


def test_shift_minimised_distance_equals_a_naive_loop():
    sector_rows, column_weights, weights = polar_case(sectors=5, columns=9, seed=1, off=(0, 4))
    scorer = WeightedL1Scorer(weights, sector_rows=sector_rows)
    rng = np.random.default_rng(2)
    query, templates = rng.normal(size=45), rng.normal(size=(30, 45))
    q = query[sector_rows]  # (S, R) full, sector-major
    expected, expected_shift = [], []
    for t in templates[:, sector_rows]:
        per_shift = [sum(column_weights @ np.abs(q[(s + k) % 5] - t[s]) for s in range(5))
                     for k in range(5)]
        expected.append(min(per_shift))
        expected_shift.append(int(np.argmin(per_shift)))
    got, yaws = scorer.distances_and_yaws_compact(scorer.compact(query), scorer.compact(templates))
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    np.testing.assert_allclose(scorer.distances(query, templates), expected, rtol=1e-5)
    signed = np.where(np.array(expected_shift) > 2, np.array(expected_shift) - 5, expected_shift)
    np.testing.assert_allclose(yaws, signed * 2 * np.pi / 5)
    # one sector is the Cartesian distance
    single = WeightedL1Scorer(weights, sector_rows=np.arange(45)[None])
    plain = WeightedL1Scorer(weights)
    np.testing.assert_allclose(single.distances(query, templates),
                               plain.distances(query, templates), rtol=1e-5)
    assert np.all(single.distances_and_yaws_compact(single.compact(query),
                                                    single.compact(templates))[1] == 0.0)


@pytest.mark.parametrize("k", [0, 1, 2, 3, 4, 5, 6, 7])
def test_rotated_scan_gives_distance_zero_and_yaw_of_the_rotation(k):
    sector_rows, _, weights = polar_case(sectors=8, columns=5, seed=3)
    scorer = WeightedL1Scorer(weights, sector_rows=sector_rows)
    rng = np.random.default_rng(k)
    template = rng.normal(size=40)
    others = rng.normal(size=(3, 40))
    query = rotate(template, sector_rows, k)  # the query scan = template scan rotated by +k sectors
    distances, yaws = scorer.distances_and_yaws_compact(
        scorer.compact(query), scorer.compact(np.vstack([others, template])))
    assert distances[-1] == 0.0 and distances[:-1].min() > 0
    expected = k * 2 * np.pi / 8 if k <= 4 else (k - 8) * 2 * np.pi / 8  # wrapped to (-pi, pi]
    assert yaws[-1] == pytest.approx(expected)
    assert -np.pi < yaws[-1] <= np.pi


def test_parabola_refines_the_yaw_of_a_rotation_between_sectors():
    sectors, columns = 24, 40
    rng = np.random.default_rng(0)
    amplitude, phase = rng.normal(size=(columns, 3)), rng.uniform(0, 2 * np.pi, (columns, 3))
    angle = 2 * np.pi / sectors
    centres = (np.arange(sectors) + 0.5) * angle

    def describe(rotation):  # smooth angular profiles, sampled at the sector centres
        theta = centres[:, None, None] - rotation
        return (amplitude * np.cos(np.arange(1, 4) * theta + phase)).sum(-1).ravel()

    sector_rows = np.arange(sectors * columns).reshape(sectors, columns)
    scorer = WeightedL1Scorer(np.tile(rng.uniform(0.5, 1.0, columns), sectors),
                              sector_rows=sector_rows)
    template = describe(0.0)[None]
    for shift, fraction in ((0, 0.3), (3, -0.4), (5, 0.25), (-7, 0.1), (11, 0.45)):
        truth = (shift + fraction) * angle
        _, coarse = scorer.distances_and_yaws_compact(describe(truth), template)
        _, fine = scorer.distances_and_yaws_compact(describe(truth), template, refine=True)
        assert abs(coarse[0] - truth) <= 0.5 * angle + 1e-9
        assert abs(fine[0] - truth) < 0.6 * abs(coarse[0] - truth)
        assert abs(fine[0] - truth) < 0.25 * angle
    _, exact = scorer.distances_and_yaws_compact(describe(2 * angle), template, refine=True)
    assert exact[0] == pytest.approx(2 * angle, abs=1e-6)  # on a sector: stays there
