"""Start the magcal correction and calibration nodes with the package's configuration.

    ros2 launch magcal_ros magcal.launch.py
    ros2 launch magcal_ros magcal.launch.py calibration:=/path/calibration.yaml namespace:=array1

Arguments:
  config        parameters of both nodes (default: <share>/magcal_ros/config/magcal.yaml)
  calibration   calibration file loaded into the correction node after ``config`` and written by
                the calibration service on success (default: ~/.ros/magcal_calibration.yaml;
                loaded only if it exists)
  namespace     namespace of both nodes and their topics (default: none)
  use_sim_time  true when replaying a bag with /clock (default: false)

An argument this file does not declare (a misspelt ``calibration_file:=...``) stops the
launch with an error instead of being ignored.
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
ARGUMENTS = ('config', 'calibration', 'namespace', 'use_sim_time')


def _check_arguments(context):
    """Refuse command-line arguments this file does not declare: a typo must not go unnoticed."""
    given = [str(a).split(':=', 1)[0] for a in getattr(context, 'argv', []) if ':=' in str(a)]
    unknown = sorted(set(given) - set(ARGUMENTS))
    if unknown:
        hints = {'calibration_file': 'calibration'}
        said = ', '.join(f'{u} (did you mean {hints[u]}?)' if u in hints else u for u in unknown)
        raise RuntimeError(
            f'magcal.launch.py: unknown launch argument(s) {said}; it takes {", ".join(ARGUMENTS)} '
            '(ros2 launch magcal_ros magcal.launch.py --show-args)')


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
    _check_arguments(context)
    config = LaunchConfiguration('config').perform(context)
    calibration = os.path.expanduser(LaunchConfiguration('calibration').perform(context))
    namespace = LaunchConfiguration('namespace').perform(context)
    sim_time = LaunchConfiguration('use_sim_time').perform(context).strip().lower()
    if sim_time not in ('true', 'false'):
        raise RuntimeError(f"magcal.launch.py: use_sim_time must be true or false, got '{sim_time}'")
    clock = {'use_sim_time': sim_time == 'true'}
    correction_parameters = [_block(config, 'magcal_correction')]
    if calibration and os.path.isfile(calibration):
        correction_parameters.append(_block(calibration, 'magcal_correction'))
    correction_parameters.append(clock)
    calibration_parameters = [
        _block(config, 'magcal_calibration'),
        {'calibration_file': calibration, 'correction_node': 'magcal_correction', **clock},
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
        DeclareLaunchArgument(
            'use_sim_time', default_value='false',
            description='true: both nodes use /clock (replaying a bag)'),
        OpaqueFunction(function=_nodes),
    ])
