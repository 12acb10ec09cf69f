"""Launch omni_driver (and optionally omni_record).

    ros2 launch haptic_omni_driver omni_driver.launch.py backend:=scripted
    ros2 launch haptic_omni_driver omni_driver.launch.py backend:=replay bag:=/path/to/bag
    ros2 launch haptic_omni_driver omni_driver.launch.py backend:=openhaptics record:=true
"""

import os

try:
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.conditions import IfCondition
    from launch.substitutions import LaunchConfiguration, PythonExpression
    from launch_ros.actions import Node
except ImportError:  # no launch here (pip-only ROS): the file still imports
    LaunchDescription = None


def generate_launch_description():
    """Driver with the backend's params file; recorder when record:=true."""
    if LaunchDescription is None:
        raise RuntimeError('the ROS 2 launch packages are not installed')
    share = get_package_share_directory('haptic_omni_driver')
    backend = LaunchConfiguration('backend')
    params_file = PythonExpression(["'", share, "/config/omni_driver_' + '", backend, "' + '.yaml'"])
    return LaunchDescription([
        DeclareLaunchArgument('backend', default_value='scripted',
                              description='openhaptics | replay | scripted'),
        DeclareLaunchArgument('bag', default_value='', description='bag folder (replay)'),
        DeclareLaunchArgument('record', default_value='false', description='also run omni_record'),
        DeclareLaunchArgument('output', default_value='', description='recorder bag folder'),
        Node(package='haptic_omni_driver', executable='omni_driver', name='omni_driver',
             output='screen',
             parameters=[os.path.join(share, 'config', 'omni_driver.yaml'), params_file,
                         {'backend': backend, 'bag': LaunchConfiguration('bag')}]),
        Node(package='haptic_omni_driver', executable='omni_record', name='omni_record',
             output='screen', condition=IfCondition(LaunchConfiguration('record')),
             parameters=[os.path.join(share, 'config', 'omni_record.yaml'),
                         {'output': LaunchConfiguration('output')}]),
    ])
