"""The whole graph in one launch: omni_driver, sim_node and viz_node (and RViz2 if asked).

    ros2 launch sph_tissue_sim bringup.launch.py                                  # scripted stylus, live
    ros2 launch sph_tissue_sim bringup.launch.py backend:=replay bag:=/path/to/bags/press timing:=lockstep
    ros2 launch sph_tissue_sim bringup.launch.py backend:=openhaptics model:=liver tool:=capsule rviz:=true
    ros2 launch sph_tissue_sim bringup.launch.py namespace:=left sim_params:=/path/to/my_sim.yaml
    ros2 launch sph_tissue_sim bringup.launch.py backend:=replay bag:=/path/to/bags/long exit_at_end:=true

Each node reads one YAML (``driver_params``, ``sim_params``, ``viz_params``; the packages'
defaults unless given), and the arguments given override what they name: ``backend`` and ``bag``
the driver's, ``model`` and ``tool`` (``tool_shape``) the simulation's, ``timing`` both (``live``:
the driver at its device rate or the bag's recorded timing, the simulation on the newest pose;
``lockstep``: a replay that waits for each force and a simulation that steps every pose in order,
bit-identical between runs; refused without ``backend:=replay``). ``exit_at_end:=true`` ends the
whole launch when omni_driver exits: the driver gets ``exit_on_end`` true, so it exits at the end
of a replay (or of a script without ``loop``), and the launch then stops sim_node and viz_node as
on Ctrl-C (SIGINT; viz_node writes its report); with ``false`` (the default) they keep running and
the driver's YAML decides whether it exits at the end. An argument left empty leaves the YAML's
value. ``namespace`` puts the three nodes and their relative topics under one name (a
second instrument beside the first); the YAMLs' node keys must then match the namespaced names
(``/left/sim_node:``), or use ``/**:`` for any. Where the ROS 2 ``launch`` packages are absent,
``scripts/demo.sh`` takes the same choices as options, and importing this file still works.
"""

from __future__ import annotations

import os

#: launch argument -> (default, description); empty: the node's YAML decides
ARGUMENTS = {
    'backend': ('', 'omni_driver backend: openhaptics | replay | scripted (empty: driver_params)'),
    'bag': ('', 'bag folder to replay (backend replay)'),
    'model': ('', 'sim_node model: liver | block | beam | mesh (empty: sim_params)'),
    'tool': ('', 'sim_node tool_shape: sphere | capsule (empty: sim_params)'),
    'timing': ('live', 'live | lockstep (a replay that waits for each force; deterministic)'),
    'namespace': ('', 'namespace of the three nodes and their topics'),
    'report_dir': ('', 'viz report folder (empty: viz_params, or ./reports/<timestamp>)'),
    'rviz': ('false', 'also start rviz2 with the tissue layout'),
    'exit_at_end': ('false', 'true: the launch ends when omni_driver exits, which it then does at '
                             'the end of a replay or script (exit_on_end true)'),
}


def exit_at_end(values: dict) -> bool:
    """Whether the launch ends with omni_driver (the ``exit_at_end`` argument; empty: false).

    Raises:
        ValueError: neither true nor false.
    """
    text = (values.get('exit_at_end') or 'false').strip().lower()
    if text not in ('true', 'false'):
        raise ValueError(f'exit_at_end must be true or false, got {values.get("exit_at_end")!r}')
    return text == 'true'


def node_overrides(values: dict) -> dict:
    """The parameters each node gets from the launch arguments' ``values`` (name -> string), on
    top of its YAML: executable -> {parameter: value}. An empty argument sets nothing.

    Raises:
        ValueError: ``timing`` lockstep without a replay (a live source cannot wait for a force), or
            ``exit_at_end`` neither true nor false.
    """
    timing = values.get('timing') or 'live'
    if timing not in ('live', 'lockstep'):
        raise ValueError(f'timing must be live or lockstep, got {timing!r}')
    if timing == 'lockstep' and values.get('backend') != 'replay':
        raise ValueError('timing:=lockstep needs backend:=replay and a bag (a live source cannot '
                         'wait for each force)')
    out = {
        'omni_driver': {'backend': values.get('backend'), 'bag': values.get('bag'),
                        'replay_mode': 'lockstep' if timing == 'lockstep' else None,
                        # false sets nothing: the driver's YAML says whether it exits at the end
                        'exit_on_end': exit_at_end(values) or None},
        'sim_node': {'model': values.get('model'), 'tool_shape': values.get('tool'),
                     'timing_mode': timing},
        'viz_node': {'report_dir': values.get('report_dir')},
    }
    return {exe: {k: v for k, v in params.items() if v} for exe, params in out.items()}


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, EmitEvent, OpaqueFunction, RegisterEventHandler
    from launch.conditions import IfCondition
    from launch.event_handlers import OnProcessExit
    from launch.events import Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    shares = {pkg: get_package_share_directory(pkg)
              for pkg in ('haptic_omni_driver', 'sph_tissue_sim', 'tissue_viz')}
    files = {'driver_params': os.path.join(shares['haptic_omni_driver'], 'config', 'omni_driver.yaml'),
             'sim_params': os.path.join(shares['sph_tissue_sim'], 'config', 'sim_node.yaml'),
             'viz_params': os.path.join(shares['tissue_viz'], 'config', 'viz.yaml')}

    def nodes(context):
        values = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
        overrides = node_overrides(values)
        ns = values['namespace']
        started = {}
        for pkg, exe, params in (('haptic_omni_driver', 'omni_driver', 'driver_params'),
                                 ('sph_tissue_sim', 'sim_node', 'sim_params'),
                                 ('tissue_viz', 'viz_node', 'viz_params')):
            started[exe] = Node(package=pkg, executable=exe, name=exe, namespace=ns,
                                output='screen',
                                parameters=[LaunchConfiguration(params).perform(context),
                                            overrides[exe]])
        out = list(started.values())
        if exit_at_end(values):
            # the other nodes get SIGINT as on Ctrl-C (viz_node writes its report)
            out.append(RegisterEventHandler(OnProcessExit(
                target_action=started['omni_driver'], on_exit=[EmitEvent(event=Shutdown(
                    reason='omni_driver exited (exit_at_end:=true)'))])))
        return out

    actions = [DeclareLaunchArgument(name, default_value=default, description=text)
               for name, (default, text) in ARGUMENTS.items()]
    actions += [DeclareLaunchArgument(name, default_value=path, description=f'{name} YAML')
                for name, path in files.items()]
    actions.append(OpaqueFunction(function=nodes))
    actions.append(Node(package='rviz2', executable='rviz2', name='rviz2', output='log',
                        namespace=LaunchConfiguration('namespace'),
                        arguments=['-d', os.path.join(shares['tissue_viz'], 'rviz', 'tissue.rviz')],
                        condition=IfCondition(LaunchConfiguration('rviz'))))
    return LaunchDescription(actions)
