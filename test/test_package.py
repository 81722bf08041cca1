"""The package as a ROS install sees it: colcon build, ament index, params file, entry points."""
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ekf_vo.config import NodeConfig, VoConfig, load_yaml_params, split_params, to_yaml
from ekf_vo.ros.harness import domain_id_for

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def test_shipped_yaml_is_generated_from_the_typed_config():
    assert (REPO / 'config' / 'ekf_vo.yaml').read_text() == to_yaml(), \
        'config/ekf_vo.yaml is stale: run `make params`'


def test_shipped_yaml_loads_into_valid_configs():
    core, node = split_params(load_yaml_params(REPO / 'config' / 'ekf_vo.yaml'))
    assert core == VoConfig() and node == NodeConfig()


@pytest.mark.slow
def test_colcon_build_installs_what_ros2_run_executes(tmp_path):
    colcon = BIN / 'colcon'
    assert colcon.exists(), 'colcon-common-extensions missing from the venv'
    ws = tmp_path / 'ws'
    (ws / 'src').mkdir(parents=True)
    # a copy of the package as a user's workspace would hold it
    shutil.copytree(REPO, ws / 'src' / 'ekf_vo', ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', 'out', '*.egg-info', '__pycache__',
        '.pytest_cache', '.hypothesis'))
    env = dict(os.environ, PATH=f'{BIN}:{os.environ["PATH"]}')
    proc = subprocess.run([str(colcon), 'build', '--packages-select', 'ekf_vo'], cwd=ws,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    prefix = ws / 'install' / 'ekf_vo'
    exe = prefix / 'lib' / 'ekf_vo' / 'vo_node'
    assert exe.exists() and os.access(exe, os.X_OK)
    for name in ('map_node', 'ekf_vo_nodes'):
        assert (prefix / 'lib' / 'ekf_vo' / name).exists()

    # ament_index finds the package and its share directory
    code = ('from ament_index_python.packages import get_package_share_directory as g;'
            'import os; d = g("ekf_vo"); print(d);'
            'assert os.path.isfile(os.path.join(d, "config", "ekf_vo.yaml"));'
            'assert os.path.isfile(os.path.join(d, "launch", "ekf_vo.launch.py"));'
            'assert os.path.isfile(os.path.join(d, "package.xml"));'
            'assert os.path.isfile(os.path.join(d, "bags", "demo", "metadata.yaml"));'
            # the demo finds its bag in the install space, not in a source tree
            'from ekf_vo.tools.demo import demo_bag;'
            'assert str(demo_bag()) == os.path.join(d, "bags", "demo"), demo_bag()')
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    env_run = dict(env, AMENT_PREFIX_PATH=str(prefix),
                   PYTHONPATH=f'{site}:{env.get("PYTHONPATH", "")}',
                   ROS_DOMAIN_ID=str(domain_id_for(__name__)))
    proc = subprocess.run([sys.executable, '-c', code], env=env_run, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert str(prefix / 'share' / 'ekf_vo') in proc.stdout

    # the installed executable starts (from the install space, not the source tree) and
    # stops cleanly on SIGINT
    p = subprocess.Popen([str(exe), '--ros-args', '--params-file',
                          str(prefix / 'share' / 'ekf_vo' / 'config' / 'ekf_vo.yaml')],
                         env=env_run, cwd=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    try:
        out = ''
        deadline = time.time() + 30
        while time.time() < deadline and 'vo_node ready' not in out:
            line = p.stdout.readline()
            if not line and p.poll() is not None:
                break
            out += line
        assert 'vo_node ready' in out, out
        p.send_signal(signal.SIGINT)
        p.wait(timeout=15)
        assert p.returncode in (0, -signal.SIGINT), out
    finally:
        if p.poll() is None:
            p.kill()
