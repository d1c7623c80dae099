from glob import glob

from setuptools import find_packages, setup

package_name = "laser_calib_nodes"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        # config is a link to the repository's config/ folder (parameters, robots).
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")),
        ("share/" + package_name + "/config/robots", glob("config/robots/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="laser-calib developers",
    maintainer_email="dev@laser-calib.local",
    description="ROS 2 nodes of laser kinematic calibration.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "arm_driver = laser_calib_nodes.arm_driver:main",
            "camera_sim = laser_calib_nodes.camera_sim:main",
            "spot_detector = laser_calib_nodes.spot_detector:main",
            "sequencer = laser_calib_nodes.sequencer:main",
            "estimator = laser_calib_nodes.estimator:main",
            "replay = laser_calib_nodes.replay:main",
        ],
    },
)
