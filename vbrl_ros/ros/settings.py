"""The node's parameters: names, defaults, meanings, validation. No ROS import.

The ROS parameters are flat: the node's own settings and, in their place in
the list, the detector's (:class:`~vbrl_ros.detection.settings.DetectorSettings`,
all but ``session``, which the node derives from ``session_id``).
:data:`DESCRIPTIONS` is the one place a parameter's meaning is written: the
node's ``--help``, its ROS parameter descriptors and ``config/vbrl.yaml``
(:func:`parameter_file`; regenerate with ``python -m vbrl_ros.ros.settings``)
all read it, and ``test/ros/test_settings.py`` keeps the file in step.
"""

from __future__ import annotations

import array
import difflib
import json
import math
import textwrap
from dataclasses import dataclass, field, fields
from typing import Any

from vbrl_ros.detection.settings import DetectorSettings, SettingsError
from vbrl_ros.index.parameters import IndexParameters

#: Seconds between diagnostics: at most 10 a second (each also carries every keyframe's marker), at least hourly.
DIAGNOSTICS_PERIOD_S = (0.1, 3600.0)

#: The node parameters that set the keyframe index's search: ``index_X`` is IndexParameters' ``X``.
INDEX_PARAMETERS = ("index_candidates", "index_refine_dim", "index_bound_shifts")

#: The detector's settings that are node parameters, by the same names.
DETECTOR_PARAMETERS = tuple(f.name for f in fields(DetectorSettings) if f.name != "session")


