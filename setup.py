"""magcal_ros: ament_python package, also installable with plain pip."""

import os
import stat
from glob import glob

from setuptools import find_packages, setup

try:
    from setuptools.command.install_data import install_data
except ImportError:  # setuptools < 80: distutils' command (setuptools' own copy)
    from distutils.command.install_data import install_data

PACKAGE = "magcal_ros"
CONSOLE_SCRIPTS = {
    "magcal": "magcal_ros.app.cli:main",
    "correction_node": "magcal_ros.nodes.entry:correction_node",
    "calibration_node": "magcal_ros.nodes.entry:calibration_node",
}
LAUNCHER = """#!/bin/sh
# `ros2 run {package} {name}` looks for <prefix>/lib/{package}/{name}, <prefix> found through the
# ament index. pip installs the console script in <prefix>/bin; this launcher runs it.
exec "$(dirname "$0")/../../bin/{name}" "$@"
"""


def _launchers():
    """Write the lib/<package> launchers into build/ (executable) and return their paths."""
    folder = os.path.join("build", "ros2_run_launchers")
    os.makedirs(folder, exist_ok=True)
    paths = []
    for name in CONSOLE_SCRIPTS:
        path = os.path.join(folder, name)
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(LAUNCHER.format(package=PACKAGE, name=name))
        os.chmod(path, os.stat(path).st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
        paths.append(path)
    return paths


class InstallData(install_data):
    """install_data that adds lib/<package> launchers when the scripts go elsewhere (pip).

    colcon installs the console scripts into lib/<package> itself (setup.cfg, install_scripts),
    where ``ros2 run`` looks; a wheel (pip) puts them in <prefix>/bin, so the launchers
    close the gap. The installed launchers keep their executable bit (pip restores it).
    """

    def finalize_options(self):
        super().finalize_options()
        scripts = os.path.normpath(self.get_finalized_command("install").install_scripts)
        if scripts.split(os.sep)[-2:] != ["lib", PACKAGE]:
            self.data_files = list(self.data_files or []) + [(f"lib/{PACKAGE}", _launchers())]


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md", "LICENSE"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    cmdclass={"install_data": InstallData},
    # The same runtime packages as requirements.txt (less the ROS wheels, which colcon users have from
    # their ROS install): `magcal batch` needs Dask, so a plain `pip install .` gives it.
    install_requires=["numpy>=1.26", "scipy>=1.11", "PyYAML>=6", "rosbags>=0.11,<0.12", "matplotlib>=3.8",
                      "pygeomag==1.1.0", "dask[distributed]>=2025.1"],
    license_files=["LICENSE"],
    package_data={PACKAGE: ["py.typed"]},
    zip_safe=True,
    maintainer="magcal_ros developers",
    maintainer_email="dev@magcal.invalid",
    description="Calibration of a magnetic gradient tensor array: core math, ROS 2 nodes, offline tools",
    license="Apache-2.0",
    python_requires=">=3.10",
    extras_require={"test": ["pytest"]},
    entry_points={"console_scripts": [f"{name} = {target}" for name, target in CONSOLE_SCRIPTS.items()]},
)
