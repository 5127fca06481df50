"""Translation search: a revisit from the other lane, driven the other way, still finds its keyframe.

The database holds the recognition descriptor (ground frame, height modality, polar grid) of
simulated scans under a uniform model; a query is one of those scans moved to the side and
turned by 180 degrees, as the same place seen from the opposite lane.
"""

import math

import numpy as np
import pytest

from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.translation_search import search_views, view_offsets
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.training.presets import RECOGNITION_TRANSLATION_SEARCH_M, recognition_config

sim = pytest.importorskip("vbrl_ros.simulator")

STEP = RECOGNITION_TRANSLATION_SEARCH_M
KEYFRAMES = range(0, 181, 2)  # every other scan of a 2 m-spaced loop: 4 m apart


def test_no_step_is_the_sensor_alone():
    np.testing.assert_array_equal(view_offsets(0), np.zeros((1, 2)))


def test_the_views_are_the_sensor_a_grid_around_it_and_the_opposite_lanes():
    offsets = view_offsets(1.5)
    assert offsets.shape == (11, 2)
    np.testing.assert_array_equal(offsets[0], (0.0, 0.0))
    assert len({tuple(o) for o in offsets}) == 11
    expected = {(x, y) for x in (-1.5, 0.0, 1.5) for y in (-1.5, 0.0, 1.5)} | {(0.0, 3.0), (0.0, -3.0)}
    assert {tuple(o) for o in offsets} == expected


@pytest.mark.parametrize("step", [-1.0, float("nan"), float("inf")])
def test_a_bad_step_is_refused(step):
    with pytest.raises(ValueError, match="translation search step"):
        view_offsets(step)


@pytest.fixture(scope="module")
def setting():
    """(run, describe, index): a uniform recognition-descriptor model's database of a loop."""
    config = recognition_config()
    d = Featurizer(config).dimension
    model = VBRLModel(config, np.ones((d, 1)), np.zeros(d), np.ones(d), 0.0, 0.0, ["all"])
    scorer, featurizer = model.scorer(), model.featurizer()
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0))
    run = sim.simulate_run(town, route, sim.LidarConfig(beams=32, columns=512), "summer_clear", seed=1)

    def describe(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        frame = featurizer.frame(points)
        return scorer.compact(model.standardize(featurizer.describe_views(frame.apply(points), offsets)))

    index = KeyframeIndex(scorer.active_weights, IndexParameters(sectors=scorer.sectors))
    index.add_batch(np.concatenate([describe(run.scan(k).points, np.zeros((1, 2))) for k in KEYFRAMES]))
    return run, describe, index


def turned(yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def other_lane(points: np.ndarray, shift: tuple[float, float], yaw_deg: float = 180.0) -> np.ndarray:
    """The scan moved by ``shift`` and turned by ``yaw_deg`` about z: the original sensor then
    stands at ``turned(yaw_deg) @ shift`` in the new scan's frame."""
    out = np.asarray(points, dtype=np.float64).copy()
    out[:, :3] = (out[:, :3] + [shift[0], shift[1], 0.0]) @ turned(yaw_deg).T
    return out


def wrapped_deg(angle: float) -> float:
    return math.degrees(math.atan2(math.sin(angle), math.cos(angle)))


@pytest.mark.parametrize("row", [5, 25, 40, 65])
@pytest.mark.parametrize("shift, yaw, gain", [((0.0, -3.0), 180.0, 0.5), ((0.4, -2.6), 180.0, 0.5),
                                              ((0.4, -2.6), 186.0, 0.9)])
def test_a_revisit_from_the_other_lane_finds_its_keyframe_with_its_offset_and_yaw(setting, row, shift, yaw, gain):
    """The keyframe comes first, found under a view within a step of where its sensor stands
    in the query, at its yaw (to a sector), at the smallest distance any view gives it (over
    every sector shift), and closer than without views (by ``gain``: half way between two
    sectors the turn costs as much as the lane)."""
    run, describe, index = setting
    offsets = view_offsets(STEP)
    views = describe(other_lane(run.scan(KEYFRAMES[row]).points, shift, yaw), offsets)
    found = search_views(index, views, offsets, top_k=5)
    assert found.indices[0] == row
    where = turned(yaw)[:2, :2] @ np.asarray(shift)  # the keyframe's sensor in the query frame
    assert np.linalg.norm(found.offsets[0] - where) <= STEP, (found.offsets[0], where)
    assert abs(wrapped_deg(found.yaws[0] - math.radians(yaw))) < 13.0, math.degrees(found.yaws[0])
    assert np.all(np.diff(found.distances) >= 0)
    only = np.arange(len(index)) == row
    per_view = [index.search_with_yaw(v, 1, only, exact=True).distances[0] for v in views]
    assert found.distances[0] == pytest.approx(min(per_view), rel=1e-6)
    # without views: the same keyframe, at its best sector shift, is further away
    assert found.distances[0] < gain * per_view[0], (found.distances[0], per_view[0])


def test_without_views_the_revisit_is_not_always_first(setting):
    """What the search is for: from the other lane, the unshifted query ranks other places first."""
    run, describe, index = setting
    offsets = view_offsets(STEP)
    missed = 0
    for row in range(0, len(KEYFRAMES), 6):
        views = describe(other_lane(run.scan(KEYFRAMES[row]).points, (0.4, -2.6)), offsets)
        missed += index.search_with_yaw(views[0], 1).indices[0] != row
        assert search_views(index, views, offsets, top_k=1).indices[0] == row
    assert missed >= 2


@pytest.mark.parametrize("row", [5, 40])
def test_brute_force_agrees_with_the_index(setting, row):
    run, describe, index = setting
    offsets = view_offsets(STEP)
    views = describe(other_lane(run.scan(KEYFRAMES[row]).points, (0.4, -2.6)), offsets)
    staged = search_views(index, views, offsets, top_k=5)
    exact = search_views(index, views, offsets, top_k=5, exact=True)
    np.testing.assert_array_equal(staged.indices, exact.indices)
    np.testing.assert_allclose(staged.distances, exact.distances, rtol=1e-6)
    np.testing.assert_array_equal(staged.offsets, exact.offsets)
    np.testing.assert_array_equal(staged.shifts, exact.shifts)


def test_allowed_masks_and_one_view(setting):
    """A masked keyframe is never returned; a single view is the plain search with zero offsets."""
    run, describe, index = setting
    offsets = view_offsets(STEP)
    views = describe(other_lane(run.scan(KEYFRAMES[25]).points, (0.0, -3.0)), offsets)
    allowed = np.ones(len(index), bool)
    allowed[25] = False
    assert 25 not in search_views(index, views, offsets, top_k=10, allowed=allowed).indices
    single = search_views(index, views[:1], offsets[:1], top_k=5)
    plain = index.search_with_yaw(views[0], 5)
    np.testing.assert_array_equal(single.indices, plain.indices)
    np.testing.assert_array_equal(single.distances, plain.distances)
    np.testing.assert_array_equal(single.offsets, np.zeros((5, 2)))
    empty = search_views(index.empty_like(), views, offsets, top_k=5)
    assert len(empty.indices) == 0 and empty.offsets.shape == (0, 2)


def test_views_and_offsets_must_pair_up(setting):
    _, _, index = setting
    with pytest.raises(ValueError, match="views for"):
        search_views(index, np.zeros((3, index.dimension), np.float32), view_offsets(STEP), top_k=1)
