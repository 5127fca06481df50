"""The keyframe index's parameters: one object, the defaults per descriptor shape, their checks.

What each parameter does is in :class:`~vbrl_ros.index.keyframe_index.KeyframeIndex`;
the defaults fit query + insert in 10 ms at 100k keyframes on one core
(``vbrl bench``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from vbrl_ros.index.harmonics import feature_count
from vbrl_ros.index.keys import MAX_KEY_DIM

_MAX_INT = 2**31 - 1
# 256 4-bit entries (128 bytes) rank the brute-force match as well as 8-bit keys
# of the same length; 512 rank it better but double the ~2 ms key scan
DEFAULT_KEY_DIM = 256
# a finer key re-scores the scan's best DEFAULT_SCAN_POOL x candidates: it ranks the
# brute-force match about as well as a 512-entry scan would, at a fraction of its cost
DEFAULT_REFINE_DIM = 512
DEFAULT_SCAN_POOL = 4
STORAGE_TYPES = {"float32": np.float32, "float16": np.float16}
#: Parameters a saved index stores apart from the integer ones (see :mod:`.state`).
SAVED_APART = ("storage", "key_clip_sigma")


@dataclass(frozen=True)
class IndexParameters:
    """How a :class:`~vbrl_ros.index.keyframe_index.KeyframeIndex` stores and searches.

    ``None`` takes the default for the descriptor's shape (:func:`default_parameters`);
    :meth:`resolved` makes every value concrete and checks it. ``storage`` and
    ``key_clip_sigma`` are checked at construction.

    The field order is the order of the integers a saved index stores
    (:mod:`.state`): a new integer parameter goes after the last of them.
    """

    sectors: int = 1
    key_dim: int | None = None
    candidates: int | None = None
    rerank: int | None = None
    yaw_dim: int | None = None
    yaw_shifts: int | None = None
    yaw_refine: bool = False
    seed: int = 0
    complete_rows: int | None = None
    refine_dim: int | None = None
    scan_pool: int | None = None
    bound_shifts: int | None = None
    storage: str = "float32"
    key_clip_sigma: float = 3.0

    def __post_init__(self) -> None:
        if self.storage not in STORAGE_TYPES:
            raise ValueError(f"storage must be one of {sorted(STORAGE_TYPES)}, got {self.storage!r}")
        if not self.key_clip_sigma > 0:
            raise ValueError(f"key_clip_sigma must be positive, got {self.key_clip_sigma!r}")

    def resolved(self, width: int) -> IndexParameters:
        """Every parameter concrete for R = ``width`` active columns of ``sectors`` sectors.

        ``ValueError`` names the first one out of range.
        """
        sectors = self.sectors
        given = asdict(self)
        chosen = {name: default if given[name] is None else given[name]
                  for name, default in default_parameters(width, sectors).items()}
        polar = sectors > 1
        features = min(feature_count(width, sectors), MAX_KEY_DIM)  # column sums and harmonics
        limits = {"key_dim": (1, features), "candidates": (1, _MAX_INT),
                  "rerank": (1, _MAX_INT), "yaw_dim": (1, width) if polar else (0, 0),
                  "yaw_shifts": (1, sectors), "bound_shifts": (1, sectors),
                  "complete_rows": (0, _MAX_INT),
                  "refine_dim": (0, features), "scan_pool": (1, 64)}
        checked = {}
        for name in limits:  # key_dim and yaw_shifts before what depends on them
            if name == "refine_dim" and given[name] is None:
                chosen[name] = _default_refine_dim(width, sectors, checked["key_dim"])
            if name == "bound_shifts":  # the shifts tried exactly are among these
                limits[name] = (checked["yaw_shifts"], sectors)
            checked[name] = checked_int(name, chosen[name], *limits[name])
        return replace(self, **checked, yaw_refine=bool(self.yaw_refine), seed=int(self.seed),
                       key_clip_sigma=float(self.key_clip_sigma))


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
    key_dim = min(DEFAULT_KEY_DIM, feature_count(width, sectors))
    return {
        "key_dim": key_dim,
        "candidates": 1024 if polar else 512,
        "rerank": 128 if polar else 512,
        "yaw_dim": min(width, 32) if polar else 0,
        "yaw_shifts": min(sectors, 2),
        "bound_shifts": sectors,  # every shift: fewer lost real matches (KeyframeIndex._yaw_bounds)
        "complete_rows": 8 if polar else 0,
        "refine_dim": _default_refine_dim(width, sectors, key_dim),
        "scan_pool": DEFAULT_SCAN_POOL,
    }


def _default_refine_dim(width: int, sectors: int, key_dim: int) -> int:
    """A refine key finer than the scan key actually used, or none."""
    refine = min(DEFAULT_REFINE_DIM, feature_count(width, sectors))
    return refine if refine > key_dim else 0


def checked_int(name: str, value: object, low: int, high: int) -> int:
    """``value`` as an int if it is one in [low, high]; else ``ValueError`` naming ``name``."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not low <= value <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)
