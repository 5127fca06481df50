"""The DDS transport of the processes that carry clouds: a shared-memory segment a whole cloud fits in.

Measured on one host (a best-effort publisher of 120k-point clouds, 1.9 MB each,
100 messages, Fast DDS as Jazzy ships it): with the default transports 4 of 100
arrived at 10 Hz and none at 2 Hz (the cloud does not fit the 512 KB
shared-memory segment, goes over UDP in fragments and any lost fragment loses
it); with the subscriber alone on a 16 MB segment, 10; with publisher and
subscriber on it, 100 of 100 at 20 Hz. So ``vbrl_node`` and ``vbrl replay`` use
``vbrl_ros/data/fastdds_large_data.xml`` unless the user chose a profile file
or another RMW, and a LiDAR driver on the same host needs it too
(``FASTRTPS_DEFAULT_PROFILES_FILE`` pointing at that file).
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

LARGE_DATA_PROFILE = Path(__file__).resolve().parents[1] / "data" / "fastdds_large_data.xml"
#: Variables naming a Fast DDS profile file: a user's choice is left alone.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_large_data_profile(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Point Fast DDS at the large-data profile before rclpy starts; False when the user chose otherwise."""
    if environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return False
    if any(environ.get(name) for name in PROFILE_VARIABLES):
        return False
    environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(LARGE_DATA_PROFILE)
    return True
