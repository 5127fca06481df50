from dataclasses import replace

import numpy as np

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector, query_verifier
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
