"""config/fastdds.xml: well-formed, the transports doc/multi-machine.md describes, used by default."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from maem_ros.ros.process import DDS_PROFILE_VARS, use_shipped_dds_profile

NS = {"d": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds.xml"


def test_profile_has_shm_with_a_large_segment_and_udp_and_no_builtins():
    root = ET.parse(PROFILE).getroot()
    kinds = {t.find("d:transport_id", NS).text: t for t in root.iterfind(".//d:transport_descriptor", NS)}
    assert {k: t.find("d:type", NS).text for k, t in kinds.items()} == {"maem_shm": "SHM",
                                                                        "maem_udp": "UDPv4"}
    assert int(kinds["maem_shm"].find("d:segment_size", NS).text) == 256 * 2**20
    part = root.find(".//d:participant", NS)
    assert part.get("is_default_profile") == "true"
    assert part.find(".//d:useBuiltinTransports", NS).text == "false"
    used = [t.text for t in part.iterfind(".//d:userTransports/d:transport_id", NS)]
    assert used == ["maem_shm", "maem_udp"]


def test_shipped_profile_is_the_default_unless_the_user_chose(monkeypatch):
    for v in DDS_PROFILE_VARS + ("RMW_IMPLEMENTATION",):
        monkeypatch.delenv(v, raising=False)
    assert Path(use_shipped_dds_profile()).resolve() == PROFILE
    import os
    assert Path(os.environ[DDS_PROFILE_VARS[0]]).resolve() == PROFILE
    monkeypatch.setenv(DDS_PROFILE_VARS[0], "/my/profile.xml")
    assert use_shipped_dds_profile() is None and os.environ[DDS_PROFILE_VARS[0]] == "/my/profile.xml"
    monkeypatch.delenv(DDS_PROFILE_VARS[0])
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert use_shipped_dds_profile() is None and DDS_PROFILE_VARS[0] not in os.environ
