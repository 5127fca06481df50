"""The large-data DDS profile: used unless the user chose a profile file or another RMW, and valid XML."""

from __future__ import annotations

from xml.etree import ElementTree

from vbrl_ros.ros.transport import LARGE_DATA_PROFILE, use_large_data_profile


def test_the_profile_is_used_unless_the_user_chose_otherwise():
    environ: dict[str, str] = {}
    assert use_large_data_profile(environ) and environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(LARGE_DATA_PROFILE)
    for chosen in ({"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}, {"FASTDDS_DEFAULT_PROFILES_FILE": "/x.xml"},
                   {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):
        environ = dict(chosen)
        assert not use_large_data_profile(environ) and environ == chosen


def test_the_profile_gives_a_shared_memory_segment_a_cloud_fits_in():
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ElementTree.parse(LARGE_DATA_PROFILE).getroot()
    shm = [d for d in root.iterfind(".//p:transport_descriptor", ns) if d.findtext("p:type", namespaces=ns) == "SHM"]
    assert int(shm[0].findtext("p:segment_size", namespaces=ns)) >= 8 * 2**20  # a 128-beam cloud is ~4 MB
