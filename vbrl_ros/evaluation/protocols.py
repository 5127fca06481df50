"""Which keyframes query which: the protocols of docs/design.md on labelled keyframe rows.

P2 pairs scenarios (every query of one against the whole database of
another); P1 stays inside one source, a query seeing only the keyframes
recorded at least ``exclude`` scans before it.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np


def protocol_pairs(labels: np.ndarray, keyframe_index: np.ndarray, source_of_row: np.ndarray,
                   exclude: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """(query rows, database rows, limits): P2 for each ordered scenario pair, else P1 per source."""
    scenarios = np.unique(labels)
    if len(scenarios) >= 2:
        for a in scenarios:
            for b in scenarios:
                if a != b:
                    yield np.flatnonzero(labels == b), np.flatnonzero(labels == a), None
        return
    for s in np.unique(source_of_row):
        rows = np.flatnonzero(source_of_row == s)
        rows = rows[np.argsort(keyframe_index[rows], kind="stable")]
        ki = keyframe_index[rows]
        # query i sees the keyframes of its source recorded >= exclude scans earlier
        limits = np.searchsorted(ki, ki - exclude, side="right")
        yield rows, rows, limits
