"""Bag and file I/O: rosbag2 reading/writing (rosbags), trajectory files, dataset folders.

Layer: beside the message bridge (:mod:`ekf_vo.bridge`, whose converters it uses), below the
nodes and CLI tools; it never imports ``ekf_vo.tools`` or ``ekf_vo.ros``.

* :mod:`.bag`: rosbag2 via the pure-Python ``rosbags`` (BagWriter, iter_bag, read_raw,
  read_ground_truth); ROS 1 ``.bag`` files are read too, as ROS 2 messages;
* :mod:`.trajectory`: TUM files and ground truth of a bag as trajectories;
* :mod:`.dataset`: the image-folder dataset layout (camera.json, images, TUM ground truth).
"""
