"""The node's parameters: names, defaults, validation. No ROS import.

``config/vbrl.yaml`` carries the same defaults in ROS 2 parameter-file
format; ``test/ros/test_settings.py`` keeps the two in step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any


class SettingsError(ValueError):
    """A parameter value the node cannot start with; the message names the parameter."""


@dataclass(frozen=True)
class NodeSettings:
    cloud_topic: str = "/points"
    odom_topic: str = ""  # empty: no odometry, keyframes by time
    model_path: str = ""  # empty: the package's built-in default model
    database_path: str = ""  # empty: keyframes are not kept across restarts
    session_id: int = -1  # -1: one more than the largest session in the database
    keyframe_distance: float = 1.0  # metres of travel between keyframes (with odometry)
    keyframe_interval: float = 1.0  # seconds between keyframes (without odometry)
    distance_threshold: float = 0.0  # accept distance <= this (Eq. 4); 0: the model's own
    exclude_recent_s: float = 30.0
    top_k: int = 3  # candidates per keyframe; also bounds the verifications
    max_closures: int = 1
    verify: bool = True
    min_fitness: float = 0.5
    verification_voxel: float = 1.0
    save_every: int = 50  # keyframes between database saves; 0: only on shutdown/service
    # Learned sparsity: descriptor rows weighing < weight_prune x the largest row weight
    # are neither stored nor scored (0.0001 drops 13 % of the default model's rows,
    # 0.003 % of its weight; 0.001 changed 3 of 334 winter top-1 matches of a
    # spikier model, 0.01 lost 17).
    weight_prune: float = 0.0001
    descriptor_storage: str = "float32"  # or "float16": half the memory per keyframe
    loop_closure_topic: str = "~/loop_closures"
    lio_sam_topic: str = "/lio_loop/loop_closure_detection"
    markers_topic: str = "~/markers"
    map_frame: str = "map"
    diagnostics_period: float = 1.0

    @classmethod
    def names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        default = cls()
        return {name: getattr(default, name) for name in cls.names()}

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> "NodeSettings":
        """Build from parameter values, checking types and ranges; errors name the parameter."""
        kinds = {f.name: type(getattr(cls(), f.name)) for f in fields(cls)}
        clean: dict[str, Any] = {}
        for name, value in values.items():
            if name not in kinds:
                raise SettingsError(f"unknown parameter '{name}'")
            kind = kinds[name]
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise SettingsError(
                    f"parameter '{name}' must be {kind.__name__}, got {type(value).__name__} {value!r}"
                )
            clean[name] = value
        settings = cls(**clean)
        settings.validate()
        return settings

    def validate(self) -> None:
        positive = ("keyframe_distance", "keyframe_interval", "verification_voxel", "diagnostics_period")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SettingsError(f"parameter '{name}' must be a positive number, got {value}")
        for name in ("distance_threshold", "exclude_recent_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise SettingsError(f"parameter '{name}' must be >= 0, got {value}")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise SettingsError(f"parameter 'min_fitness' must be in [0, 1], got {self.min_fitness}")
        for name in ("top_k", "max_closures"):
            if getattr(self, name) < 1:
                raise SettingsError(f"parameter '{name}' must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.weight_prune) and 0.0 <= self.weight_prune < 1.0):
            raise SettingsError(f"parameter 'weight_prune' must be in [0, 1), got {self.weight_prune}")
        if self.descriptor_storage not in ("float32", "float16"):
            raise SettingsError(
                f"parameter 'descriptor_storage' must be 'float32' or 'float16', "
                f"got {self.descriptor_storage!r}"
            )
        if self.save_every < 0:
            raise SettingsError(f"parameter 'save_every' must be >= 0, got {self.save_every}")
        if self.session_id < -1:
            raise SettingsError(f"parameter 'session_id' must be >= 0 (or -1 for auto), got {self.session_id}")
        if not self.cloud_topic:
            raise SettingsError("parameter 'cloud_topic' must not be empty")
