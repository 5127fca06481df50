from dataclasses import replace

import numpy as np

from vbrl_ros.detection.candidate_verification import query_verifier, verify_candidates, wants_wider_retry
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.registration import SEARCH_MARGIN_M
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.model.builtin import load_default_model
from vbrl_ros.model.model_file import UNCALIBRATED_DISTANCE_THRESHOLD


def detector(model, **settings):
    database = KeyframeDatabase(model.scorer(), model.identity())
    return LoopClosureDetector(model, database, DetectorSettings(verify=False, **settings))


def test_distance_threshold_is_the_settings_or_else_the_models_own():
    model = load_default_model()
    calibrated = model.metadata["distance_threshold"]
    assert detector(model).distance_threshold == calibrated
    assert detector(model, distance_threshold=0.25).distance_threshold == 0.25
    uncalibrated = replace(model, metadata={})
    assert detector(uncalibrated).distance_threshold == UNCALIBRATED_DISTANCE_THRESHOLD


def test_a_revisit_below_the_threshold_is_a_closure():
    model = load_default_model()
    found = detector(model, exclude_recent_s=0.0)
    points = np.random.default_rng(0).uniform(-30, 30, (20_000, 3)).astype(np.float32)
    points[:, 2] = np.abs(points[:, 2]) % 5 - 2
    assert found.process_keyframe(points, 0.0).closures == []
    again = found.process_keyframe(points, 1.0)
    assert [c.match_id for c in again.closures] == [0] and again.closures[0].distance == 0.0


def test_a_querys_verifier_searches_headings_only_as_far_as_a_closure_is_accepted():
    cloud = np.random.default_rng(1).uniform(-20, 20, (500, 3))
    for farthest in (3.0, 5.0, 12.0):
        verifier = query_verifier(cloud, DetectorSettings(max_closure_distance=farthest, verification_voxel=0.5))
        assert verifier.search_radius == farthest + SEARCH_MARGIN_M
        assert verifier.voxel == 0.5


# -- a degenerate registration retried with wider submaps ------------------------------------------

END_WALL_X = -7.5  # the corridor's end: the only structure that fixes a position along it


def corridor_scan(rng: np.random.Generator, x: float, reach: float = 5.0) -> np.ndarray:
    """A short-range scan from 1 m up at ``x`` in a 6 m wide, 5 m high corridor closed at END_WALL_X:
    the two walls, the floor and, within ``reach``, the end wall."""
    def plane(n, xs, ys, zs):
        return np.c_[rng.uniform(*xs, n), rng.uniform(*ys, n), rng.uniform(*zs, n)]
    world = np.vstack([plane(6000, (END_WALL_X, 60), (3, 3), (0, 5)), plane(6000, (END_WALL_X, 60), (-3, -3), (0, 5)),
                       plane(4000, (END_WALL_X, 60), (-3, 3), (0, 0)), plane(800, (END_WALL_X, END_WALL_X), (-3, 3), (0, 5))])
    near = world[np.abs(world[:, 0] - x) < reach]
    return (near - [x, 0.0, 1.0]).astype(np.float32)


def corridor_revisit(at: float = -1.0, **settings):
    """A corridor walked twice with odometry, keyframes 1.5 m apart; the second walk's keyframe at
    ``at`` m, verified against the first walk's there: ``(detector, retrieval of that pair, match id)``."""
    rng = np.random.default_rng(3)
    model = load_default_model()
    found = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()),
                                DetectorSettings(top_k=10, exclude_recent_s=30.0, **settings))

    def pose(x):
        T = np.eye(4)
        T[0, 3], T[2, 3] = x, 1.0
        return T

    first_walk = np.arange(-7.0, 21.0, 1.5)
    for i, x in enumerate(first_walk):
        found.retrieve(corridor_scan(rng, x), float(i), pose(x))
    for i, x in enumerate(np.arange(-7.0, at + 0.1, 1.5)):
        retrieval = found.retrieve(corridor_scan(rng, x), 1000.0 + i, pose(x))
    match = int(np.flatnonzero(first_walk == at)[0])
    k = [c.keyframe_id for c in retrieval.candidates].index(match)
    only = replace(retrieval, candidates=[retrieval.candidates[k]], candidate_clouds=[retrieval.candidate_clouds[k]],
                   candidate_frames=[retrieval.candidate_frames[k]])
    return found, only, match