#: What each parameter means, in a sentence or two a user reads in ``vbrl_node --help``.
DESCRIPTIONS: dict[str, str] = {
    "cloud_topic": "sensor_msgs/PointCloud2 topic of the LiDAR scans (subscribed with sensor-data QoS).",
    "odom_topic": "nav_msgs/Odometry topic; with it a keyframe comes every keyframe_distance metres of "
                  "travel. Empty: no odometry, a keyframe every keyframe_interval seconds.",
    "model_path": "VBRL model file (.npz, written by vbrl train). Empty: the package's built-in model.",
    "database_path": "keyframe database file (.npz): loaded at start if it exists, saved every save_every "
                     "keyframes and at shutdown; the start checks that it can be written. Empty: keyframes "
                     "are not kept across restarts.",
    "session_id": "session number of this run's keyframes: one odometry frame (a restart of odometry is a new "
                  "session). -1: one more than the largest in the database.",
    "keyframe_distance": "metres of odometry travel between keyframes (with odom_topic).",
    "keyframe_interval": "seconds between keyframes (without odometry).",
    "level_from_odometry": "level each scan by odometry's roll and pitch instead of by its own ground; the "
                           "ground still sets the height.",
    "odometry_lidar_pose": "the LiDAR frame's pose in the frame odometry moves (its child_frame_id, a robot's "
                           "base_link, say): [x, y, z, roll, pitch, yaw] in metres and radians, as a URDF "
                           "joint's origin. Submaps and level_from_odometry then follow the LiDAR. All zero: "
                           "odometry moves the LiDAR frame itself.",
    "distance_threshold": "accept a candidate whose distance is <= this (lower = more similar). "
                          "0: with verify, every one of the top_k is verified; without, the "
                          "model's own calibrated threshold.",
    "exclude_recent_s": "same-session keyframes younger than this many seconds are not candidates.",
    "top_k": "candidates scored, and at most verified, per keyframe.",
    "max_closures": "accepted loop closures published per keyframe.",
    "verify": "check each candidate by KISS-ICP registration of the two clouds.",
    "min_fitness": "verified closures whose fitness (the share of each cloud's structure within 0.3 "
                   "voxels of the other after registration, the smaller) is below this are rejected "
                   "(0 to 1).",
    "corroborated_fitness": "a verified closure whose fitness is below min_fitness but at least this is "
                            "accepted when two of the three keyframes before it were registered, at least "
                            "this well, to the same session and there agree with it: where each "
                            "registration puts the sensor lies within the distance odometry moved between "
                            "them, plus 1 m (a sparse sensor's right closures along a stretch); in its own "
                            "session it must also lie where odometry allows (1 m plus odometry_drift "
                            "times the path since the match). >= min_fitness: off; without odometry it "
                            "never applies.",
    "max_closure_distance": "verified closures between sensors farther apart than this many metres "
                            "are rejected: the registration may be right, but they are not one place.",
    "verification_voxel": "voxel size in metres of the stored clouds and of their registration, 0.05 to 10.",
    "translation_search": "metres between the extra viewpoints a query is also described from. 0: off; "
                          "-1: the model's own (1.5 for the built-in model).",
    "sequence_length": "keyframes a candidate is scored over: this one and the ones before it, against the "
                       "candidate's neighbours driven either way (with odometry, the stored keyframes where "
                       "the query was then). 1: this keyframe alone (keyframes that do not follow each other "
                       "along a path).",
    "fill_blind_wedges": "where the model does (the built-in one: yes), describe a keyframe with a blind "
                         "wedge (a mast, the robot's body) all round as well where the keyframes of the "
                         "last 60 m saw into it, and compare it all round with the keyframes described so and "
                         "those that saw all round by themselves. "
                         "false: only with the wedge and its mirror image hidden, which costs about half "
                         "the time such a keyframe takes to describe and store.",
    "submap_keyframes": "neighbouring keyframes merged into each verified cloud by odometry poses (the "
                        "query's past, a stored keyframe's both sides): sparse scans then register as small "
                        "local maps. 0: single scans; without odometry, single scans too.",
    "odometry_drift": "share of the path driven between two keyframes of one session (session_id) that "
                      "odometry may have drifted: a candidate odometry places farther from the keyframe than "
                      "max_closure_distance + 5 m + this share of that path is rejected without being "
                      "registered (a repeated building, a second identical corridor), and the next "
                      "candidates take its place among the top_k verified; the others are registered only "
                      "at headings within 45 degrees of odometry's (a symmetric courtyard or crossing turned "
                      "by a quarter is not the place). 0: off; without odometry, and between keyframes of "
                      "different sessions, it never applies.",
    "save_every": "keyframes between database saves. 0: only at shutdown or on ~/save_database.",
    "weight_prune": "descriptor rows weighing less than this times the largest row weight are neither "
                    "stored nor scored (learned sparsity; 0.0001 drops about 13 % of the built-in "
                    "model's rows, 0.003 % of its weight).",
    "descriptor_storage": "float32, or float16: half the memory per keyframe.",
    "index_candidates": "keyframes the index's key scan keeps per query for the exact distance; more find "
                        "more true matches in a large database and cost ~6 us each. -1: the default for "
                        "the model (1024 on the polar grid, 512 on the Cartesian).",
    "index_refine_dim": "entries of the index's finer key that re-ranks the key scan's pool; 0: none. "
                        "-1: the default for the model (512, or none when the scan key is as fine).",
    "index_bound_shifts": "sector shifts (polar grid) among which the index picks, by a coarse bound, the "
                          "ones it scores exactly; fewer are faster and lose more matches. -1: every "
                          "shift. The three index_ parameters apply to a new database; a saved one keeps "
                          "its own.",
    "loop_closure_topic": "std_msgs/Float64MultiArray topic of the accepted closures, one row each, "
                          "columns named in the message's layout.",
    "lio_sam_topic": "std_msgs/Float64MultiArray topic of each closure as LIO-SAM reads it: "
                     "[query stamp, match stamp].",
    "markers_topic": "visualization_msgs/MarkerArray topic of the keyframes and closures, for RViz.",
    "map_frame": "frame id of the markers.",
    "diagnostics_period": "seconds between /diagnostics status messages and marker updates, 0.1 to 3600.",
}


