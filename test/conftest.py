"""Test-session isolation: a private ROS_DOMAIN_ID and localhost-only discovery.

Set before any test imports rclpy so every node (in-process or subprocess, which
inherits the environment) of this session lives in its own DDS domain.
MAEM_TEST_DOMAIN_ID picks the domain instead of chance, for concurrent sessions on one
machine that must not hear each other.
"""
import os
import random

os.environ["ROS_DOMAIN_ID"] = os.environ.get("MAEM_TEST_DOMAIN_ID") or str(
    random.SystemRandom().randint(1, 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
