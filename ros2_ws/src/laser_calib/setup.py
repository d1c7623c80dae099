from setuptools import find_packages, setup

package_name = "laser_calib"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="laser-calib developers",
    maintainer_email="dev@laser-calib.local",
    description="ROS-free core of laser-based kinematic calibration.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={"console_scripts": ["laser-calib = laser_calib.cli.main:main"]},
)
