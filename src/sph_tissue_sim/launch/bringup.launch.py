"""The whole graph in one launch: omni_driver, sim_node and viz_node (and RViz2 if asked).

    ros2 launch sph_tissue_sim bringup.launch.py                                  # scripted stylus, live
    ros2 launch sph_tissue_sim bringup.launch.py backend:=replay bag:=/path/to/bags/press timing:=lockstep
    ros2 launch sph_tissue_sim bringup.launch.py backend:=openhaptics model:=liver tool:=capsule rviz:=true
    ros2 launch sph_tissue_sim bringup.launch.py namespace:=left sim_params:=/path/to/my_sim.yaml

Each node reads one YAML (``driver_params``, ``sim_params``, ``viz_params``; the packages'
defaults unless given), and the arguments override what they name: ``backend`` and ``bag`` the
driver's, ``model`` and ``tool`` (``tool_shape``) the simulation's, ``timing`` both (``live``: the
driver at its device rate or the bag's recorded timing, the simulation on the newest pose;
``lockstep``: a replay that waits for each force and a simulation that steps every pose in order,
bit-identical between runs). ``namespace`` puts the three nodes and their relative topics under
one name (a second instrument beside the first). Where the ROS 2 ``launch`` packages are absent,
``scripts/demo.sh`` takes the same choices as options, and importing this file still works.
"""

from __future__ import annotations

import os

#: launch argument -> (default, description); the node parameters each one sets are in
#: :func:`node_overrides`
ARGUMENTS = {
    'backend': ('scripted', 'omni_driver backend: openhaptics | replay | scripted'),
    'bag': ('', 'bag folder to replay (backend replay)'),
    'model': ('liver', 'sim_node model: liver | block | beam | mesh'),
    'tool': ('sphere', 'sim_node tool_shape: sphere | capsule'),
    'timing': ('live', 'live | lockstep (a replay that waits for each force; deterministic)'),
    'namespace': ('', 'namespace of the three nodes and their topics'),
    'report_dir': ('', 'viz report folder (empty: ./reports/<timestamp>)'),
    'rviz': ('false', 'also start rviz2 with the tissue layout'),
}


def node_overrides(arg) -> dict:
    """The parameters each node gets from the launch arguments (``arg(name)`` gives a value or a
    substitution), on top of its YAML: node executable -> {parameter: value}."""
    return {
        'omni_driver': {'backend': arg('backend'), 'bag': arg('bag'),
                        'replay_mode': arg('replay_mode')},
        'sim_node': {'model': arg('model'), 'tool_shape': arg('tool'),
                     'timing_mode': arg('timing_mode')},
        'viz_node': {'report_dir': arg('report_dir')},
    }


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.conditions import IfCondition
    from launch.substitutions import LaunchConfiguration, PythonExpression
    from launch_ros.actions import Node

    shares = {pkg: get_package_share_directory(pkg)
              for pkg in ('haptic_omni_driver', 'sph_tissue_sim', 'tissue_viz')}
    files = {'driver_params': os.path.join(shares['haptic_omni_driver'], 'config', 'omni_driver.yaml'),
             'sim_params': os.path.join(shares['sph_tissue_sim'], 'config', 'sim_node.yaml'),
             'viz_params': os.path.join(shares['tissue_viz'], 'config', 'viz.yaml')}
    timing = LaunchConfiguration('timing')
    derived = {
        # a lockstep simulation needs a replay that waits for each force, and live needs timed
        'replay_mode': PythonExpression(["'lockstep' if '", timing, "' == 'lockstep' else 'timed'"]),
        'timing_mode': PythonExpression(["'lockstep' if '", timing, "' == 'lockstep' else 'live'"]),
    }

    def arg(name):
        return derived[name] if name in derived else LaunchConfiguration(name)

    overrides = node_overrides(arg)
    ns = LaunchConfiguration('namespace')
    actions = [DeclareLaunchArgument(name, default_value=default, description=text)
               for name, (default, text) in ARGUMENTS.items()]
    actions += [DeclareLaunchArgument(name, default_value=path, description=f'{name} YAML')
                for name, path in files.items()]
    for pkg, exe, params in (('haptic_omni_driver', 'omni_driver', 'driver_params'),
                             ('sph_tissue_sim', 'sim_node', 'sim_params'),
                             ('tissue_viz', 'viz_node', 'viz_params')):
        actions.append(Node(package=pkg, executable=exe, name=exe, namespace=ns, output='screen',
                            parameters=[LaunchConfiguration(params), overrides[exe]]))
    actions.append(Node(package='rviz2', executable='rviz2', name='rviz2', output='log',
                        namespace=ns,
                        arguments=['-d', os.path.join(shares['tissue_viz'], 'rviz', 'tissue.rviz')],
                        condition=IfCondition(LaunchConfiguration('rviz'))))
    return LaunchDescription(actions)