def test_a_registration_that_slides_along_a_corridor_is_retried_with_wider_submaps():
    """The query's and the match's submaps (two neighbours) see only the walls, which fix nothing
    along the corridor; with four, both reach the end wall, and the registration holds."""
    found, retrieval, match = corridor_revisit()
    first = verify_candidates(retrieval, found.settings)
    assert first.closures == [] and first.rejections == {"degenerate": 1} and first.degenerate == [0]
    result = found.verified(retrieval, lambda r: verify_candidates(r, found.settings))
    assert [c.match_id for c in result.closures] == [match] and result.rejections == {}
    assert np.linalg.norm(result.closures[0].T_query_match[:3, 3]) < 0.5  # the same place: no slide
    assert "wider_retry" in result.timings_ms and result.degenerate == []


def test_the_wider_retry_reaches_the_structure_more_than_6_m_along():
    """At 2 m the first walk's keyframe has the end wall 9.5 m behind it: only neighbours up to
    7.5 m away see it, beyond the 6 m of ordinary submaps and of four neighbours, 1.5 m apart."""
    found, retrieval, match = corridor_revisit(at=2.0)
    assert verify_candidates(retrieval, found.settings).degenerate == [0]
    result = found.verified(retrieval, lambda r: verify_candidates(r, found.settings))
    assert [c.match_id for c in result.closures] == [match]
    assert np.linalg.norm(result.closures[0].T_query_match[:3, 3]) < 0.5


def test_without_submaps_nothing_is_retried():
    found, retrieval, _ = corridor_revisit(submap_keyframes=0)
    first = verify_candidates(retrieval, found.settings)
    assert first.rejections == {"degenerate": 1}
    assert not wants_wider_retry(first, found.settings) and found.widened(retrieval, first.degenerate) is None
    again = found.verified(retrieval, lambda r: verify_candidates(r, found.settings))
    assert again.rejections == first.rejections and "wider_retry" not in again.timings_ms


def test_a_wider_retry_adds_what_it_accepted_after_the_closures_already_found():
    from vbrl_ros.detection.candidate_verification import KeyframeResult, LoopClosure, with_wider_retry

    def closure(match_id):
        return LoopClosure(query_id=9, match_id=match_id, query_stamp=9.0, match_stamp=float(match_id),
                           query_session="", match_session="", distance=0.1)

    first = KeyframeResult(9, [closure(1)], 5, {"verify": 30.0}, {"degenerate": 3, "low fitness": 1}, [0, 2, 3])
    retried = KeyframeResult(9, [closure(2), closure(3)], 5, {"verify": 20.0}, {"degenerate": 1}, [])
    merged = with_wider_retry(first, retried, DetectorSettings(max_closures=2))
    assert [c.match_id for c in merged.closures] == [1, 2]  # max_closures
    assert merged.rejections == {"degenerate": 2, "low fitness": 1} and merged.degenerate == []
    assert merged.timings_ms == {"verify": 30.0, "wider_retry": 20.0}
    assert not wants_wider_retry(merged, DetectorSettings(max_closures=2))


# -- a keyframe described with its trail -----------------------------------------------------------

def sparse_walk(tmp_path, count: int):
    """(the simulated run, a KITTI-style folder of its first ``count`` scans): a 16-beam sensor,
    sparse enough to be described with its trail, one keyframe a metre."""
    import pytest

    from vbrl_ros.datasets.kitti_style import write_kitti_style

    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=3)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0)),
                           sim.LidarConfig(beams=16, columns=512), "summer_clear", seed=1)
    return run, write_kitti_style(tmp_path / "run", [run.scan(k).points for k in range(count)],
                                  run.poses[:count], run.stamps[:count])


