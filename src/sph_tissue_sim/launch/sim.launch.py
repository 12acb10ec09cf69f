"""Launch sim_node with its defaults (config/sim_node.yaml), optionally with a preset on top.

    ros2 launch sph_tissue_sim sim.launch.py
    ros2 launch sph_tissue_sim sim.launch.py preset:=sim_node_paper.yaml
    ros2 launch sph_tissue_sim sim.launch.py timing_mode:=lockstep namespace:=left

Where the ROS 2 ``launch`` packages are absent, importing this file still works; only
``generate_launch_description`` needs them.
"""

from __future__ import annotations

import os


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
    from launch_ros.actions import Node

    share = get_package_share_directory('sph_tissue_sim')
    config = os.path.join(share, 'config')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=os.path.join(config, 'sim_node.yaml'),
                              description='sim_node parameters (defaults: the liver preset)'),
        DeclareLaunchArgument('preset', default_value='sim_node.yaml',
                              description='a second params file in share/sph_tissue_sim/config '
                                          'loaded on top, e.g. sim_node_paper.yaml'),
        DeclareLaunchArgument('timing_mode', default_value='live', description='live | lockstep'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its (relative) topics'),
        Node(package='sph_tissue_sim', executable='sim_node', name='sim_node', output='screen',
             namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file'),
                         PathJoinSubstitution([config, LaunchConfiguration('preset')]),
                         {'timing_mode': LaunchConfiguration('timing_mode')}]),
    ])
