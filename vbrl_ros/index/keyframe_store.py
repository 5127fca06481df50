"""The keyframe index's memory: descriptors in insertion order, each with its small keys.

Per keyframe: the compact descriptor (float32, or float16 for half the
memory), the 4-bit candidate key in blocks of :data:`~vbrl_ros.index.keys.BLOCK`
keyframes, the 4-bit refine key row-major, and the float32 yaw key split
into its first quarter of groups (the coarse screen) and the rest (see
:mod:`vbrl_ros.index.keys`). Inserts are O(d) amortised: arrays grow by
doubling and a key never changes once written, so nothing is ever rebuilt.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.index import keys as kk
from vbrl_ros.index.parameters import STORAGE_TYPES, IndexParameters
from vbrl_ros.index.state import StoredArrays
from vbrl_ros.model import distance_kernels as wk

INITIAL_CAPACITY = 64
_BATCH_ROWS = 4096  # keys of a bulk insert are computed in chunks of this many rows
_FLOAT16_MAX = 65504.0
_KEY_CHECK_ROWS = 64  # stored keys compared with recomputed ones on restore
_REKEY_ROWS = 4096


def grown(array: np.ndarray, needed: int) -> np.ndarray:
    """``array`` with capacity >= needed along axis 0, doubling so growth is amortised O(1)."""
    capacity = len(array)
    if needed <= capacity:
        return array
    out = np.empty((max(needed, 2 * capacity, INITIAL_CAPACITY), *array.shape[1:]), array.dtype)
    out[:capacity] = array
    return out


class KeyframeStore:
    """Descriptors and keys of the keyframes, for resolved ``parameters`` and column weights.

    The search reads the arrays directly: :attr:`key_blocks`, :attr:`refine_key_bytes`,
    :attr:`yaw_coarse`, :attr:`yaw_fine` and :meth:`kernel_view` (valid up to ``len(store)``;
    an insert may replace them).
    """

    def __init__(self, column_weights: np.ndarray, parameters: IndexParameters, dimension: int) -> None:
        p = parameters
        self.parameters, self.dimension, self.sectors = p, dimension, p.sectors
        self.codec = kk.KeyCodec(column_weights, p.sectors, p.key_dim, p.yaw_dim, p.seed,
                                 p.key_clip_sigma, p.refine_dim)
        self._size = 0
        self._descriptors = np.empty((INITIAL_CAPACITY, dimension), STORAGE_TYPES[p.storage])
        self.key_blocks = np.empty((1, self._key_bytes(), kk.BLOCK), np.uint8)
        self.refine_key_bytes = np.empty((INITIAL_CAPACITY, -(-p.refine_dim // 2)), np.uint8)
        # the yaw key's first quarter of groups is kept apart to screen candidates cheaply
        self.coarse_groups = p.yaw_dim // 4
        self.yaw_coarse = np.empty((INITIAL_CAPACITY, p.sectors, self.coarse_groups), np.float32)
        self.yaw_fine = np.empty((INITIAL_CAPACITY, p.sectors, p.yaw_dim - self.coarse_groups),
                                 np.float32)

    # -- size and memory ------------------------------------------------------

    def __len__(self) -> int:
        return self._size

    def bytes_breakdown(self) -> dict[str, int]:
        """Per-keyframe bytes of the descriptor (d x 4 or 2), the 4-bit keys and the yaw key."""
        p = self.parameters
        return {"descriptor": self.dimension * np.dtype(STORAGE_TYPES[p.storage]).itemsize,
                "key": self._key_bytes() + self.refine_key_bytes.shape[1],
                "yaw_key": 4 * self.sectors * p.yaw_dim}

    def _key_bytes(self) -> int:
        return -(-self.parameters.key_dim // 2)  # two 4-bit entries per byte

    def reserve(self, needed: int) -> None:
        """Room for ``needed`` keyframes (avoids doubling copies in bulk loads)."""
        self._descriptors = grown(self._descriptors, needed)
        self.yaw_coarse = grown(self.yaw_coarse, needed)
        self.yaw_fine = grown(self.yaw_fine, needed)
        self.refine_key_bytes = grown(self.refine_key_bytes, needed)
        self.key_blocks = grown(self.key_blocks, -(-needed // kk.BLOCK))

    # -- descriptors ------------------------------------------------------------

    def check(self, descriptors: np.ndarray, ndim: int = 1) -> np.ndarray:
        """float32 (d,) or (n, d) compact descriptor(s), or ``ValueError`` naming the problem."""
        # aligned + contiguous: numba compiles unaligned views (e.g. from an .npz) to scalar code
        x = np.require(descriptors, np.float32, ["C", "A"])
        if x.ndim != ndim or x.shape[-1] != self.dimension:
            what = "(d,)" if ndim == 1 else "(n, d)"
            raise ValueError(
                f"compact descriptor(s) must have shape {what} with d = {self.dimension} active "
                f"rows, got {x.shape} (pass scorer.compact(descriptor))"
            )
        if not np.all(np.isfinite(x)):
            raise ValueError("descriptor contains NaN or inf")
        if self.parameters.storage == "float16" and x.size and float(np.abs(x).max()) > _FLOAT16_MAX:
            raise ValueError("descriptor exceeds the float16 range; use storage='float32'")
        return x

    def descriptors(self) -> np.ndarray:
        """Read-only view of the stored descriptors (n, d) in the storage dtype."""
        view = self._descriptors[: self._size]
        view.flags.writeable = False
        return view

    def descriptor(self, index: int) -> np.ndarray:
        """A copy of stored descriptor ``index`` as float32 (as stored: float16-rounded if so)."""
        if not -self._size <= index < self._size:
            raise IndexError(f"keyframe index {index} out of range for {self._size} keyframes")
        return self._descriptors[index % self._size].astype(np.float32)

    def kernel_view(self) -> np.ndarray:
        """The descriptors as the compiled kernels read them: float32, or float16 bits as uint16."""
        if self.parameters.storage == "float32":
            return self._descriptors
        return self._descriptors.view(np.uint16)

    def insert(self, x: np.ndarray) -> np.ndarray:
        """Append checked descriptors (m, d) with their keys; returns their indices."""
        n, m = self._size, len(x)
        self.reserve(n + m)
        for start in range(0, m, _BATCH_ROWS):
            chunk = np.ascontiguousarray(x[start : start + _BATCH_ROWS])
            rows = np.arange(n + start, n + start + len(chunk))
            if self.parameters.storage == "float32":
                self._descriptors[rows[0] : rows[-1] + 1] = chunk
            else:  # keys of the values as stored, so the bounds stay valid
                wk.store_half(chunk, self.kernel_view()[rows[0] : rows[-1] + 1])
            keys, yaw, refine = self.codec.raw(self.kernel_view()[rows[0] : rows[-1] + 1])
            self._write_keys(rows, self.codec.quantised(keys), yaw,
                             self.codec.refine_quantised(refine))
        self._size = n + m
        return np.arange(n, n + m, dtype=np.int64)

    # -- keys -------------------------------------------------------------------

    def raw_keys(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unquantised (candidate keys (n, key_dim), yaw keys (n, S, yaw_dim)) of (n, d).

        Their L1 distances (the yaw key's under a circular shift of its first
        axis) are lower bounds of D_k for every shift k.
        """
        x = np.ascontiguousarray(descriptors, dtype=np.float32).reshape(-1, self.dimension)
        return self.codec.raw(x)[:2]

    def keys_as_stored(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(candidate keys (n, key_dim) int8, yaw keys (n, S, yaw_dim) float32, refine keys
        (n, refine_dim) int8) of compact descriptors (n, d), from one pass over them."""
        x = np.ascontiguousarray(descriptors, dtype=np.float32).reshape(-1, self.dimension)
        keys, yaw, refine = self.codec.raw(x)
        return (self.codec.quantised(keys).astype(np.int8) - 8, yaw,
                self.codec.refine_quantised(refine).astype(np.int8) - 8)

    def keys(self, descriptors: np.ndarray) -> np.ndarray:
        """Candidate keys (n, key_dim) or (key_dim,) of compact descriptors: int8 in [-7, 7]."""
        x = np.asarray(descriptors)
        return self.keys_as_stored(x)[0].reshape(*x.shape[:-1], self.parameters.key_dim)

    def refine_keys(self, descriptors: np.ndarray) -> np.ndarray:
        """Refine keys (n, refine_dim) of compact descriptors (n, d): int8 in [-7, 7]."""
        return self.keys_as_stored(descriptors)[2]

    def stored_keys(self) -> np.ndarray:
        """The stored candidate keys (n, key_dim), int8 in [-7, 7], row-major."""
        pairs = self.key_blocks.transpose(0, 2, 1).reshape(-1, self._key_bytes())[: self._size]
        return kk.unpacked(pairs, self.parameters.key_dim).astype(np.int8) - 8

    def stored_refine_keys(self) -> np.ndarray:
        """The stored refine keys (n, refine_dim), int8 in [-7, 7]."""
        return (kk.unpacked(self.refine_key_bytes[: self._size], self.parameters.refine_dim)
                .astype(np.int8) - 8)

    def stored_yaw_keys(self) -> np.ndarray:
        """The stored yaw keys (n, S, yaw_dim) float32 (a copy)."""
        n = self._size
        return np.concatenate([self.yaw_coarse[:n], self.yaw_fine[:n]], axis=2)

    def _write_keys(self, rows: np.ndarray, key_codes: np.ndarray, yaw: np.ndarray,
                    refine_codes: np.ndarray) -> None:
        """Store the keys of consecutive ``rows`` (nibble codes: value + 8)."""
        first, last, split = rows[0], rows[-1] + 1, self.coarse_groups
        self.key_blocks[rows // kk.BLOCK, :, rows % kk.BLOCK] = kk.packed(key_codes)
        self.refine_key_bytes[first:last] = kk.packed(refine_codes)
        self.yaw_coarse[first:last] = yaw[:, :, :split]
        self.yaw_fine[first:last] = yaw[:, :, split:]

    # -- persistence ------------------------------------------------------------

    def arrays(self) -> StoredArrays:
        """What is stored, as plain arrays (copies of the keys; a view of the descriptors)."""
        return StoredArrays(self.descriptors(), self.stored_keys(), self.stored_yaw_keys(),
                            self.stored_refine_keys())

    def restore(self, stored: StoredArrays) -> None:
        """Replace the contents by saved arrays (checked by :func:`~vbrl_ros.index.state.read_arrays`).

        Keys of an older construction are recomputed from the descriptors; a sample
        of saved ones must equal keys recomputed from them (``ValueError`` otherwise).
        """
        descriptors, keys, yaw, refine = (stored.descriptors, stored.keys, stored.yaw_keys,
                                          stored.refine_keys)
        n = len(descriptors)
        if keys is None or refine is None:  # candidate keys of an older construction
            keys = np.empty((n, self.parameters.key_dim), np.int8)
            refine = np.empty((n, self.parameters.refine_dim), np.int8)
            for start in range(0, n, _REKEY_ROWS):
                chunk = descriptors[start : start + _REKEY_ROWS].astype(np.float32)
                keys[start : start + len(chunk)], _, refine[start : start + len(chunk)] = (
                    self.keys_as_stored(chunk))
        sample = np.unique(np.linspace(0, n - 1, min(n, _KEY_CHECK_ROWS)).astype(np.int64))
        expected = self.keys_as_stored(descriptors[sample].astype(np.float32))
        if n and not all(np.array_equal(computed, saved[sample])
                         for computed, saved in zip(expected, (keys, yaw, refine))):
            raise ValueError("stored keys do not match the descriptors (other key parameters?)")
        self._size = 0
        self.reserve(n)
        self._descriptors[:n] = descriptors
        if n:
            self._write_keys(np.arange(n), (keys + 8).astype(np.uint8), yaw,
                             (refine + 8).astype(np.uint8))
        self._size = n
