"""ament_python setup for ekf_vo (layout of ros2/demos demo_nodes_py, Jazzy)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'ekf_vo'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, PACKAGE + '.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.py')),
        ('share/' + PACKAGE + '/rviz', glob('rviz/*.rviz')),
        # the demo bag, found by ekf-vo-demo through the ament index (tools/demo.py)
        ('share/' + PACKAGE + '/bags/demo', glob('bags/demo/*')),
    ],
    # Runtime dependencies are pinned in requirements.txt (venv installs) and declared in
    # package.xml (rosdep on a ROS install); nothing here so colcon never pip-installs.
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='ekf_vo developers',
    maintainer_email='dev@ekf-vo.invalid',
    description='Monocular EKF visual odometry (hybrid EKFPnP) for ROS 2 Jazzy',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'vo_node = ekf_vo.ros.vo_node:main',
            'map_node = ekf_vo.ros.map_node:main',
            'ekf_vo_nodes = ekf_vo.ros.run_all:main',
            'ekf-vo-synth = ekf_vo.tools.synth:main',
            'ekf-vo-convert = ekf_vo.tools.convert:main',
            'ekf-vo-play = ekf_vo.ros.player:main',
            'ekf-vo-run = ekf_vo.tools.run:main',
            'ekf-vo-eval = ekf_vo.tools.evaluate:main',
            'ekf-vo-demo = ekf_vo.tools.demo:main',
            'ekf-vo-params = ekf_vo.config:main',
        ],
    },
)
