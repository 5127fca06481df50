"""The node's parameters: names, defaults, validation. No ROS import.

The ROS parameters are flat: the node's own settings and, in their place in
the list, the detector's (:class:`~vbrl_ros.detection.settings.DetectorSettings`,
all but ``session``, which the node derives from ``session_id``).
``config/vbrl.yaml`` carries the same defaults in ROS 2 parameter-file
format; ``test/ros/test_settings.py`` keeps the two in step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

from vbrl_ros.detection.settings import DetectorSettings, SettingsError
from vbrl_ros.index.parameters import IndexParameters

#: The detector's settings that are node parameters, by the same names.
DETECTOR_PARAMETERS = tuple(f.name for f in fields(DetectorSettings) if f.name != "session")


@dataclass(frozen=True)
class NodeSettings:
    cloud_topic: str = "/points"
    odom_topic: str = ""  # empty: no odometry, keyframes by time
    model_path: str = ""  # empty: the package's built-in default model
    database_path: str = ""  # empty: keyframes are not kept across restarts
    session_id: int = -1  # -1: one more than the largest session in the database
    keyframe_distance: float = 1.0  # metres of travel between keyframes (with odometry)
    keyframe_interval: float = 1.0  # seconds between keyframes (without odometry)
    # level scans by odometry's roll and pitch (its frame must be the LiDAR's) instead of
    # their own ground; the ground still sets the height
    level_from_odometry: bool = False
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    save_every: int = 50  # keyframes between database saves; 0: only on shutdown/service
    # Learned sparsity: descriptor rows weighing < weight_prune x the largest row weight
    # are neither stored nor scored (0.0001: about 13 % of the default model's rows,
    # 0.003 % of its weight).
    weight_prune: float = 0.0001
    descriptor_storage: str = "float32"  # or "float16": half the memory per keyframe
    loop_closure_topic: str = "~/loop_closures"
    lio_sam_topic: str = "/lio_loop/loop_closure_detection"
    markers_topic: str = "~/markers"
    map_frame: str = "map"
    diagnostics_period: float = 1.0

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """Every ROS parameter with its default, in the order of config/vbrl.yaml."""
        default, out = cls(), {}
        for f in fields(cls):
            if f.name == "detector":
                out.update({name: getattr(default.detector, name) for name in DETECTOR_PARAMETERS})
            else:
                out[f.name] = getattr(default, f.name)
        return out

    @classmethod
    def names(cls) -> list[str]:
        return list(cls.defaults())

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> "NodeSettings":
        """Build from parameter values, checking types and ranges; errors name the parameter."""
        kinds = {name: type(default) for name, default in cls.defaults().items()}
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
        detector = {name: clean.pop(name) for name in DETECTOR_PARAMETERS if name in clean}
        try:
            settings = cls(**clean, detector=DetectorSettings(**detector))
        except SettingsError as error:
            raise SettingsError(f"parameter {error}") from None
        settings.validate()
        return settings

    def validate(self) -> None:
        """The node's own values (the detector's check themselves)."""
        for name in ("keyframe_distance", "keyframe_interval", "diagnostics_period"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SettingsError(f"parameter '{name}' must be a positive number, got {value}")
        if not (math.isfinite(self.weight_prune) and 0.0 <= self.weight_prune < 1.0):
            raise SettingsError(f"parameter 'weight_prune' must be in [0, 1), got {self.weight_prune}")
        try:
            IndexParameters(storage=self.descriptor_storage)
        except ValueError as error:
            raise SettingsError(f"parameter 'descriptor_storage': {error}") from None
        if self.save_every < 0:
            raise SettingsError(f"parameter 'save_every' must be >= 0, got {self.save_every}")
        if self.session_id < -1:
            raise SettingsError(f"parameter 'session_id' must be >= 0 (or -1 for auto), got {self.session_id}")
        if not self.cloud_topic:
            raise SettingsError("parameter 'cloud_topic' must not be empty")
