"""The launch file and the README agree: every `name:=value` the README passes to
`ros2 launch` is an argument the launch file declares."""
import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / 'launch' / 'ekf_vo.launch.py'


def _declared_arguments() -> set[str]:
    """Names passed to DeclareLaunchArgument, read from the source (launch may be absent)."""
    names = set()
    for node in ast.walk(ast.parse(LAUNCH.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', '') == \
                'DeclareLaunchArgument' and node.args and \
                isinstance(node.args[0], ast.Constant):
            names.add(node.args[0].value)
    return names


def _readme_launch_arguments() -> list[tuple[str, str]]:
    """(line, argument) for every `name:=` on a README `ros2 launch` command line,
    following backslash continuations."""
    text = REPO.joinpath('README.md').read_text().replace('\\\n', ' ')
    found = []
    for line in text.splitlines():
        if 'ros2 launch ekf_vo' in line:
            found += [(line.strip(), name) for name in re.findall(r'(\w+):=', line)]
    return found


def test_the_launch_file_declares_its_arguments():
    assert {'image_topic', 'camera_info_topic', 'use_sim_time', 'params_file',
            'log_level'} <= _declared_arguments()


def test_every_launch_argument_in_the_readme_is_declared():
    used = _readme_launch_arguments()
    assert used, 'the README shows no `ros2 launch ekf_vo ... name:=value` line'
    declared = _declared_arguments()
    unknown = [(line, name) for line, name in used if name not in declared]
    assert not unknown, f'README passes undeclared launch arguments: {unknown}'


def test_generate_launch_description_runs_where_launch_is_installed():
    pytest.importorskip('launch', reason='launch / launch_ros are not installed here '
                        '(no PyPI wheels); they are on a full ROS 2 install')
    pytest.importorskip('launch_ros', reason='launch_ros is not installed')
    import importlib.util
    spec = importlib.util.spec_from_file_location('ekf_vo_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    declared = {a.name for a in description.get_launch_arguments()}
    assert declared == _declared_arguments()
