"""Start vo_node and map_node (ROS 2 Jazzy, full install with launch/launch_ros).

    ros2 launch ekf_vo ekf_vo.launch.py image_topic:=/camera/image_raw \\
        camera_info_topic:=/camera/camera_info use_sim_time:=true

Parameters come from the installed ``share/ekf_vo/config/ekf_vo.yaml`` (override with
``params_file:=...``). vo_node subscribes ``image`` (or ``image/compressed`` with
``image_transport: compressed``) and ``camera_info``; they are remapped to the launch
arguments. map_node reads vo_node's ``landmarks`` and publishes ``map_points``.

launch / launch_ros are imported inside :func:`generate_launch_description` only, so this
module can be imported (e.g. by tests) where they are not installed.
"""
import os


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue

    default_params = os.path.join(get_package_share_directory('ekf_vo'), 'config',
                                  'ekf_vo.yaml')
    image_topic = LaunchConfiguration('image_topic')
    camera_info_topic = LaunchConfiguration('camera_info_topic')
    params_file = LaunchConfiguration('params_file')
    use_sim_time = ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)
    log_level = LaunchConfiguration('log_level')

    arguments = [
        DeclareLaunchArgument('image_topic', default_value='/camera/image_raw',
                              description='Image topic (its /compressed sub-topic is used '
                                          'when image_transport is compressed).'),
        DeclareLaunchArgument('camera_info_topic', default_value='/camera/camera_info',
                              description='sensor_msgs/CameraInfo topic of the camera.'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='Follow /clock (true when playing a bag).'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS parameters YAML for vo_node and map_node.'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='Logging level of both nodes.'),
    ]
    vo_node = Node(
        package='ekf_vo', executable='vo_node', name='vo_node', output='screen',
        parameters=[params_file, {'use_sim_time': use_sim_time}],
        remappings=[
            ('image', image_topic),
            ('image/compressed', [image_topic, '/compressed']),
            ('camera_info', camera_info_topic),
        ],
        arguments=['--ros-args', '--log-level', log_level],
    )
    map_node = Node(
        package='ekf_vo', executable='map_node', name='map_node', output='screen',
        parameters=[params_file, {'use_sim_time': use_sim_time}],
        arguments=['--ros-args', '--log-level', log_level],
    )
    return LaunchDescription([*arguments, vo_node, map_node])
