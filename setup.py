"""ament_python package brepose_ros: builds with colcon and installs with pip.

Extras: ``[ros]`` the ROS 2 PyPI wheels (optional, so that a user with an apt ROS install
never gets a second rclpy); ``[compile]`` the CAD stack (cadquery/OCP with VTK, about 2 GB)
and plotting, needed only to compile aspect graphs, render scenes and evaluate. A robot that
runs the node on precompiled graphs needs neither the CAD stack nor matplotlib:
``pip install '.[ros]'`` (docs/ros.md).
"""
import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "brepose_ros"
#: the one place the version is written is brepose_ros/__init__.py (read, not imported: setup
#: runs before the dependencies are installed); test_version.py checks package.xml agrees
VERSION = re.search(r'^__version__ = "([^"]+)"', (Path(__file__).parent / PACKAGE / "__init__.py").read_text(),
                    re.MULTILINE).group(1)

setup(
    name=PACKAGE,
    version=VERSION,
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    # the confidence's calibration, read by the core from inside the package (online/confidence.py)
    package_data={PACKAGE: ["confidence.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "opencv-python-headless>=4.8,<5",
        "rosbags>=0.10",
        "pyyaml>=6",
        "tqdm>=4.60",
        "numba>=0.58",  # nogil kernels of the online path (online/kernels.py, docs/DECISIONS.md)
    ],
    extras_require={
        "ros": [
            "ros-kilted-rclpy",
            "ros-kilted-rmw-fastrtps-cpp",
            "ros-kilted-sensor-msgs",
            "ros-kilted-geometry-msgs",
            "ros-kilted-diagnostic-msgs",
            "ros-kilted-visualization-msgs",
        ],
        "compile": ["cadquery>=2.4", "trimesh>=4", "matplotlib>=3.7"],
        # brepose-learn's search (docs/DECISIONS.md); it also needs [compile] for its scenes
        "learn": ["optuna>=3.4"],
        "test": ["pytest>=7"],
    },
    zip_safe=True,
    maintainer="brepose_ros developers",
    maintainer_email="dev@brepose.invalid",
    description="6-DoF pose of texture-less parts from a STEP model and one image (ROS 2 node).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "brepose-compile = brepose_ros.cli.compile:main",
            "brepose-render = brepose_ros.cli.render:main",
            "brepose-bag = brepose_ros.cli.bag:main",
            "brepose-estimate = brepose_ros.cli.estimate:main",
            "brepose-eval = brepose_ros.cli.evaluate:main",
            "brepose-threshold = brepose_ros.cli.threshold:main",
            "brepose-learn = brepose_ros.cli.learn:main",
            "estimator = brepose_ros.ros.node:main",
        ],
    },
)
