"""Launch viz_node with its default parameters (config/viz.yaml), optionally with RViz2.

    ros2 launch tissue_viz viz.launch.py report_dir:=/tmp/run1 rviz:=true

Where the ROS 2 ``launch`` packages are absent, importing this file still works; only
``generate_launch_description`` needs them.
"""

from __future__ import annotations

import os


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.conditions import IfCondition
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    share = get_package_share_directory('tissue_viz')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'viz.yaml'),
                              description='viz_node parameters'),
        DeclareLaunchArgument('report_dir', default_value='',
                              description='report folder (empty: ./reports/<timestamp>)'),
        DeclareLaunchArgument('rviz', default_value='false',
                              description='also start rviz2 with rviz/tissue.rviz'),
        Node(package='tissue_viz', executable='viz_node', name='viz_node', output='screen',
             parameters=[LaunchConfiguration('params_file'),
                         {'report_dir': LaunchConfiguration('report_dir')}]),
        Node(package='rviz2', executable='rviz2', name='rviz2', output='log',
             arguments=['-d', os.path.join(share, 'rviz', 'tissue.rviz')],
             condition=IfCondition(LaunchConfiguration('rviz'))),
    ])
