"""Build script for vbrl_ros: an ament_python package that also installs with plain pip."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "vbrl_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Online LiDAR loop-closure detection with VBRL for ROS 2 Jazzy",
    license="MIT",
    python_requires=">=3.11",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["data/*.npz", "data/*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=[
        "numpy>=1.26",
        "numba>=0.60",
        "scipy>=1.11",
        "rosbags>=0.10",
        "kiss-icp>=1.0",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "ros-jazzy-rclpy[fastrtps]>=7.1",
        "ros-jazzy-common-interfaces>=5.3",
    ],
    extras_require={
        "test": [
            "pytest>=8",
            "pytest-xdist>=3",
            "pytest-timeout>=2.3",
            "hypothesis>=6",
            "scikit-image>=0.22",
            "pyyaml>=6",
            "colcon-core>=0.15",
            "colcon-ros>=0.4",
        ],
    },
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "vbrl = vbrl_ros.tools.cli:main",
            "vbrl_node = vbrl_ros.ros.node:main",
        ],
    },
)
