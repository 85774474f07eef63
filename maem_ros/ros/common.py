"""Transitional: the names tools/live.py, latency.py and soak.py still import from here.

ros/common.py was split by concern into qos, params, diagnostics, intake, process, rig_tf (and
cli for ``--help``); this module goes once those tools import from the new homes.
"""
from maem_ros.ros.params import load_rig_param
from maem_ros.ros.process import DDS_PROFILE_VARS, keep_freed_memory, use_shipped_dds_profile
from maem_ros.ros.qos import DATA_QOS

__all__ = ["DATA_QOS", "DDS_PROFILE_VARS", "keep_freed_memory", "load_rig_param",
           "use_shipped_dds_profile"]