@dataclass(frozen=True)
class NodeSettings:
    """The node's settings; :data:`DESCRIPTIONS` says what each parameter means."""

    cloud_topic: str = "/points"
    odom_topic: str = ""
    model_path: str = ""
    database_path: str = ""
    session_id: int = -1
    keyframe_distance: float = 1.0
    keyframe_interval: float = 1.0
    level_from_odometry: bool = False
    odometry_lidar_pose: tuple[float, ...] = (0.0,) * 6
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    save_every: int = 50
    weight_prune: float = 0.0001
    descriptor_storage: str = "float32"
    index_candidates: int = -1
    index_refine_dim: int = -1
    index_bound_shifts: int = -1
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
            else:  # a ROS array parameter, as a parameter file or rclpy gives it
                value = getattr(default, f.name)
                out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def names(cls) -> list[str]:
        return list(cls.defaults())

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> "NodeSettings":
        """Build from parameter values, checking types and ranges; errors name the parameter."""
        default = cls()
        kinds = {f.name: type(getattr(default, f.name)) for f in fields(cls) if f.name != "detector"}
        kinds.update({name: type(getattr(default.detector, name)) for name in DETECTOR_PARAMETERS})
        clean: dict[str, Any] = {}
        for name, value in values.items():
            if name not in kinds:
                raise SettingsError(unknown_parameters([name]))
            kind = kinds[name]
            if kind is tuple:
                clean[name] = pose_values(name, value)
                continue
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
        for name in ("keyframe_distance", "keyframe_interval"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SettingsError(f"parameter '{name}' must be a positive number, got {value}")
        low, high = DIAGNOSTICS_PERIOD_S
        if not low <= self.diagnostics_period <= high:  # NaN fails too
            raise SettingsError(f"parameter 'diagnostics_period' must be in [{low}, {high}] seconds, "
                                f"got {self.diagnostics_period}")
        if not (math.isfinite(self.weight_prune) and 0.0 <= self.weight_prune < 1.0):
            raise SettingsError(f"parameter 'weight_prune' must be in [0, 1), got {self.weight_prune}")
        try:
            IndexParameters(storage=self.descriptor_storage)
        except ValueError as error:
            raise SettingsError(f"parameter 'descriptor_storage': {error}") from None
        for name in INDEX_PARAMETERS:  # the upper bounds depend on the model: checked when it is loaded
            if getattr(self, name) < -1:
                raise SettingsError(f"parameter '{name}' must be -1 (the default) or >= 0, "
                                    f"got {getattr(self, name)}")
        if self.save_every < 0:
            raise SettingsError(f"parameter 'save_every' must be >= 0, got {self.save_every}")
        if self.session_id < -1:
            raise SettingsError(f"parameter 'session_id' must be >= 0 (or -1 for auto), got {self.session_id}")
        if not self.cloud_topic:
            raise SettingsError("parameter 'cloud_topic' must not be empty")


def pose_values(name: str, value: Any) -> tuple[float, ...]:
    """Six finite numbers ``[x, y, z, roll, pitch, yaw]`` from a parameter value (a ROS double or
    integer array arrives as a list or an ``array.array``)."""
    numbers = list(value) if isinstance(value, (list, tuple, array.array)) else None
    if (numbers is None or len(numbers) != 6
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers)):
        raise SettingsError(f"parameter '{name}' must be six finite numbers [x, y, z, roll, pitch, yaw], "
                            f"got {value!r}")
    return tuple(float(v) for v in numbers)


def index_parameters(settings: NodeSettings) -> IndexParameters:
    """The keyframe index's parameters the node's settings give (-1: the model's default, None)."""
    chosen = {name.removeprefix("index_"): getattr(settings, name) for name in INDEX_PARAMETERS}
    return IndexParameters(storage=settings.descriptor_storage,
                           **{name: None if value == -1 else value for name, value in chosen.items()})


def unknown_parameters(names: list[str]) -> str:
    """One line naming parameters the node does not have, each with the closest one it has.

    rclpy drops an override nobody declared without a word, so a misspelled
    ``cloud_topics`` would leave the node listening on the default topic.
    """
    known = NodeSettings.names()
    described = []
    for name in names:
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        described.append(f"'{name}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
    noun = "parameter" if len(names) == 1 else "parameters"
    return f"unknown {noun} {', '.join(described)}; vbrl_node --help lists them"


def yaml_value(value: Any) -> str:
    """A default as it is written in a parameter file or after ``-p name:=``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return value if value and value[0] not in "\"'{[&*!|>%@`#" else json.dumps(value)
    return repr(value)


def parameter_file() -> str:
    """``config/vbrl.yaml``: every parameter at its default, its description above it."""
    lines = [
        "# vbrl_node parameters (ROS 2 parameter-file format), every one at its default.",
        "#   vbrl_node --ros-args --params-file config/vbrl.yaml",
        "# Every value is checked at start: a bad value or an unknown name stops the node",
        "# with a message naming it. Generated from vbrl_ros/ros/settings.py",
        "# (python -m vbrl_ros.ros.settings > config/vbrl.yaml); edit the meanings there.",
        "/**:",
        "  ros__parameters:",
    ]
    for name, default in NodeSettings.defaults().items():
        # "\0": never break a line between a number and its unit
        text = DESCRIPTIONS[name].replace(" %", "\0%")
        lines += [line.replace("\0", " ")
                  for line in textwrap.wrap(text, 96, initial_indent="    # ", subsequent_indent="    # ")]
        lines.append(f"    {name}: {yaml_value(default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(parameter_file(), end="")
