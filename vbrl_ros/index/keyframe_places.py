"""Where stored keyframes were taken, by keyframe id, and whether any lies near a point.

Sequence matching by place (:mod:`vbrl_ros.index.sequence_matching`) asks, for each of a
keyframe's ~100 candidates and each earlier keyframe, whether any stored keyframe lies near a
point. Keyframes arrive one at a time and a database grows to 100k of them, so the positions
live in a hash grid of ground cells (x, y) as wide as the radius asked for, compiled: adding
is O(1) and a lookup walks the keyframes of the 9 cells around the point, stopping at the
first near one.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_EMPTY = -1
#: Bytes each keyframe adds: its id, position and link in its cell's chain (the table of cells
#: grows with the ground covered, not with the keyframes, and is not counted).
BYTES_PER_KEYFRAME = 8 + 3 * 8 + 8


@njit(cache=True, nogil=True)
def _slot(kx: int, ky: int, used: np.ndarray, keys: np.ndarray) -> int:
    """The table slot of cell (kx, ky): its own, or the empty one where it would go."""
    mask = len(used) - 1
    s = ((kx * 73856093) ^ (ky * 19349663)) & mask
    while used[s] and (keys[s, 0] != kx or keys[s, 1] != ky):
        s = (s + 1) & mask
    return s


@njit(cache=True, nogil=True)
def _insert(row: int, positions: np.ndarray, cell_m: float, used: np.ndarray, keys: np.ndarray,
            heads: np.ndarray, chain: np.ndarray) -> int:
    """Put ``row`` at the head of its cell's chain; returns 1 when the cell is new, else 0."""
    kx, ky = int(np.floor(positions[row, 0] / cell_m)), int(np.floor(positions[row, 1] / cell_m))
    s = _slot(kx, ky, used, keys)
    new = 0
    if not used[s]:
        used[s], keys[s, 0], keys[s, 1], heads[s], new = True, kx, ky, _EMPTY, 1
    chain[row], heads[s] = heads[s], row
    return new


@njit(cache=True, nogil=True)
def _insert_rows(stop: int, positions: np.ndarray, cell_m: float, used: np.ndarray, keys: np.ndarray,
                 heads: np.ndarray, chain: np.ndarray) -> int:
    """:func:`_insert` every located row below ``stop``; returns the cells made."""
    cells = 0
    for row in range(stop):
        if np.isfinite(positions[row, 0]) and np.isfinite(positions[row, 1]) and np.isfinite(positions[row, 2]):
            cells += _insert(row, positions, cell_m, used, keys, heads, chain)
    return cells


@njit(cache=True, nogil=True)
def _any_within(points: np.ndarray, radius: float, positions: np.ndarray, cell_m: float,
                used: np.ndarray, keys: np.ndarray, heads: np.ndarray, chain: np.ndarray) -> np.ndarray:
    out = np.zeros(len(points), np.bool_)
    r2 = radius * radius
    for n in range(len(points)):
        p = points[n]
        if not (np.isfinite(p[0]) and np.isfinite(p[1]) and np.isfinite(p[2])):
            continue
        cx, cy = int(np.floor(p[0] / cell_m)), int(np.floor(p[1] / cell_m))
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                s = _slot(cx + dx, cy + dy, used, keys)
                row = heads[s] if used[s] else _EMPTY
                while row != _EMPTY and not out[n]:
                    ex, ey, ez = positions[row, 0] - p[0], positions[row, 1] - p[1], positions[row, 2] - p[2]
                    out[n] = ex * ex + ey * ey + ez * ez <= r2
                    row = chain[row]
    return out


class KeyframePlaces:
    """Positions (x, y, z in one odometry frame) of keyframes by id; ids grow as they are added.

    ``cell_m``: the hash grid's cell size, the largest radius :meth:`any_within` answers.
    Keyframes without a position (NaN) are remembered as unknown and never near anything.
    """

    def __init__(self, cell_m: float) -> None:
        if not (np.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell size must be > 0 metres, got {cell_m!r}")
        self.cell_m = float(cell_m)
        self._size = 0
        self._ids = np.empty(64, np.int64)
        self._positions = np.empty((64, 3))
        self._chain = np.empty(64, np.int64)  # the next keyframe of the same cell
        self._table(64)

    @classmethod
    def of(cls, cell_m: float, ids: np.ndarray, positions: np.ndarray) -> KeyframePlaces:
        """Keyframes ``ids`` (increasing) at ``positions`` (n, 3; NaN rows: unknown), all at once,
        as a loaded database has them."""
        places = cls(cell_m)
        ids = np.asarray(ids, np.int64)
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        if len(ids) != len(positions) or (np.diff(ids) <= 0).any():
            raise ValueError(f"{len(ids)} increasing ids are needed for {len(positions)} positions")
        capacity = max(64, len(ids))
        places._ids, places._chain = np.resize(ids, capacity), np.full(capacity, _EMPTY, np.int64)
        places._positions = np.resize(positions, (capacity, 3))
        places._size = len(ids)
        places._rehash(max(64, 1 << (2 * len(ids)).bit_length()))  # at most half full
        return places

    def _table(self, slots: int) -> None:
        self._used = np.zeros(slots, np.bool_)
        self._keys = np.zeros((slots, 2), np.int64)
        self._heads = np.full(slots, _EMPTY, np.int64)
        self._cells = 0

    def __len__(self) -> int:
        return self._size

    def add(self, keyframe_id: int, position: np.ndarray | None) -> None:
        """Remember keyframe ``keyframe_id`` (larger than every id before it) at ``position`` (3,)."""
        if self._size and keyframe_id <= self._ids[self._size - 1]:
            raise ValueError(f"keyframe id {keyframe_id} does not follow {self._ids[self._size - 1]}")
        p = np.full(3, np.nan) if position is None else np.asarray(position, np.float64).reshape(3)
        row = self._size
        if row == len(self._ids):
            grown = 2 * len(self._ids)
            self._ids, self._chain = np.resize(self._ids, grown), np.resize(self._chain, grown)
            self._positions = np.resize(self._positions, (grown, 3))
        self._ids[row], self._positions[row], self._chain[row] = keyframe_id, p, _EMPTY
        if np.isfinite(p).all():
            if 2 * (self._cells + 1) > len(self._used):  # keep the table at most half full
                self._rehash(2 * len(self._used))
            self._cells += _insert(row, self._positions, self.cell_m, self._used, self._keys, self._heads,
                                   self._chain)
        self._size += 1

    def _rehash(self, slots: int) -> None:
        self._table(slots)
        self._cells = _insert_rows(self._size, self._positions, self.cell_m, self._used, self._keys, self._heads,
                                   self._chain)

    def clear(self) -> None:
        self.__init__(self.cell_m)

    def positions(self, ids: np.ndarray) -> np.ndarray:
        """(n, 3) positions of keyframes ``ids``; NaN rows for ids unknown or without a position."""
        ids = np.asarray(ids, np.int64)
        out = np.full((len(ids), 3), np.nan)
        if self._size:
            known = self._ids[: self._size]
            at = np.minimum(np.searchsorted(known, ids), self._size - 1)
            hit = known[at] == ids
            out[hit] = self._positions[at[hit]]
        return out

    def any_within(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(n,) bool: whether a stored keyframe lies within ``radius`` (<= ``cell_m``) of each point."""
        if radius > self.cell_m:
            raise ValueError(f"radius {radius} m exceeds the grid's {self.cell_m} m cells")
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        return _any_within(points, float(radius), self._positions, self.cell_m, self._used, self._keys,
                           self._heads, self._chain)
