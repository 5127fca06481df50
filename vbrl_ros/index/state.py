"""A keyframe index as plain arrays: its parameters, weights, descriptors and keys.

The arrays go into the keyframe database's ``.npz`` (no pickle): the
parameters, the weights, the stored descriptors in their storage dtype, the
candidate and refine keys (int8 values in [-7, 7]) and the float32 yaw keys.
This module only writes and reads them; the index checks on restore that a
sample of the keys matches its descriptors, so a file written with other key
parameters (or another key construction) is refused instead of silently
searching with wrong keys.

Older files come back without candidate and refine keys, which the index
computes from the stored descriptors (their yaw keys are today's): version 2
(8-bit keys) and version 3 (keys of column sums only, at most one entry per
column). Their key sizes, if they were the defaults of their day, become
today's, so a database of a narrow descriptor saved before the keys had
harmonics gains them on loading; sizes chosen by hand are kept.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from vbrl_ros.index.parameters import SAVED_APART, IndexParameters
from vbrl_ros.io.npz import INTEGER, NUMBER, TEXT, Member

INDEX_FORMAT = "vbrl_ros.keyframe_index"
INDEX_FORMAT_VERSION = 4
_REKEYED_VERSIONS = (2, 3)  # readable: same descriptors and parameters, keys recomputed
# key sizes every version before 4 defaulted to (min with the column count)
_OLD_KEY_DIM, _OLD_REFINE_DIM = 256, 512
#: The integer parameters, in the order a saved index stores them.
STORED_INTEGERS = tuple(f.name for f in fields(IndexParameters) if f.name not in SAVED_APART)
_FIRST_PARAMS = 8  # files written before the later parameters existed: their defaults apply
#: Every array a saved index may hold (names without the prefix), for the file that carries it.
STATE_MEMBERS = {
    "format": TEXT, "format_version": INTEGER, "weights": Member("f", 1), "params": Member("iu", 1),
    "key_clip_sigma": NUMBER, "storage": TEXT, "descriptors": Member("f", 2), "keys": Member("i", 2),
    "yaw_keys": Member("f", 3), "refine_keys": Member("i", 2),
}


@dataclass(frozen=True)
class StoredArrays:
    """What an index stores per keyframe, in insertion order."""

    descriptors: np.ndarray  # (n, d) in the storage dtype
    keys: np.ndarray | None  # (n, key_dim) int8; None: to be recomputed (older construction)
    yaw_keys: np.ndarray  # (n, S, yaw_dim) float32
    refine_keys: np.ndarray | None  # (n, refine_dim) int8; None as for keys


def state_arrays(parameters: IndexParameters, weights: np.ndarray, stored: StoredArrays,
                 prefix: str) -> dict[str, np.ndarray]:
    """The arrays of a saved index, each name starting with ``prefix``."""
    return {
        f"{prefix}format": np.array(INDEX_FORMAT),
        f"{prefix}format_version": np.array(INDEX_FORMAT_VERSION, np.int64),
        f"{prefix}weights": weights.copy(),
        f"{prefix}params": np.array([int(getattr(parameters, name)) for name in STORED_INTEGERS],
                                    np.int64),
        f"{prefix}key_clip_sigma": np.array(parameters.key_clip_sigma, np.float64),
        f"{prefix}storage": np.array(parameters.storage),
        f"{prefix}descriptors": np.array(stored.descriptors),
        f"{prefix}keys": stored.keys,
        f"{prefix}yaw_keys": stored.yaw_keys,
        f"{prefix}refine_keys": stored.refine_keys,
    }


def read_parameters(arrays: Mapping[str, np.ndarray],
                    prefix: str) -> tuple[IndexParameters, np.ndarray]:
    """The saved parameters (as given, not resolved) and weights; ``ValueError`` names the problem."""
    get = _getter(arrays, prefix)
    if get("format").shape != () or str(get("format")) != INDEX_FORMAT:
        raise ValueError(f"not a keyframe index state (format tag '{INDEX_FORMAT}' missing)")
    rekey = _version(get) in _REKEYED_VERSIONS
    params = get("params")
    if (params.ndim != 1 or not _FIRST_PARAMS <= len(params) <= len(STORED_INTEGERS)
            or params.dtype.kind not in "iu"):
        raise ValueError(f"index params have shape {params.shape}, expected "
                         f"({len(STORED_INTEGERS)},) integers")
    options: dict[str, Any] = {name: int(value) for name, value in zip(STORED_INTEGERS, params)}
    options["yaw_refine"] = bool(options["yaw_refine"])
    weights = get("weights")
    if rekey:
        _take_todays_key_sizes(options, len(weights) // max(options["sectors"], 1))
    if _version(get) != 2:  # version 2's clip was in int8 steps: it takes today's default
        options["key_clip_sigma"] = float(get("key_clip_sigma"))
    return IndexParameters(storage=str(get("storage")), **options), weights


def _take_todays_key_sizes(options: dict[str, Any], width: int) -> None:
    """Key sizes of an older file that were its defaults (a width of R columns) become today's."""
    key_dim = min(_OLD_KEY_DIM, width)
    refine_dim = min(_OLD_REFINE_DIM, width) if min(_OLD_REFINE_DIM, width) > key_dim else 0
    if options["key_dim"] == key_dim and options.get("refine_dim", refine_dim) == refine_dim:
        options["key_dim"] = options["refine_dim"] = None


