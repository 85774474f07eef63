"""ament_python package that is also pip-installable (see setup.cfg)."""
from glob import glob

from setuptools import setup

PACKAGE = "maem_ros"

setup(
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/config/rigs", glob("config/rigs/*.yaml")),
    ],
)
