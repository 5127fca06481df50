"""Saving and restoring a :class:`~vbrl_ros.keyframe_index.KeyframeIndex` as plain arrays.

The arrays go into the keyframe database's ``.npz`` (no pickle): parameters,
weights, the stored descriptors in their storage dtype, the candidate keys
(int8 values in [-7, 7]) and the float32 yaw keys. Keys are derived data, so
on restore a sample of them is recomputed from the descriptors: a file written
with other key parameters (or a different key construction) is refused
instead of silently searching with wrong keys. Version 2 files (int8 keys of
the 8-bit construction) are re-keyed from their descriptors on load.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from vbrl_ros.keyframe_index import KeyframeIndex

INDEX_FORMAT = "vbrl_ros.keyframe_index"
INDEX_FORMAT_VERSION = 3
_REKEYED_VERSIONS = (2,)  # readable: same descriptors and parameters, keys recomputed
_PARAMS = ("sectors", "key_dim", "candidates", "rerank", "yaw_dim", "yaw_shifts", "yaw_refine",
           "seed", "complete_rows", "refine_dim", "scan_pool", "bound_shifts")
_FIRST_PARAMS = 8  # files written before the later parameters existed: their defaults apply
_KEY_CHECK_ROWS = 64
_REKEY_ROWS = 4096


def index_state(index: KeyframeIndex, prefix: str) -> dict[str, np.ndarray]:
    return {
        f"{prefix}format": np.array(INDEX_FORMAT),
        f"{prefix}format_version": np.array(INDEX_FORMAT_VERSION, np.int64),
        f"{prefix}weights": index.weights.copy(),
        f"{prefix}params": np.array([int(getattr(index, name)) for name in _PARAMS], np.int64),
        f"{prefix}key_clip_sigma": np.array(index.key_clip_sigma, np.float64),
        f"{prefix}storage": np.array(index.storage),
        f"{prefix}descriptors": np.array(index.descriptors()),
        f"{prefix}keys": index.stored_keys(),
        f"{prefix}yaw_keys": index.stored_yaw_keys(),
        f"{prefix}refine_keys": index.stored_refine_keys(),
    }


def index_from_state(cls: type[KeyframeIndex], arrays: Mapping[str, np.ndarray],
                     prefix: str) -> KeyframeIndex:
    def get(name: str) -> np.ndarray:
        if f"{prefix}{name}" not in arrays:
            raise ValueError(f"keyframe index state lacks '{prefix}{name}'")
        return np.asarray(arrays[f"{prefix}{name}"])

    if get("format").shape != () or str(get("format")) != INDEX_FORMAT:
        raise ValueError(f"not a keyframe index state (format tag '{INDEX_FORMAT}' missing)")
    version = get("format_version")
    readable = (INDEX_FORMAT_VERSION, *_REKEYED_VERSIONS)
    if version.shape != () or version.dtype.kind not in "iu" or int(version) not in readable:
        raise ValueError(f"keyframe index state version {version}; this code reads {readable}")
    rekey = int(version) in _REKEYED_VERSIONS
    params = get("params")
    if (params.ndim != 1 or not _FIRST_PARAMS <= len(params) <= len(_PARAMS)
            or params.dtype.kind not in "iu"):
        raise ValueError(f"index params have shape {params.shape}, expected ({len(_PARAMS)},) integers")
    options: dict[str, Any] = {name: int(value) for name, value in zip(_PARAMS, params)}
    options["yaw_refine"] = bool(options["yaw_refine"])
    if not rekey:  # the old clip was in int8 steps: re-keyed files take today's default
        options["key_clip_sigma"] = float(get("key_clip_sigma"))
    index = cls(get("weights"), storage=str(get("storage")), **options)
    descriptors, keys, yaw = get("descriptors"), get("keys"), get("yaw_keys")
    n = len(descriptors)
    if descriptors.shape != (n, index.dimension) or descriptors.dtype != np.dtype(index.storage):
        raise ValueError(f"descriptors have shape {descriptors.shape} {descriptors.dtype}, "
                         f"expected ({n}, {index.dimension}) {index.storage}")
    if not np.all(np.isfinite(descriptors)):
        raise ValueError("descriptors contain NaN or inf")
    if rekey:  # candidate keys of the 8-bit construction (yaw keys are unchanged)
        keys = np.empty((n, index.key_dim), np.int8)
        refine = np.empty((n, index.refine_dim), np.int8)
        for start in range(0, n, _REKEY_ROWS):
            chunk = descriptors[start : start + _REKEY_ROWS].astype(np.float32)
            keys[start : start + len(chunk)], _, refine[start : start + len(chunk)] = (
                index.keys_as_stored(chunk))
    else:
        refine = get("refine_keys")
    if refine.shape != (n, index.refine_dim) or refine.dtype != np.int8:
        raise ValueError(f"refine keys have shape {refine.shape} {refine.dtype}, "
                         f"expected ({n}, {index.refine_dim}) int8")
    if keys.shape != (n, index.key_dim) or keys.dtype != np.int8:
        raise ValueError(f"keys have shape {keys.shape} {keys.dtype}, "
                         f"expected ({n}, {index.key_dim}) int8")
    if yaw.shape != (n, index.sectors, index.yaw_dim) or yaw.dtype != np.float32:
        raise ValueError(f"yaw keys have shape {yaw.shape} {yaw.dtype}, "
                         f"expected ({n}, {index.sectors}, {index.yaw_dim}) float32")
    sample = np.unique(np.linspace(0, n - 1, min(n, _KEY_CHECK_ROWS)).astype(np.int64))
    expected = index.keys_as_stored(descriptors[sample].astype(np.float32))
    if n and not all(np.array_equal(computed, stored[sample])
                     for computed, stored in zip(expected, (keys, yaw, refine))):
        raise ValueError("stored keys do not match the descriptors (other key parameters?)")
    index._adopt(descriptors, keys, yaw, refine)
    return index