def read_arrays(arrays: Mapping[str, np.ndarray], prefix: str, parameters: IndexParameters,
                dimension: int) -> StoredArrays:
    """The saved descriptors and keys, checked against the (resolved) ``parameters``.

    Candidate and refine keys of an older construction come back as ``None``.
    """
    get = _getter(arrays, prefix)
    p = parameters
    descriptors = get("descriptors")
    n = len(descriptors)
    if descriptors.shape != (n, dimension) or descriptors.dtype != np.dtype(p.storage):
        raise ValueError(f"descriptors have shape {descriptors.shape} {descriptors.dtype}, "
                         f"expected ({n}, {dimension}) {p.storage}")
    if not np.all(np.isfinite(descriptors)):
        raise ValueError("descriptors contain NaN or inf")
    keys = refine = None
    yaw = get("yaw_keys")
    if _version(get) not in _REKEYED_VERSIONS:
        keys, refine = get("keys"), get("refine_keys")
        if refine.shape != (n, p.refine_dim) or refine.dtype != np.int8:
            raise ValueError(f"refine keys have shape {refine.shape} {refine.dtype}, "
                             f"expected ({n}, {p.refine_dim}) int8")
        if keys.shape != (n, p.key_dim) or keys.dtype != np.int8:
            raise ValueError(f"keys have shape {keys.shape} {keys.dtype}, "
                             f"expected ({n}, {p.key_dim}) int8")
    if yaw.shape != (n, p.sectors, p.yaw_dim) or yaw.dtype != np.float32:
        raise ValueError(f"yaw keys have shape {yaw.shape} {yaw.dtype}, "
                         f"expected ({n}, {p.sectors}, {p.yaw_dim}) float32")
    return StoredArrays(descriptors, keys, yaw, refine)


def _getter(arrays: Mapping[str, np.ndarray], prefix: str):
    def get(name: str) -> np.ndarray:
        if f"{prefix}{name}" not in arrays:
            raise ValueError(f"keyframe index state lacks '{prefix}{name}'")
        return np.asarray(arrays[f"{prefix}{name}"])

    return get


def _version(get) -> int:
    version = get("format_version")
    readable = (INDEX_FORMAT_VERSION, *_REKEYED_VERSIONS)
    if version.shape != () or version.dtype.kind not in "iu" or int(version) not in readable:
        raise ValueError(f"keyframe index state version {version}; this code reads {readable}")
    return int(version)
