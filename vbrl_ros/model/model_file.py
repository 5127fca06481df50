"""The VBRL model file: one versioned ``.npz`` holding everything needed to score.

Loaded with ``allow_pickle=False`` only: a model file is data, never code.
Keys (all plain arrays or JSON strings):

==================  =============================================================
``format``          ``"vbrl_ros.model"`` (tells a foreign ``.npz`` apart)
``format_version``  integer, currently 1
``config_json``     the :class:`~vbrl_ros.config.VBRLConfig` as JSON
``W``               (d, c) learned weights, rows laid out as ``features.FeatureLayout``
``feature_mean``    (d,) standardisation offset of the raw descriptor
``feature_scale``   (d,) standardisation divisor (1 where a feature never varied)
``lambda1/2``       the regularisation weights W was trained with
``w_modality``      (m,) modality importances, sum 1 (paper Fig. 4a)
``w_voxel``         voxel importances, sum 1 (paper Fig. 4b): one per voxel of a
                    Cartesian grid, one per (layer, ring) column of a polar grid
                    (tied across sectors, ``FeatureLayout.weight_layout``)
``scenarios_json``  the c scenario names, column order of W
``metadata_json``   free-form training facts (scan count, objective, sources, ...)
==================  =============================================================
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vbrl_ros.config import VBRLConfig
from vbrl_ros.features.featurizer import Featurizer, FeatureLayout
from vbrl_ros.io.atomic import atomic_write
from vbrl_ros.io.npz import INTEGER, NUMBER, TEXT, Member, one_line, read_npz
from vbrl_ros.model.scoring import WeightedL1Scorer, importance_weights, row_weights

MODEL_FORMAT = "vbrl_ros.model"
MODEL_FORMAT_VERSION = 1
#: Acceptance threshold of a model trained without one (no poses, or streamed)
UNCALIBRATED_DISTANCE_THRESHOLD = 0.5
_ARRAY_KEYS = ("W", "feature_mean", "feature_scale", "w_modality", "w_voxel")
#: Every member a model file may hold; others are never read.
MODEL_MEMBERS = {
    "format": TEXT, "format_version": INTEGER, "config_json": TEXT, "scenarios_json": TEXT,
    "metadata_json": TEXT, "lambda1": NUMBER, "lambda2": NUMBER, "W": Member("f", 2),
    "feature_mean": Member("f", 1), "feature_scale": Member("f", 1), "w_modality": Member("f", 1),
    "w_voxel": Member("f", 1),
}
#: Metadata the detector reads, and the range each must be in when a file gives it.
METADATA_NUMBERS = {"distance_threshold": (0.0, math.inf), "translation_search": (0.0, 10.0)}


class ModelFileError(ValueError):
    """A model file that cannot be used; the message is one line naming the problem."""


@dataclass
class VBRLModel:
    config: VBRLConfig
    W: np.ndarray
    feature_mean: np.ndarray
    feature_scale: np.ndarray
    lambda1: float
    lambda2: float
    scenarios: list[str]
    w_modality: np.ndarray = field(default=None)  # type: ignore[assignment]
    w_voxel: np.ndarray = field(default=None)  # type: ignore[assignment]
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.layout: FeatureLayout = Featurizer(self.config).layout
        d = self.layout.dimension
        self.W = np.asarray(self.W, dtype=np.float64)
        if self.W.ndim != 2 or self.W.shape[0] != d:
            raise ModelFileError(f"W has shape {self.W.shape}, the configuration needs ({d}, c)")
        if len(self.scenarios) != self.W.shape[1]:
            raise ModelFileError(
                f"{len(self.scenarios)} scenario names for {self.W.shape[1]} columns of W"
            )
        if self.w_modality is None or self.w_voxel is None:
            self.w_modality, self.w_voxel = importance_weights(self.W, self.layout.weight_layout)
        expected = {
            "feature_mean": (d,),
            "feature_scale": (d,),
            "w_modality": (self.layout.n_modalities,),
            "w_voxel": (self.layout.weight_layout.n_voxels,),
        }
        for name, shape in expected.items():
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ModelFileError(f"{name} has shape {value.shape}, expected {shape}")
            setattr(self, name, value)
        for name in _ARRAY_KEYS:
            if not np.all(np.isfinite(getattr(self, name))):
                raise ModelFileError(f"{name} contains NaN or inf")
        if np.any(self.feature_scale <= 0):
            raise ModelFileError("feature_scale must be positive")
        for name in ("w_modality", "w_voxel"):
            weights = getattr(self, name)
            if np.any(weights < 0) or not weights.sum() > 0:
                raise ModelFileError(f"{name} must be non-negative importances with a positive sum")

    # -- using the model ---------------------------------------------------

    def standardize(self, descriptors: np.ndarray) -> np.ndarray:
        """Raw descriptors (d,) or (N, d) -> standardised float32, as W was trained on."""
        out = (np.asarray(descriptors, dtype=np.float64) - self.feature_mean) / self.feature_scale
        return out.astype(np.float32)

    def row_weights(self) -> np.ndarray:
        """wM * wV per descriptor row; on a polar grid equal across the sectors of a column."""
        return row_weights(self.w_modality, self.w_voxel, self.layout.weight_layout)

    def scorer(self, prune: float = 0.0) -> WeightedL1Scorer:
        """Eq. 4 scorer with this model's importances (lower distance = more similar)."""
        # polar grid: distances minimised over sector shifts (a yaw comes with them)
        sector_rows = self.layout.sector_rows if self.layout.sectors > 1 else None
        return WeightedL1Scorer(self.row_weights(), prune=prune, sector_rows=sector_rows)

    def featurizer(self) -> Featurizer:
        return Featurizer(self.config)

    def distance_threshold(self) -> float:
        """Accept Eq. 4 distances <= this: the threshold calibrated in training
        (``metadata["distance_threshold"]``), else :data:`UNCALIBRATED_DISTANCE_THRESHOLD`."""
        return float(self.metadata.get("distance_threshold", UNCALIBRATED_DISTANCE_THRESHOLD))

    def translation_search(self) -> float:
        """Step in metres of the viewpoints a query is also described from (0 = none):
        ``metadata["translation_search"]``, which models trained for it record."""
        return float(self.metadata.get("translation_search", 0.0))

    def identity(self) -> str:
        """Content hash of everything that decides a descriptor's meaning and its score.

        A keyframe database stores standardised descriptors; it is only valid
        with the exact model that produced them, whatever its file name.
        """
        digest = hashlib.sha256(json.dumps(self.config.to_dict(), sort_keys=True).encode())
        for name in _ARRAY_KEYS:
            digest.update(np.ascontiguousarray(getattr(self, name), dtype=np.float64).tobytes())
        return digest.hexdigest()[:16]

    # -- file I/O -----------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write atomically (temp file + rename); the last good copy survives a crash."""
        arrays = {name: np.asarray(getattr(self, name)) for name in _ARRAY_KEYS}
        payload = dict(
            format=np.array(MODEL_FORMAT),
            format_version=np.array(MODEL_FORMAT_VERSION),
            config_json=np.array(json.dumps(self.config.to_dict())),
            lambda1=np.array(float(self.lambda1)),
            lambda2=np.array(float(self.lambda2)),
            scenarios_json=np.array(json.dumps(list(self.scenarios))),
            metadata_json=np.array(json.dumps(self.metadata, default=str)),
            **arrays,
        )
        return atomic_write(path, lambda handle: np.savez(handle, **payload))


