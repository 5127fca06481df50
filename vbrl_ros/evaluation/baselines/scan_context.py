"""Scan Context, the field's LiDAR place-recognition baseline.

Written from the paper's description (G. Kim and A. Kim, "Scan Context:
Egocentric Spatial Descriptor for Place Recognition within 3D Point Cloud
Map", IROS 2018), not from any reference implementation.

Descriptor: the sensor's surroundings are split into ``num_rings`` rings
(equal radial width up to ``max_range``) x ``num_sectors`` sectors (equal
azimuth width, sector 0 starts at azimuth 0 = +x and grows counter-clockwise).
Each bin holds the maximum point height ``z + lidar_height``; empty bins are
0, and so are bins whose points all lie below ``-lidar_height`` (the
descriptor is non-negative, which keeps column cosines in [0, 1]).

Distance (lower = more similar, in [0, 1]): for every column shift, the mean
over column pairs where *both* columns are non-empty of (1 - cosine); the
minimum over all shifts wins and the shift gives the yaw. A shift with no
common non-empty column has distance 1 (no evidence of similarity), so the
distance is always defined, also for empty descriptors.

Yaw convention: ``yaw`` is the rotation about +z that maps the candidate's
points onto the query's, ``p_query ~= Rz(yaw) @ p_candidate`` - i.e. the
rotation part of T_query<-candidate, usable as an ICP initial guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "ScanContextConfig",
    "ScanContextDatabase",
    "Match",
    "scan_context",
    "ring_key",
    "sector_key",
    "sector_key_shift",
    "scan_context_distance",
    "scan_context_distances",
]


@dataclass(frozen=True)
class ScanContextConfig:
    """Descriptor geometry. Defaults are the paper's (20 x 60, 80 m)."""

    num_rings: int = 20
    num_sectors: int = 60
    max_range: float = 80.0
    # Sensor height above the ground: shifts z so that ground points are ~0.
    # 2.0 m is the KITTI car mount the paper used; set it per platform.
    lidar_height: float = 2.0

    def __post_init__(self) -> None:
        for name in ("num_rings", "num_sectors"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not (math.isfinite(self.max_range) and self.max_range > 0):
            raise ValueError(f"max_range must be finite and > 0, got {self.max_range!r}")
        if not math.isfinite(self.lidar_height):
            raise ValueError(f"lidar_height must be finite, got {self.lidar_height!r}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.num_rings, self.num_sectors)

    @property
    def sector_angle(self) -> float:
        """Azimuth width of one sector, radians."""
        return 2.0 * math.pi / self.num_sectors


DEFAULT_CONFIG = ScanContextConfig()


class Match(NamedTuple):
    """Best database match; ``index == -1`` (distance inf) when there is none."""

    index: int
    distance: float
    yaw: float


def scan_context(points: np.ndarray, config: ScanContextConfig = DEFAULT_CONFIG) -> np.ndarray:
    """(num_rings, num_sectors) float32 max-height descriptor of ``points``.

    ``points`` is (N, 3) or (N, >=3) (extra columns such as intensity are
    ignored) in the sensor frame. Non-finite points and points at or beyond
    ``max_range`` (horizontal distance) are dropped.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3) or (N, >=3), got shape {pts.shape}")
    x = pts[:, 0].astype(np.float64)
    y = pts[:, 1].astype(np.float64)
    z = pts[:, 2].astype(np.float64)
    range_sq = x * x + y * y
    # NaN compares False, so this also drops non-finite x / y.
    keep = (range_sq < config.max_range**2) & np.isfinite(z)
    x, y, z, range_sq = x[keep], y[keep], z[keep], range_sq[keep]

    ring = (np.sqrt(range_sq) * (config.num_rings / config.max_range)).astype(np.intp)
    azimuth = np.arctan2(y, x)
    azimuth[azimuth < 0] += 2.0 * math.pi
    sector = (azimuth * (config.num_sectors / (2.0 * math.pi))).astype(np.intp)
    # Round-off can put a point exactly on the outer edge (e.g. -1e-17 + 2*pi).
    np.minimum(ring, config.num_rings - 1, out=ring)
    np.minimum(sector, config.num_sectors - 1, out=sector)

    # Starting from zeros makes empty bins 0 and clips below-ground heights.
    flat = np.zeros(config.num_rings * config.num_sectors, dtype=np.float64)
    np.maximum.at(flat, ring * config.num_sectors + sector, z + config.lidar_height)
    return flat.reshape(config.shape).astype(np.float32)


def ring_key(descriptor: np.ndarray) -> np.ndarray:
    """Per-ring mean (rotation invariant): the prefilter key, shape (..., num_rings)."""
    return np.asarray(descriptor, dtype=np.float32).mean(axis=-1)


def sector_key(descriptor: np.ndarray) -> np.ndarray:
    """Per-sector mean, shape (..., num_sectors): cheap 1-D yaw alignment."""
    return np.asarray(descriptor, dtype=np.float32).mean(axis=-2)


def _shift_index(num_sectors: int) -> np.ndarray:
    """idx[k, j] = (j - k) mod S: the candidate column paired with query column j at shift k."""
    j = np.arange(num_sectors)
    return np.mod(j[None, :] - j[:, None], num_sectors)


def sector_key_shift(query_sector_key: np.ndarray, candidate_sector_key: np.ndarray) -> int:
    """Coarse column shift minimising the L2 distance between sector keys (all shifts at once)."""
    q = np.asarray(query_sector_key, dtype=np.float64)
    c = np.asarray(candidate_sector_key, dtype=np.float64)
    shifted = c[_shift_index(q.shape[-1])]  # (S shifts, S columns)
    return int(np.argmin(((shifted - q[None, :]) ** 2).sum(axis=1)))


def _unit_columns(descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit norm (empty columns stay 0) and the non-empty mask."""
    d = np.asarray(descriptors, dtype=np.float64)
    norms = np.linalg.norm(d, axis=-2)
    nonempty = norms > 0
    return d / np.where(nonempty, norms, 1.0)[..., None, :], nonempty


def _yaw_of_shift(shift: np.ndarray, num_sectors: int) -> np.ndarray:
    # Map shifts to (-S/2, S/2] so the yaw lands in (-pi, pi].
    signed = np.where(shift > num_sectors // 2, shift - num_sectors, shift)
    return signed * (2.0 * math.pi / num_sectors)


def scan_context_distances(
    query: np.ndarray,
    candidates: np.ndarray,
    search_radius: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Distances and yaws from one query (R, S) to many candidates (M, R, S).

    All column shifts are scored at once (one matrix product over shifted
    copies of the query), no Python loop over shifts or candidates. With ``search_radius``, only
    shifts within +-search_radius columns of the sector-key alignment are
    considered (the paper's fast variant); by default all shifts are.
    Returns ``(distances (M,), yaws (M,))``.
    """
    q = np.asarray(query)
    c = np.asarray(candidates)
    if c.ndim == 2:
        c = c[None]
    if q.ndim != 2 or c.ndim != 3 or c.shape[1:] != q.shape:
        raise ValueError(f"shape mismatch: query {q.shape}, candidates {c.shape}")
    num_sectors = q.shape[1]
    if c.shape[0] == 0:
        return np.empty(0), np.empty(0)

    q_unit, q_nonempty = _unit_columns(q)
    c_unit, c_nonempty = _unit_columns(c)
    # Query columns pre-shifted for every shift k: q_shifted[k, :, l] is the
    # query column paired with candidate column l, i.e. column (l + k) mod S.
    # Then all M x S cosine sums are one (M, R*S) @ (R*S, S) product.
    paired = np.mod(np.arange(num_sectors)[None, :] + np.arange(num_sectors)[:, None], num_sectors)
    q_shifted = np.transpose(q_unit[:, paired], (1, 0, 2))  # (S shifts, R, S)
    cos_sum = c_unit.reshape(c.shape[0], -1) @ q_shifted.reshape(num_sectors, -1).T
    pairs = c_nonempty.astype(np.float64) @ q_nonempty[paired].astype(np.float64).T
    per_shift = np.where(pairs > 0, 1.0 - cos_sum / np.maximum(pairs, 1.0), 1.0)
    # Cosines of non-negative vectors are in [0, 1]; clip float round-off.
    np.clip(per_shift, 0.0, 1.0, out=per_shift)

    if search_radius is not None:
        if search_radius < 0:
            raise ValueError("search_radius must be >= 0")
        q_key = sector_key(q).astype(np.float64)
        c_key = sector_key(c).astype(np.float64)
        cols = _shift_index(num_sectors)
        key_err = ((c_key[:, cols] - q_key[None, None, :]) ** 2).sum(axis=2)  # (M, S)
        coarse = np.argmin(key_err, axis=1)
        offset = np.mod(np.arange(num_sectors)[None, :] - coarse[:, None], num_sectors)
        outside = np.minimum(offset, num_sectors - offset) > search_radius
        per_shift = np.where(outside, np.inf, per_shift)

    best = np.argmin(per_shift, axis=1)
    distances = per_shift[np.arange(c.shape[0]), best]
    return distances, _yaw_of_shift(best, num_sectors)


def scan_context_distance(
    query: np.ndarray, candidate: np.ndarray, search_radius: int | None = None
) -> tuple[float, float]:
    """``(distance, yaw)`` between two descriptors; see the module docstring."""
    d, yaw = scan_context_distances(query, np.asarray(candidate)[None], search_radius)
    return float(d[0]), float(yaw[0])


class ScanContextDatabase:
    """Growing keyframe database: ring-key k-d tree prefilter + exact SC distance.

    The k-d tree over ring keys is rebuilt lazily, when the entries added since
    the last build exceed ``max(rebuild_min, rebuild_fraction * tree size)``
    (geometric growth keeps the amortised cost per insert O(log n)). Entries
    not yet in the tree are scanned brute force, so the prefilter returns the
    exact ring-key nearest neighbours among the allowed entries at any time.
    """

    def __init__(
        self,
        config: ScanContextConfig = DEFAULT_CONFIG,
        rebuild_min: int = 64,
        rebuild_fraction: float = 0.1,
        search_radius: int | None = None,
    ) -> None:
        if rebuild_min < 1 or rebuild_fraction < 0:
            raise ValueError("rebuild_min must be >= 1 and rebuild_fraction >= 0")
        self.config = config
        self.rebuild_min = int(rebuild_min)
        self.rebuild_fraction = float(rebuild_fraction)
        self.search_radius = search_radius
        self._size = 0
        self._descriptors = np.zeros((16, *config.shape), dtype=np.float32)
        self._ring_keys = np.zeros((16, config.num_rings), dtype=np.float32)
        self._tree: cKDTree | None = None
        self._tree_size = 0
        self.tree_builds = 0  # exposed for tests / diagnostics

    def __len__(self) -> int:
        return self._size

    @property
    def descriptors(self) -> np.ndarray:
        """Read-only view of the stored descriptors, (len, R, S)."""
        view = self._descriptors[: self._size]
        view.flags.writeable = False
        return view

    def add(self, descriptor: np.ndarray) -> int:
        """Append a descriptor; returns its index (insertion order)."""
        d = np.asarray(descriptor, dtype=np.float32)
        if d.shape != self.config.shape:
            raise ValueError(f"descriptor shape {d.shape} != {self.config.shape}")
        if not np.isfinite(d).all():
            raise ValueError("descriptor contains non-finite values")
        if self._size == len(self._descriptors):  # amortised O(1) growth
            self._descriptors = np.concatenate([self._descriptors, np.zeros_like(self._descriptors)])
            self._ring_keys = np.concatenate([self._ring_keys, np.zeros_like(self._ring_keys)])
        self._descriptors[self._size] = d
        self._ring_keys[self._size] = ring_key(d)
        self._size += 1
        return self._size - 1

    def add_points(self, points: np.ndarray) -> int:
        """Describe a scan and append it."""
        return self.add(scan_context(points, self.config))

    def _limit(self, exclude_last: int, max_index: int | None) -> int:
        if exclude_last < 0:
            raise ValueError("exclude_last must be >= 0")
        limit = self._size - exclude_last
        if max_index is not None:
            limit = min(limit, int(max_index))
        return max(limit, 0)

    def ring_key_candidates(self, key: np.ndarray, num_candidates: int, limit: int) -> np.ndarray:
        """Indices (< limit) of the ``num_candidates`` nearest ring keys, nearest first."""
        if num_candidates < 1:
            raise ValueError("num_candidates must be >= 1")
        key = np.asarray(key, dtype=np.float32)
        if limit <= 0:
            return np.empty(0, dtype=np.intp)
        tail_start = min(self._tree_size, limit)
        if limit - self._tree_size > max(self.rebuild_min, self.rebuild_fraction * self._tree_size):
            self._tree = cKDTree(self._ring_keys[:limit].copy())
            self._tree_size = tail_start = limit
            self.tree_builds += 1
        if self._tree is not None and tail_start >= self._tree_size - tail_start:
            # Tree entries >= limit are filtered out; asking for that many
            # extra neighbours guarantees num_candidates allowed ones survive.
            k = min(num_candidates + self._tree_size - tail_start, self._tree_size)
            dist, idx = self._tree.query(key, k=k)
            dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
            ok = idx < tail_start
            idx, dist = idx[ok].astype(np.intp), dist[ok]
        else:
            tail_start = 0  # tree missing or mostly excluded: scan the prefix instead
            idx, dist = np.empty(0, dtype=np.intp), np.empty(0)
        tail = np.arange(tail_start, limit)
        tail_dist = np.linalg.norm(self._ring_keys[tail_start:limit] - key[None, :], axis=1)
        idx = np.concatenate([idx, tail])
        dist = np.concatenate([dist, tail_dist])
        order = np.lexsort((idx, dist))[:num_candidates]  # ties: lower index first
        return idx[order]

    def query_top_k(
        self,
        descriptor: np.ndarray,
        k: int = 1,
        num_candidates: int = 10,
        exclude_last: int = 0,
        max_index: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Up to ``k`` best matches among entries ``< min(len - exclude_last, max_index)``.

        Returns ``(indices, distances, yaws)``, sorted by distance; fewer than
        ``k`` when fewer candidates pass the prefilter.
        """
        d = np.asarray(descriptor, dtype=np.float32)
        if d.shape != self.config.shape:
            raise ValueError(f"descriptor shape {d.shape} != {self.config.shape}")
        limit = self._limit(exclude_last, max_index)
        cand = self.ring_key_candidates(ring_key(d), max(num_candidates, k), limit)
        dist, yaw = scan_context_distances(d, self._descriptors[cand], self.search_radius)
        order = np.lexsort((cand, dist))[:k]
        return cand[order], dist[order], yaw[order]

    def query(
        self,
        descriptor: np.ndarray,
        num_candidates: int = 10,
        exclude_last: int = 0,
        max_index: int | None = None,
    ) -> Match:
        """Best match ``(index, distance, yaw)``; ``Match(-1, inf, 0.0)`` if none allowed."""
        idx, dist, yaw = self.query_top_k(descriptor, 1, num_candidates, exclude_last, max_index)
        if len(idx) == 0:
            return Match(-1, math.inf, 0.0)
        return Match(int(idx[0]), float(dist[0]), float(yaw[0]))
