"""How much room the keyframe index's first stage leaves before it misses matches at scale.

The index keeps a fixed number of candidates from its 4-bit key scan (512
Cartesian / 1024 polar by default, :func:`~vbrl_ros.index.parameters.default_parameters`),
so the larger the map, the smaller the share of it that reaches the exact
re-rank: 1 % at 100k polar keyframes, 0.5 % Cartesian. An evaluation set is
small enough that the index re-ranks most of it, so agreeing with brute force
there says little about 100k. This measures the margin instead: where the
brute-force top-1 ranks under the candidate key, as a share of the database
the query saw, for the queries whose brute-force top-1 is a true match (the
others have nothing to lose). A match ranked within the first 1 % would still
reach the re-rank at 100k keyframes if the rest of that map ranked like this
one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vbrl_ros.index.keyframe_index import KeyframeIndex

SHARES = (0.005, 0.01, 0.05)  # key-ranking prefixes reported (share of the database)


def key_rank_shares(index: KeyframeIndex, queries: np.ndarray, templates: np.ndarray,
                    targets: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Share of ``templates[:limit]`` whose candidate key is nearer the query's than its target's.

    ``queries`` / ``templates``: compact descriptors for ``index``; ``targets``
    (n_q,) the template each query should find (e.g. the brute-force top-1),
    -1 to skip (NaN out). Ties count half, so equal keys do not flatter.
    """
    key_q = index.store.keys(queries).astype(np.int16)
    key_t = index.store.keys(templates).astype(np.int16)
    out = np.full(len(queries), np.nan)
    for q, (target, limit) in enumerate(zip(targets, limits)):
        if target < 0 or limit <= 0:
            continue
        distance = np.abs(key_t[:limit] - key_q[q]).sum(axis=1, dtype=np.int32)
        own = distance[target]
        out[q] = (np.count_nonzero(distance < own) + 0.5 * (np.count_nonzero(distance == own) - 1)) / limit
    return out


def summary(shares: np.ndarray) -> dict[str, Any]:
    """JSON-ready: how many queries have their target within each prefix of :data:`SHARES`."""
    shares = shares[np.isfinite(shares)]
    return {"queries": int(len(shares)),
            "within": {f"{s:g}": int(np.count_nonzero(shares < s)) for s in SHARES},
            "median_share": float(np.median(shares)) if len(shares) else None}


def describe(result: dict[str, Any]) -> str:
    """One line for the ``vbrl eval`` output."""
    n, within = result["queries"], result["within"]
    parts = ", ".join(f"{within[f'{s:g}']} in the first {100 * s:g} %" for s in SHARES)
    return (f"candidate key headroom: of {n} correct brute-force top-1s, {parts} of the key "
            "ranking (stage 1 keeps ~1 % of a 100k polar map, ~0.5 % Cartesian)")
