"""launch/magcal.launch.py builds the right nodes (launch itself is not on PyPI: stand-ins record calls).

The stand-ins accept exactly the launch / launch_ros calls a real ROS 2 Jazzy install
provides (LaunchDescription, DeclareLaunchArgument, OpaqueFunction, LaunchConfiguration,
launch_ros.actions.Node with package/executable/name/namespace/parameters/output/emulate_tty)
and a LaunchContext with ``argv`` (the ``name:=value`` arguments of the command line, as
``ros2 launch`` passes them) and ``launch_configurations``.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from pathlib import Path
from typing import Any

import pytest
import yaml

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = ROOT / "launch" / "magcal.launch.py"


class _Recorded:
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


class _DeclareLaunchArgument(_Recorded):
    def __init__(self, name: str, *, default_value: str = "", description: str = "") -> None:
        super().__init__(name, default_value=default_value, description=description)
        self.name, self.default_value = name, default_value


class _OpaqueFunction(_Recorded):
    def __init__(self, *, function: Any) -> None:
        super().__init__(function=function)
        self.function = function


class _LaunchContext:
    """launch.LaunchContext's two members the launch file uses."""

    def __init__(self, argv: list[str], configurations: dict[str, str]) -> None:
        self.argv = argv
        self.launch_configurations = configurations


class _LaunchConfiguration:
    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context: _LaunchContext) -> str:
        return context.launch_configurations[self.name]


class _Node(_Recorded):
    ALLOWED = {"package", "executable", "name", "namespace", "parameters", "output", "emulate_tty", "arguments",
               "remappings"}

    def __init__(self, **kwargs: Any) -> None:
        unknown = set(kwargs) - self.ALLOWED
        assert not unknown, f"launch_ros Node has no arguments {unknown}"
        super().__init__(**kwargs)


@pytest.fixture
def launch_module(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> types.ModuleType:
    share = tmp_path / "share" / "magcal_ros"
    (share / "config").mkdir(parents=True)
    for f in (ROOT / "config").glob("*.yaml"):
        (share / "config" / f.name).write_text(f.read_text())
    stubs = {
        "launch": types.ModuleType("launch"),
        "launch.actions": types.ModuleType("launch.actions"),
        "launch.substitutions": types.ModuleType("launch.substitutions"),
        "launch_ros": types.ModuleType("launch_ros"),
        "launch_ros.actions": types.ModuleType("launch_ros.actions"),
        "ament_index_python": types.ModuleType("ament_index_python"),
        "ament_index_python.packages": types.ModuleType("ament_index_python.packages"),
    }
    stubs["launch"].LaunchDescription = lambda actions: list(actions)  # type: ignore[attr-defined]
    stubs["launch.actions"].DeclareLaunchArgument = _DeclareLaunchArgument  # type: ignore[attr-defined]
    stubs["launch.actions"].OpaqueFunction = _OpaqueFunction  # type: ignore[attr-defined]
    stubs["launch.substitutions"].LaunchConfiguration = _LaunchConfiguration  # type: ignore[attr-defined]
    stubs["launch_ros.actions"].Node = _Node  # type: ignore[attr-defined]
    stubs["ament_index_python.packages"].get_package_share_directory = (  # type: ignore[attr-defined]
        lambda pkg: str(share) if pkg == "magcal_ros" else (_ for _ in ()).throw(KeyError(pkg))
    )
    for name, module in stubs.items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("magcal_launch", LAUNCH_FILE)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _nodes(module: types.ModuleType, **overrides: str) -> tuple[list[Any], dict[str, _Node]]:
    """Run the launch description as ``ros2 launch ... name:=value`` (overrides) would."""
    actions = module.generate_launch_description()
    args = {a.name: a.default_value for a in actions if isinstance(a, _DeclareLaunchArgument)}
    args.update(overrides)
    opaque = [a for a in actions if isinstance(a, _OpaqueFunction)]
    assert len(opaque) == 1
    nodes = opaque[0].function(_LaunchContext([f"{k}:={v}" for k, v in overrides.items()], args))
    return actions, {n.kwargs["executable"]: n for n in nodes}


def _executables() -> set[str]:
    """Console scripts named in setup.py (``"name": "module:function"``)."""
    return set(re.findall(r'"(\w+)": "magcal_ros[\w.]*:\w+"', (ROOT / "setup.py").read_text()))


def test_launch_starts_both_installed_executables_with_config(launch_module: types.ModuleType, tmp_path: Path) -> None:
    actions, nodes = _nodes(launch_module, calibration=str(tmp_path / "none.yaml"))
    declared = {a.name for a in actions if isinstance(a, _DeclareLaunchArgument)}
    assert declared == {"config", "calibration", "namespace", "use_sim_time"}
    assert set(nodes) == {"correction_node", "calibration_node"} <= _executables()
    correction, calibration = nodes["correction_node"].kwargs, nodes["calibration_node"].kwargs
    assert correction["package"] == calibration["package"] == "magcal_ros"
    assert correction["name"] == "magcal_correction" and calibration["name"] == "magcal_calibration"
    config = yaml.safe_load((ROOT / "config" / "magcal.yaml").read_text())
    assert correction["parameters"] == [config["magcal_correction"]["ros__parameters"], {"use_sim_time": False}]
    assert calibration["parameters"][0] == config["magcal_calibration"]["ros__parameters"]
    assert calibration["parameters"][1]["correction_node"] == "magcal_correction"
    assert calibration["parameters"][1]["use_sim_time"] is False
    # The configuration gives no per-sensor calibration: only a calibration file does.
    assert not any(k.endswith(("matrix", "offset")) or isinstance(v, dict)
                   for k, v in config["magcal_correction"]["ros__parameters"].items())


def test_launch_loads_an_existing_calibration_file(launch_module: types.ModuleType) -> None:
    example = ROOT / "config" / "example_calibration.yaml"
    _, nodes = _nodes(launch_module, calibration=str(example), namespace="array1")
    correction = nodes["correction_node"].kwargs
    assert correction["namespace"] == "array1"
    block = yaml.safe_load(example.read_text())["magcal_correction"]["ros__parameters"]
    assert correction["parameters"][-2] == block
    assert nodes["calibration_node"].kwargs["parameters"][1]["calibration_file"] == str(example)


def test_launch_passes_use_sim_time_to_both_nodes(launch_module: types.ModuleType, tmp_path: Path) -> None:
    _, nodes = _nodes(launch_module, calibration=str(tmp_path / "none.yaml"), use_sim_time="true")
    for node in nodes.values():
        assert node.kwargs["parameters"][-1]["use_sim_time"] is True
    with pytest.raises(RuntimeError, match="use_sim_time must be true or false"):
        _nodes(launch_module, use_sim_time="yes please")


def test_unknown_launch_arguments_stop_the_launch(launch_module: types.ModuleType) -> None:
    """The old README spelling calibration_file:= used to start an uncalibrated node silently."""
    with pytest.raises(RuntimeError, match=r"unknown launch argument\(s\) calibration_file \(did you mean calibration\?\)"):
        _nodes(launch_module, calibration_file="/tmp/cal.yaml")
    with pytest.raises(RuntimeError, match="namespce.*takes config, calibration, namespace, use_sim_time"):
        _nodes(launch_module, namespce="array1")
    readme = (ROOT / "README.md").read_text()
    assert "calibration_file:=" not in readme and "calibration:=" in readme
