"""Eq. 3 on revisit pairs: weights learned for recognising places, not for telling sessions apart.

With Y labelling each scan's scenario, the sparsity norms pick exactly what changes between
sessions, and Eq. 4 then weighs it most. Here the rows of X are scan *pairs*: the
feature-wise absolute difference of two scans (the query turned by its best sector shift),
and Y says same place or different place. The same solver and the same two group norms then
keep the voxels and modalities whose differences tell a revisit from another place, and
their group norms are the importances Eq. 4 weighs with (the paper's Fig. 4 outputs still).

Pairs come from keyframes of one source (their poses share a frame): every pair within
``same_m`` metres and at least ``min_gap`` keyframes apart is a revisit; for each keyframe,
its nearest other places (more than ``different_m`` away) under unweighted Eq. 4 are the
hard negatives, plus as many random far ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from vbrl_ros.features.featurizer import FeatureLayout
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.model.distance_kernels import min_over_shifts

SAME_PLACE_M = 3.0
DIFFERENT_PLACE_M = 20.0
MIN_GAP = 10  # keyframes: neighbours on the same pass are not revisits
MAX_PAIRS_PER_SOURCE = 4000  # of each kind; enough for d in the thousands, bounded memory
HARD_NEGATIVES = 2  # nearest far places per keyframe


@dataclass(frozen=True)
class PairTargets:
    """X (pairs, d) feature-wise |z_a - shifted z_b| of standardised descriptors; Y (pairs, 2)
    one-hot (same place, different place)."""

    X: np.ndarray
    Y: np.ndarray
    n_same: int
    n_different: int


def pair_targets(standardised: np.ndarray, positions: np.ndarray, source_of_row: np.ndarray,
                 layout: FeatureLayout, *, seed: int = 0) -> PairTargets:
    """Revisit and non-revisit pairs of the training keyframes (see the module docstring)."""
    rng = np.random.default_rng(seed)
    Z = np.asarray(standardised, dtype=np.float32)
    rows = layout.sector_rows  # (S, R): sector-major view of a descriptor
    compact = np.ascontiguousarray(Z[:, rows.ravel()])  # what an index stores, unweighted
    same, different = [], []
    for source in np.unique(source_of_row):
        members = np.flatnonzero((source_of_row == source) & np.isfinite(positions).all(axis=1))
        if len(members) < 2:
            continue
        s, d = _source_pairs(compact[members], positions[members], layout.sectors, rng)
        same.append(members[s]), different.append(members[d])
    same_pairs = np.concatenate(same) if same else np.zeros((0, 2), np.int64)
    different_pairs = np.concatenate(different) if different else np.zeros((0, 2), np.int64)
    if len(same_pairs) == 0 or len(different_pairs) == 0:
        raise ValueError("--targets pairs needs revisits: keyframes within "
                         f"{SAME_PLACE_M:g} m of each other at least {MIN_GAP} keyframes apart, "
                         f"and places more than {DIFFERENT_PLACE_M:g} m apart (check --poses)")
    pairs = np.concatenate([same_pairs, different_pairs])
    X = np.empty((len(pairs), Z.shape[1]), np.float64)
    shifts = _best_shifts(compact, pairs, layout.sectors)
    sm = compact.reshape(len(Z), *rows.shape)
    for p, ((a, b), k) in enumerate(zip(pairs, shifts)):
        X[p, rows.ravel()] = np.abs(np.roll(sm[a], -k, axis=0) - sm[b]).ravel()
    Y = np.zeros((len(pairs), 2))
    Y[: len(same_pairs), 0] = 1.0
    Y[len(same_pairs):, 1] = 1.0
    return PairTargets(X, Y, len(same_pairs), len(different_pairs))


def _best_shifts(compact: np.ndarray, pairs: np.ndarray, sectors: int) -> np.ndarray:
    """Per pair (a, b) the shift k minimising unweighted Eq. 4, sum |a[(s + k) % S] - b[s]|:
    the brute-force kernel the index itself uses, one call per query a."""
    weights = np.ones(compact.shape[1] // sectors, np.float32)
    shifts = np.empty(len(pairs), np.int64)
    for a in np.unique(pairs[:, 0]):
        at = np.flatnonzero(pairs[:, 0] == a)
        rows = np.ascontiguousarray(pairs[at, 1], dtype=np.int64)
        distance, shift = np.empty(len(rows), np.float32), np.empty(len(rows), np.int64)
        min_over_shifts(compact, rows, compact[a], weights, sectors, distance, shift)
        shifts[at] = shift
    return shifts


def _source_pairs(compact: np.ndarray, positions: np.ndarray, sectors: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(same-place pairs, different-place pairs) of one source, as (m, 2) row indices."""
    n = len(compact)
    tree = cKDTree(positions[:, :2])
    close = tree.query_pairs(SAME_PLACE_M, output_type="ndarray")
    close = close[np.abs(close[:, 0] - close[:, 1]) >= MIN_GAP]
    if len(close) > MAX_PAIRS_PER_SOURCE:
        close = close[rng.choice(len(close), MAX_PAIRS_PER_SOURCE, replace=False)]
    index = KeyframeIndex(np.ones(compact.shape[1], np.float32), IndexParameters(sectors=sectors))
    index.add_batch(compact)
    far_pairs = []
    for i in range(n):
        far = np.linalg.norm(positions[:, :2] - positions[i, :2], axis=1) > DIFFERENT_PLACE_M
        if not far.any():
            continue
        found = index.search(compact[i], HARD_NEGATIVES, far)[0]
        random = rng.choice(np.flatnonzero(far), min(HARD_NEGATIVES, int(far.sum())), replace=False)
        far_pairs += [(i, int(j)) for j in (*found, *random)]
    far_pairs = np.array(far_pairs, np.int64).reshape(-1, 2)
    if len(far_pairs) > MAX_PAIRS_PER_SOURCE:
        far_pairs = far_pairs[rng.choice(len(far_pairs), MAX_PAIRS_PER_SOURCE, replace=False)]
    return close.astype(np.int64), far_pairs
