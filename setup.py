"""magcal_ros: ament_python package, also installable with plain pip."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "magcal_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["numpy", "scipy", "PyYAML", "rosbags", "matplotlib", "pygeomag==1.1.0"],
    package_data={PACKAGE: ["py.typed"]},
    zip_safe=True,
    maintainer="magcal_ros developers",
    maintainer_email="dev@magcal.invalid",
    description="Calibration of a magnetic gradient tensor array: core math, ROS 2 nodes, offline tools",
    license="Apache-2.0",
    python_requires=">=3.10",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "magcal = magcal_ros.app.cli:main",
            "correction_node = magcal_ros.nodes.correction_node:main",
            "calibration_node = magcal_ros.nodes.calibration_node:main",
        ],
    },
)
