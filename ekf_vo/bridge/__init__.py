"""The message bridge: ROS 2 messages <-> numpy, and the topic rule (no rclpy, no rosbags).

Layer: below the nodes and CLI tools (``ekf_vo.ros``, ``ekf_vo.tools``), beside the bag I/O
(``ekf_vo.io``), above the estimation core (``ekf_vo.core``). Nothing here imports upwards.

One module per message kind: :mod:`.image` (Image / CompressedImage, the one decoder
:func:`decode_image`), :mod:`.camera_info`, :mod:`.pointcloud2`, :mod:`.odometry` (poses,
odometry, covariances), :mod:`.common` (ConversionError, stamps, field readers) and
:mod:`.topics` (which topic carries the images). Readers take fields by name, so they work on
rclpy messages and rosbags classes alike; builders make either (``typestore=None``: rclpy).
This package re-exports the public names of all of them.
"""
from __future__ import annotations

from .camera_info import (DISTORTION_MODELS, camera_info_from_params, camera_info_to_dict,
                          validate_camera_info)
from .common import (CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, POSE_STAMPED, ConversionError,
                     ns_to_stamp, stamp_to_ns)
from .image import (IMAGE_ENCODINGS, compressed_to_gray, decode_image, image_to_gray,
                    image_to_numpy, numpy_to_compressed, numpy_to_image)
from .odometry import (matrix_to_pose_stamped, matrix_to_quat_xyzw, odometry_to_pose,
                       pose_msg_to_matrix, pose_stamped_to_matrix, pose_to_odometry,
                       quat_xyzw_to_matrix, transform_pose_covariance)
from .pointcloud2 import (POINTFIELD_DTYPES, pointcloud2_to_numpy, pointcloud2_to_xyz,
                          points_to_pointcloud2)
from .topics import CameraTopics, TopicError, select_camera_topics, transport_topic


__all__ = [
    'ConversionError', 'IMAGE', 'COMPRESSED_IMAGE', 'CAMERA_INFO', 'POSE_STAMPED',
    'stamp_to_ns', 'ns_to_stamp',
    'IMAGE_ENCODINGS', 'image_to_numpy', 'decode_image', 'image_to_gray', 'compressed_to_gray',
    'numpy_to_image', 'numpy_to_compressed',
    'DISTORTION_MODELS', 'camera_info_to_dict', 'validate_camera_info', 'camera_info_from_params',
    'POINTFIELD_DTYPES', 'points_to_pointcloud2', 'pointcloud2_to_numpy', 'pointcloud2_to_xyz',
    'quat_xyzw_to_matrix', 'matrix_to_quat_xyzw', 'pose_msg_to_matrix', 'pose_to_odometry',
    'odometry_to_pose', 'pose_stamped_to_matrix', 'matrix_to_pose_stamped',
    'transform_pose_covariance',
    'TopicError', 'CameraTopics', 'transport_topic', 'select_camera_topics',
]
