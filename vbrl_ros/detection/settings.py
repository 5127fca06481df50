"""What the loop-closure detector accepts, verifies and publishes per keyframe; every value checked.

The node's parameters contain these settings (:mod:`vbrl_ros.ros.settings`);
offline tools build them directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from vbrl_ros.index.sequence_matching import DEFAULT_LENGTH


#: Verification voxel bounds: finer stores every point and no two scans' points lie that close (every
#: closure would fail); coarser than 10 m leaves too few points to register.
VOXEL_M = (0.05, 10.0)


class SettingsError(ValueError):
    """A setting the detector or the node cannot start with; the message names it."""


@dataclass(frozen=True)
class DetectorSettings:
    """Policy of :class:`~vbrl_ros.detection.detector.LoopClosureDetector`."""

    session: str = "default"
    distance_threshold: float = 0.0  # accept Eq. 4 distance <= this; 0: any with verify, else the model's own
    exclude_recent_s: float = 30.0  # same-session keyframes younger than this are not candidates
    top_k: int = 3  # candidates scored (and at most verified) per keyframe
    max_closures: int = 1  # accepted closures published per keyframe
    verify: bool = True  # KISS-ICP registration of each candidate
    min_fitness: float = 0.2  # verified closures whose structure overlap is below this are rejected
    # a closure below min_fitness but at least this is accepted when two of the three keyframes before
    # registered to the same place, agreeing with it (detection.corroboration); >= min_fitness: off.
    # Another sensor's or a thinned robot's right registrations overlap .12-.2; at .10 a lookalike
    # passed three in a row (design 6.1 item 12)
    corroborated_fitness: float = 0.12
    max_closure_distance: float = 5.0  # metres; verified closures between sensors farther apart are rejected
    verification_voxel: float = 1.0  # metres; stored clouds and registration use this voxel
    translation_search: float = -1.0  # metres between query viewpoints; 0: none; -1: the model's
    sequence_length: int = DEFAULT_LENGTH  # keyframes a candidate is scored over; 1: this one alone
    # describe a partly blind keyframe all round as well where the model does (features.fill_blind_wedges)
    fill_blind_wedges: bool = True
    submap_keyframes: int = 2  # neighbours merged into each verified cloud by odometry; 0: single scans
    # share of the path between two same-session keyframes odometry may drift; a candidate odometry
    # places farther than that (plus max_closure_distance and 5 m) is rejected unverified; 0: off
    odometry_drift: float = 0.1

    def __post_init__(self) -> None:
        rules = {
            "session": (bool(self.session) and isinstance(self.session, str), "a non-empty string"),
            "distance_threshold": (_at_least(self.distance_threshold, 0), ">= 0"),
            "exclude_recent_s": (_at_least(self.exclude_recent_s, 0), ">= 0"),
            "top_k": (isinstance(self.top_k, int) and self.top_k >= 1, ">= 1"),
            "max_closures": (isinstance(self.max_closures, int) and self.max_closures >= 1, ">= 1"),
            "min_fitness": (0.0 <= self.min_fitness <= 1.0, "in [0, 1]"),
            "corroborated_fitness": (0.0 <= self.corroborated_fitness <= 1.0, "in [0, 1] (>= min_fitness: off)"),
            "max_closure_distance": (_at_least(self.max_closure_distance, 0) and self.max_closure_distance > 0,
                                     "a positive number of metres"),
            "verification_voxel": (_at_least(self.verification_voxel, VOXEL_M[0])
                                   and self.verification_voxel <= VOXEL_M[1], f"in [{VOXEL_M[0]}, {VOXEL_M[1]}] m"),
            "translation_search": (self.translation_search == -1 or (_at_least(self.translation_search, 0)
                                                                      and self.translation_search <= 10),
                                   "-1 (the model's), 0 (off) or a step in (0, 10] metres"),
            "sequence_length": (isinstance(self.sequence_length, int) and 1 <= self.sequence_length <= 20,
                                "an integer in [1, 20]"),
            "fill_blind_wedges": (isinstance(self.fill_blind_wedges, bool), "true or false"),
            "submap_keyframes": (isinstance(self.submap_keyframes, int) and 0 <= self.submap_keyframes <= 10,
                                 "an integer in [0, 10]"),
            "odometry_drift": (_at_least(self.odometry_drift, 0) and self.odometry_drift <= 1,
                               "a share of the path in [0, 1] (0: off)"),
        }
        for name, (ok, rule) in rules.items():
            if not ok:
                raise SettingsError(f"'{name}' must be {rule}, got {getattr(self, name)!r}")


def _at_least(value: float, low: float) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value >= low
