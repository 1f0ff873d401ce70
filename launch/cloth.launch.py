"""ros2 launch cosserat_ros cloth.launch.py [config:=/path/to/params.yaml] [rviz:=true]

Starts cloth_node with a params file (default: the installed config/cloth.yaml) and,
with rviz:=true, RViz with the shipped view (rviz/cloth.rviz: the cloth, its pins and
handles, and the obstacles, in the node's frame_id 'world')."""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    share = FindPackageShare('cosserat_ros')
    return LaunchDescription([
        DeclareLaunchArgument(
            'config', default_value=PathJoinSubstitution([share, 'config', 'cloth.yaml']),
            description='params file of cloth_node (any of the installed config/*.yaml)'),
        DeclareLaunchArgument('rviz', default_value='false',
                              description='also start RViz with rviz/cloth.rviz'),
        Node(package='cosserat_ros', executable='cloth_node', name='cloth_node',
             parameters=[LaunchConfiguration('config')], output='screen'),
        Node(package='rviz2', executable='rviz2', name='rviz2', output='screen',
             arguments=['-d', PathJoinSubstitution([share, 'rviz', 'cloth.rviz'])],
             condition=IfCondition(LaunchConfiguration('rviz'))),
    ])