def load_model(path: str | Path, expected_config: VBRLConfig | None = None) -> VBRLModel:
    """Load and validate a model file; any problem raises :class:`ModelFileError`.

    With ``expected_config`` (the running featurizer's), a model trained for
    a different grid or feature configuration is refused instead of silently
    mis-scoring.
    """
    path = Path(path)
    contents = read_npz(path, ModelFileError, "model", MODEL_FORMAT, MODEL_MEMBERS)
    version = int(contents.get("format_version", -1))
    if version != MODEL_FORMAT_VERSION:
        raise ModelFileError(
            f"{path} has model format version {version}; this vbrl_ros reads version "
            f"{MODEL_FORMAT_VERSION}"
        )
    missing = [
        key
        for key in (*_ARRAY_KEYS, "config_json", "lambda1", "lambda2", "scenarios_json")
        if key not in contents
    ]
    if missing:
        raise ModelFileError(f"{path} lacks {', '.join(missing)}")
    try:
        config = VBRLConfig.from_dict(_json(str(contents["config_json"]), "config_json"))
    except (ValueError, TypeError) as error:
        raise ModelFileError(f"{path} has an invalid configuration: {one_line(error)}") from None
    if expected_config is not None and config != expected_config:
        raise ModelFileError(
            f"{path} was trained for another configuration ({'; '.join(config.differences(expected_config))})"
        )
    try:
        return VBRLModel(
            config=config,
            scenarios=_scenarios(str(contents["scenarios_json"])),
            lambda1=float(contents["lambda1"]),
            lambda2=float(contents["lambda2"]),
            metadata=_metadata(str(contents.get("metadata_json", "{}"))),
            **{key: contents[key] for key in _ARRAY_KEYS},
        )
    except ModelFileError as error:
        raise ModelFileError(f"{path}: {error}") from None


def _scenarios(text: str) -> list[str]:
    scenarios = _json(text, "scenarios_json")
    if not isinstance(scenarios, list) or not all(isinstance(name, str) for name in scenarios):
        raise ModelFileError("scenarios_json must be a JSON list of names")
    return scenarios


def _metadata(text: str) -> dict[str, Any]:
    """The training facts; the two the detector reads must be numbers it can use."""
    metadata = _json(text, "metadata_json")
    if not isinstance(metadata, dict):
        raise ModelFileError(f"metadata_json must be a JSON object, got {type(metadata).__name__}")
    for name, (low, high) in METADATA_NUMBERS.items():
        value = metadata.get(name, low)
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and low <= value <= high):
            rule = f">= {low:g}" if high == math.inf else f"in [{low:g}, {high:g}]"
            raise ModelFileError(f"metadata_json: {name} must be a finite number {rule}, got {value!r}")
    return metadata


def _json(text: str, name: str) -> Any:
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as error:  # RecursionError: nested too deeply
        raise ModelFileError(f"{name} is not valid JSON: {one_line(error)}") from None
