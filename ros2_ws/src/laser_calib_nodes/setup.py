from glob import glob

from setuptools import find_packages, setup

package_name = "laser_calib_nodes"
# The node executables: links to bin/node, which runs laser_calib_nodes.<name>.main (not
# console_scripts: its wrapper imports importlib.metadata before any line of ours can take a Ctrl-C).
executables = ("arm_driver", "camera_sim", "spot_detector", "sequencer", "estimator", "replay")

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("lib/" + package_name, [f"bin/{name}" for name in executables]),
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
)