def test_the_detector_describes_keyframes_with_their_trail_as_the_evaluation_does(tmp_path):
    """With odometry the node merges the last metres of keyframes into each before describing it,
    exactly as ``vbrl eval`` (and training) do with a recording's poses; without poses, alone."""
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source

    count = 6
    run, folder = sparse_walk(tmp_path, count)
    builtin = load_default_model()
    model = replace(builtin, config=replace(builtin.config, features=replace(builtin.config.features,
                                                                              trail_m=3.0, trail_ahead_m=0.0)))
    source = describe_source(folder, model.config, ScanContextConfig(), workers=1, progress=False)
    with_odometry, without = detector(model), detector(model)
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)  # as written, to the digit
    for k in range(count):
        points = np.fromfile(folder / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        with_odometry.process_keyframe(points, float(run.stamps[k]), pose=np.vstack([poses[k], [0, 0, 0, 1]]))
        without.process_keyframe(points, float(run.stamps[k]))
    stored = np.stack([with_odometry.database.descriptor(k) for k in range(count)])
    alone = np.stack([without.database.descriptor(k) for k in range(count)])
    expected = model.scorer().compact(model.standardize(source.vbrl))
    np.testing.assert_allclose(stored, expected, atol=1e-5)
    np.testing.assert_array_equal(stored[0], alone[0])  # the first keyframe has no trail yet
    assert all(np.abs(stored[k] - alone[k]).max() > 1e-3 for k in range(1, count))


def test_a_keyframe_waits_for_the_metres_after_it_and_is_described_as_the_evaluation_does(tmp_path):
    """With ``trail_ahead_m`` a keyframe is described once odometry has carried the sensor that far
    past it, with the keyframes of those metres merged in too, exactly as ``vbrl eval`` and training
    describe it; the rest, when the input stops, with what came."""
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source

    count = 8
    run, folder = sparse_walk(tmp_path, count)
    builtin = load_default_model()
    model = replace(builtin, config=replace(builtin.config, features=replace(
        builtin.config.features, trail_m=3.0, trail_ahead_m=2.5)))
    source = describe_source(folder, model.config, ScanContextConfig(), workers=1, progress=False)
    node, at_once, reused = detector(model), detector(model), detector(model)
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    due, buffer = [], np.eye(4)
    for k in range(count):
        points = np.fromfile(folder / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        pose = np.vstack([poses[k], [0, 0, 0, 1]])
        now = node.keyframes_due(points, float(run.stamps[k]), pose, tag=k)
        due.append([keyframe.tag for keyframe in now])
        for keyframe in now:
            node.retrieve_keyframe(keyframe)
        at_once.process_keyframe(points, float(run.stamps[k]), pose=pose)
        buffer[:] = pose  # a caller that moves one pose array along, and reuses its points' buffer
        for keyframe in reused.keyframes_due(points, float(run.stamps[k]), buffer):
            reused.retrieve_keyframe(keyframe)
        points[:] = np.nan
    assert due[:4] == [[], [], [], [0]] and sum(due, []) == list(range(count - 3))  # 1 m apart: 3 m on
    assert len(node.trail_ahead) == 3
    for waiting in (node, reused):
        for keyframe in waiting.keyframes_waiting():
            waiting.retrieve_keyframe(keyframe)
    assert len(node.trail_ahead) == 0 and len(node.database) == count
    np.testing.assert_array_equal(reused.database.index.descriptors(), node.database.index.descriptors())
    stored = np.stack([node.database.descriptor(k) for k in range(count)])
    np.testing.assert_allclose(stored, model.scorer().compact(model.standardize(source.vbrl)), atol=1e-5)
    # process_keyframe describes a keyframe when it comes: without the metres after it
    alone = np.stack([at_once.database.descriptor(k) for k in range(count)])
    assert all(np.abs(stored[k] - alone[k]).max() > 1e-3 for k in range(count - 1))
    np.testing.assert_array_equal(stored[-1], alone[-1])  # nothing came after the last


def test_a_forward_looking_keyframe_is_described_with_its_forward_trail_as_the_evaluation_does(tmp_path):
    """The node's forward trail reaches back less than half ``exclude_recent_s``, the evaluation's
    less than half its exclusion in scans (as far as a submap reaches): with a keyframe a second,
    the two describe alike, and neither holds a keyframe a candidate or its submap holds."""
    import pytest

    from vbrl_ros.datasets.kitti_style import write_kitti_style
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source

    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=3)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0)),
                           sim.LidarConfig(beams=16, columns=512, vertical_fov_deg=(-30.0, 30.0),
                                           blocked_azimuth_deg=(35.0, -35.0)), "summer_clear", seed=1)
    count, exclude = 28, 24
    stamps = np.arange(count, dtype=float)  # one keyframe a second: seconds and scans agree
    folder = write_kitti_style(tmp_path / "run", [run.scan(k).points for k in range(count)],
                               run.poses[:count], stamps)
    model = load_default_model()
    assert model.config.features.forward_trail_m > 0
    source = describe_source(folder, model.config, ScanContextConfig(), workers=1, progress=False,
                             exclude=exclude, verification_voxel=DetectorSettings().verification_voxel)
    longer = describe_source(folder, model.config, ScanContextConfig(), workers=1, progress=False,
                             exclude=2 * exclude)
    settings = DetectorSettings(exclude_recent_s=float(exclude))
    node = LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()), settings)
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    for k in range(count):
        points = np.fromfile(folder / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        node.process_keyframe(points, stamps[k], pose=np.vstack([poses[k], [0, 0, 0, 1]]))
    stored = np.stack([node.database.descriptor(k) for k in range(count)])
    np.testing.assert_allclose(stored, model.scorer().compact(model.standardize(source.vbrl)), atol=1e-5)
    # the bound decides: reaching back further describes the last keyframes otherwise
    assert all(np.abs(source.vbrl[k] - longer.vbrl[k]).max() > 1e-3 for k in range(exclude // 2 + 1, count))
    # verified with its forward trail, as the evaluation verifies it: what lay behind it is there
    last = node.database.cloud(count - 1)
    np.testing.assert_allclose(last, source.clouds.clouds[count - 1], atol=1e-4)
    frame = source.clouds.frames[count - 1]
    behind = (last - frame[:3, 3]) @ frame[:3, :3]  # back in the sensor's axes
    assert (behind[:, 0] < -1.0).sum() > 50  # the scan alone sees only ahead


def test_with_odometry_earlier_keyframes_are_matched_by_place():
    """The node hands the database its odometry position: the sequence terms are then the places'
    (index.sequence_matching), so they differ from matching by id once earlier keyframes exist."""
    builtin = load_default_model()  # without a trail: the keyframes are described alike either way
    model = replace(builtin, config=replace(builtin.config, features=replace(builtin.config.features, trail_m=0.0,
                                                                              trail_ahead_m=0.0)))
    rng = np.random.default_rng(4)
    clouds = [rng.uniform(-30, 30, (20_000, 3)).astype(np.float32) for _ in range(7)]
    for cloud in clouds:
        cloud[:, 2] = np.abs(cloud[:, 2]) % 5 - 2
    # four keyframes along x, then three on a street along y towards the fourth, then the fourth again
    path = [(0, 0), (2, 0), (4, 0), (6, 0), (6, 9), (6, 6), (6, 3), (6, 0)]
    order = [0, 1, 2, 3, 4, 5, 6, 3]
    distances = {}
    for with_odometry in (True, False):
        found = detector(model, exclude_recent_s=0.0, sequence_length=4, distance_threshold=1e9)
        for stamp, ((x, y), k) in enumerate(zip(path, order)):
            pose = np.eye(4)
            pose[:2, 3] = x, y
            result = found.process_keyframe(clouds[k], float(stamp), pose=pose if with_odometry else None)
        distances[with_odometry] = {c.match_id: c.distance for c in result.closures}
    assert 3 in distances[True] and 3 in distances[False]
    assert distances[True][3] != distances[False][3]


def test_a_keyframe_whose_wedge_its_trail_fills_is_stored_all_round_as_the_evaluation_describes_it(tmp_path):
    """A mast hides 90° behind the sensor; driving on, the keyframes behind saw into the wedge, and
    the node describes a keyframe all round as well, exactly as ``vbrl eval`` does."""
    import pytest

    from vbrl_ros.datasets.kitti_style import write_kitti_style
    from vbrl_ros.evaluation.baselines.scan_context import ScanContextConfig
    from vbrl_ros.evaluation.methods import describe_source

    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=3)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0)),
                           sim.LidarConfig(beams=16, columns=512, blocked_azimuth_deg=(135.0, -135.0)),
                           "summer_clear", seed=1)
    count, exclude = 24, 24
    stamps = np.arange(count, dtype=float)
    folder = write_kitti_style(tmp_path / "run", [run.scan(k).points for k in range(count)],
                               run.poses[:count], stamps)
    model = load_default_model()
    assert model.config.features.fill_blind_wedges
    source = describe_source(folder, model.config, ScanContextConfig(), workers=1, progress=False, exclude=exclude)
    node, hidden_only = (LoopClosureDetector(model, KeyframeDatabase(model.scorer(), model.identity()),
                                             DetectorSettings(verify=False, exclude_recent_s=float(exclude),
                                                              fill_blind_wedges=fill)) for fill in (True, False))
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    for k in range(count):
        points = np.fromfile(folder / "velodyne" / f"{k:06d}.bin", np.float32).reshape(-1, 4)
        for detector_ in (node, hidden_only):  # as the node: each keyframe once the sensor has passed it
            for keyframe in detector_.keyframes_due(points, stamps[k], np.vstack([poses[k], [0, 0, 0, 1]])):
                detector_.retrieve_keyframe(keyframe)
    for detector_ in (node, hidden_only):
        for keyframe in detector_.keyframes_waiting():
            detector_.retrieve_keyframe(keyframe)
    assert len(hidden_only.database.all_round) == 0  # the node's fill_blind_wedges off
    np.testing.assert_array_equal(hidden_only.database.index.descriptors(), node.database.index.descriptors())
    assert source.has_all_round is not None and source.has_all_round.sum() >= count // 2
    assert not source.has_all_round[0]  # nothing behind the first keyframe to fill its wedge
    np.testing.assert_array_equal(node.database.all_round.rows, np.flatnonzero(source.has_all_round))
    expected = model.scorer().compact(model.standardize(source.all_round[source.has_all_round, 0]))
    np.testing.assert_allclose(node.database.all_round.index.descriptors(), expected, atol=1e-5)
