"""Candidate-key headroom: where a target ranks under the index's int8 key."""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation import headroom
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters


def test_key_rank_shares_rank_targets_among_the_database_prefix():
    rng = np.random.default_rng(0)
    templates = rng.standard_normal((200, 64)).astype(np.float32)
    index = KeyframeIndex(np.full(64, 1 / 64, np.float32), IndexParameters(key_dim=32))
    queries = templates[[10, 20, 30, 40]] + 0.01
    keys = index.store.keys(templates).astype(np.int32)
    farthest = int(np.abs(keys[:150] - index.store.keys(queries[2]).astype(np.int32)).sum(1).argmax())
    targets = np.array([10, 20, farthest, -1])
    limits = np.array([200, 100, 150, 200])
    shares = headroom.key_rank_shares(index, queries, templates, targets, limits)
    assert shares[0] == 0.0 and shares[1] == 0.0  # itself: nothing nearer
    assert shares[2] > 0.9  # the farthest of the first 150
    assert np.isnan(shares[3])  # skipped
    result = headroom.summary(shares)
    assert result["queries"] == 3 and result["within"] == {"0.005": 2, "0.01": 2, "0.05": 2}
    assert "2 in the first 1 %" in headroom.describe(result)
