"""Launch viz_node with its default parameters (config/viz.yaml).

    ros2 launch tissue_viz viz.launch.py report_dir:=/tmp/run1

Where the ROS 2 ``launch`` packages are absent, importing this file still works; only
``generate_launch_description`` needs them.
"""

from __future__ import annotations

import os


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    share = get_package_share_directory('tissue_viz')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'viz.yaml'),
                              description='viz_node parameters'),
        DeclareLaunchArgument('report_dir', default_value='',
                              description='report folder (empty: ./reports/<timestamp>)'),
        Node(package='tissue_viz', executable='viz_node', name='viz_node', output='screen',
             parameters=[LaunchConfiguration('params_file'),
                         {'report_dir': LaunchConfiguration('report_dir')}]),
    ])
