"""Start the magcal correction and calibration nodes with the package's configuration.

    ros2 launch magcal_ros magcal.launch.py
    ros2 launch magcal_ros magcal.launch.py calibration:=/path/calibration.yaml namespace:=array1

Arguments:
  config       parameters of both nodes (default: <share>/magcal_ros/config/magcal.yaml)
  calibration  calibration file loaded into the correction node after ``config`` and written by
               the calibration service on success (default: ~/.ros/magcal_calibration.yaml;
               loaded only if it exists)
  namespace    namespace of both nodes and their topics (default: none)
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = 'magcal_ros'
DEFAULT_CALIBRATION = os.path.join('~', '.ros', 'magcal_calibration.yaml')


def _block(path, node):
    """The ``ros__parameters`` of ``node`` in a parameters file (key ``node``, ``/ns/node`` or ``/**/node``).

    Passed as a dict, so the values reach the node whatever namespace it is launched in.
    """
    with open(path, encoding='utf-8') as stream:
        doc = yaml.safe_load(stream) or {}
    for key, value in doc.items():
        if str(key).rstrip('/').split('/')[-1] == node and isinstance(value, dict):
            return value.get('ros__parameters') or {}
    return {}


def _nodes(context, *args, **kwargs):
    """Both nodes, with the calibration file added only when it exists."""
    config = LaunchConfiguration('config').perform(context)
    calibration = os.path.expanduser(LaunchConfiguration('calibration').perform(context))
    namespace = LaunchConfiguration('namespace').perform(context)
    correction_parameters = [_block(config, 'magcal_correction')]
    if calibration and os.path.isfile(calibration):
        correction_parameters.append(_block(calibration, 'magcal_correction'))
    calibration_parameters = [
        _block(config, 'magcal_calibration'),
        {'calibration_file': calibration, 'correction_node': 'magcal_correction'},
    ]
    return [
        Node(
            package=PACKAGE,
            executable='correction_node',
            name='magcal_correction',
            namespace=namespace,
            parameters=correction_parameters,
            output='screen',
            emulate_tty=True,
        ),
        Node(
            package=PACKAGE,
            executable='calibration_node',
            name='magcal_calibration',
            namespace=namespace,
            parameters=calibration_parameters,
            output='screen',
            emulate_tty=True,
        ),
    ]


def generate_launch_description():
    """Launch description of the magcal nodes."""
    default_config = os.path.join(get_package_share_directory(PACKAGE), 'config', 'magcal.yaml')
    return LaunchDescription([
        DeclareLaunchArgument(
            'config', default_value=default_config,
            description='parameters file of both nodes (sensor names, positions, method, ...)'),
        DeclareLaunchArgument(
            'calibration', default_value=DEFAULT_CALIBRATION,
            description='calibration file: loaded into the correction node if it exists, '
                        'written by the calibration service'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of both nodes and their topics'),
        OpaqueFunction(function=_nodes),
    ])
