"""Named descriptors ``vbrl train --descriptor`` offers: the paper's and the recognition one.

The recognition descriptor is what the built-in model uses (docs/design.md §6): scans
levelled on their own ground, the height and spectrum modalities on a 20 ring x 30 sector
polar grid (2 m x 12 degrees, 40 m), each modality's block normalised to unit L1, the
mirror image of any wedge the sensor did not see hidden, of a tilted sensor only what it would
also see turned half a turn, returns from rain or snow near the
sensor left out, each keyframe described with the keyframes of the last 3 m merged in by
odometry (its trail, when poses are known; of a forward-looking sensor, the keyframes of the last
60 m that looked at where it stands; of a partly blind one, also all round where those fill its
wedge), and queries also described from viewpoints
1.5 m around the sensor (translation search).
"""

from __future__ import annotations

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig

DESCRIPTORS = ("paper", "recognition")
RECOGNITION_GRID = dict(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0),
                        frame="ground")
RECOGNITION_FEATURES = FeatureConfig(modalities=("height", "spectrum"), min_points=1, normalise=True,
                                     mirror_blind_wedges=True, mirror_field_of_view=True,
                                     drop_weather_clutter=True, trail_m=3.0,
                                     forward_trail_m=60.0, fill_blind_wedges=True, trail_ahead_m=3.0)
RECOGNITION_TRANSLATION_SEARCH_M = 1.5


def recognition_config(**polar: float) -> VBRLConfig:
    """The recognition descriptor, with ``rings``/``sectors``/``max_range`` overridden."""
    return VBRLConfig(grid=VoxelGridConfig(**{**RECOGNITION_GRID, **polar}), features=RECOGNITION_FEATURES)
