"""The keyframe index's search parameters: defaults per descriptor shape, and their checks.

What each parameter does is in :class:`~vbrl_ros.keyframe_index.KeyframeIndex`;
the defaults are what ``vbrl bench`` measured to fit query + insert in 10 ms
at 100k keyframes on one core.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.index_keys import MAX_KEY_DIM

_MAX_INT = 2**31 - 1
# 256 4-bit entries (128 bytes): ranks the brute-force match as the 8-bit keys
# of the same length did; 512 ranks it better but doubles the ~2 ms key scan
DEFAULT_KEY_DIM = 256
# a finer (512-entry) key re-scores the scan's best SCAN_POOL x candidates: ranked the
# brute-force match within the 1024 candidates for 32 of 40 winter queries at 100k
# keyframes, as a 512-entry scan would, where the 256-entry key alone managed 26
DEFAULT_REFINE_DIM = 512
DEFAULT_SCAN_POOL = 4


def default_parameters(width: int, sectors: int) -> dict[str, int]:
    """Defaults for R = ``width`` active columns and S sectors, tuned with ``vbrl bench``.

    Query + insert <= 10 ms at 100k keyframes on one core for the Cartesian
    (S = 1, d ~ 7.9k: key scan ~2-3 ms + ~6 us per candidate) and polar
    (S = 24, d ~ 16-23k: key scan ~2-3 ms, yaw keys ~2.5 us per candidate,
    exact ~4-8 us per re-ranked shift, ~1-1.5 ms to complete 8 rows) shapes,
    spending the rest of the budget on candidates, which is what recall on
    cross-season queries needs most.
    """
    polar = sectors > 1
    key_dim = min(DEFAULT_KEY_DIM, width)
    return {
        "key_dim": key_dim,
        "candidates": 1024 if polar else 512,
        "rerank": 128 if polar else 512,
        "yaw_dim": min(width, 32) if polar else 0,
        "yaw_shifts": min(sectors, 2),
        "bound_shifts": sectors,  # every shift: fewer lost real matches (KeyframeIndex._yaw_bounds)
        "complete_rows": 8 if polar else 0,
        "refine_dim": _default_refine_dim(width, key_dim),
        "scan_pool": DEFAULT_SCAN_POOL,
    }


def search_parameters(width: int, sectors: int, **given: int | None) -> dict[str, int]:
    """The search parameters for R = ``width`` columns and S sectors: ``given`` or the default.

    ``ValueError`` names the first out of range.
    """
    chosen = {name: default if given.get(name) is None else given[name]
              for name, default in default_parameters(width, sectors).items()}
    polar = sectors > 1
    limits = {"key_dim": (1, min(width, MAX_KEY_DIM)), "candidates": (1, _MAX_INT),
              "rerank": (1, _MAX_INT), "yaw_dim": (1, width) if polar else (0, 0),
              "yaw_shifts": (1, sectors), "bound_shifts": (1, sectors),
              "complete_rows": (0, _MAX_INT),
              "refine_dim": (0, min(width, MAX_KEY_DIM)), "scan_pool": (1, 64)}
    checked = {}
    for name in limits:  # key_dim and yaw_shifts before what depends on them
        if name == "refine_dim" and given.get(name) is None:
            chosen[name] = _default_refine_dim(width, checked["key_dim"])
        if name == "bound_shifts":  # the shifts tried exactly are among these
            limits[name] = (checked["yaw_shifts"], sectors)
        checked[name] = checked_int(name, chosen[name], *limits[name])
    return checked


def _default_refine_dim(width: int, key_dim: int) -> int:
    """A refine key finer than the scan key actually used, or none."""
    refine = min(DEFAULT_REFINE_DIM, width)
    return refine if refine > key_dim else 0


def checked_int(name: str, value: object, low: int, high: int) -> int:
    """``value`` as an int if it is one in [low, high]; else ``ValueError`` naming ``name``."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not low <= value <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)
