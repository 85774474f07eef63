"""Test-session isolation: a private ROS_DOMAIN_ID and localhost-only discovery.

Set before any test imports rclpy so every node (in-process or subprocess, which
inherits the environment) of this session lives in its own DDS domain.
"""
import os
import random

os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
