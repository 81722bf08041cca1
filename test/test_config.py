"""The typed parameter definitions: defaults valid, every field documented, clear errors."""
import dataclasses

import pytest

from ekf_vo.config import (ConfigError, MapNodeConfig, NodeConfig, VoConfig, split_params,
                           to_yaml)


@pytest.mark.parametrize('cls', [VoConfig, NodeConfig, MapNodeConfig])
def test_defaults_are_valid_and_every_field_is_documented(cls):
    cls().validate()
    for f in dataclasses.fields(cls):
        assert f.metadata['doc'], f'{f.name} has no description'
        assert f'{f.name}:' in to_yaml()


@pytest.mark.parametrize('values, message', [
    ({'max_features': 3}, 'below its minimum'),
    ({'fading_memory': 2.0}, 'above its maximum'),
    ({'estimator': 'orbslam'}, 'not one of'),
    ({'pixel_sigma_px': 'one'}, 'must be a number'),
    ({'pixel_sigma_px': float('nan')}, 'finite'),
    ({'one_point_ransac': 1}, 'must be a bool'),
    ({'max_features': 10.5}, 'integer'),
    ({'no_such_parameter': 1}, 'unknown'),
])
def test_invalid_values_name_the_parameter(values, message):
    with pytest.raises(ConfigError, match=message):
        VoConfig.from_mapping(values)


def test_yaml_numbers_are_coerced_to_the_field_type():
    cfg = VoConfig.from_mapping({'accel_sigma': 3, 'max_features': 200.0})
    assert cfg.accel_sigma == 3.0 and isinstance(cfg.accel_sigma, float)
    assert cfg.max_features == 200 and isinstance(cfg.max_features, int)


def test_extrinsic_must_be_a_unit_quaternion():
    with pytest.raises(ConfigError, match='unit quaternion'):
        NodeConfig.from_mapping({'T_base_cam_xyzw': [0.0, 0.0, 0.0, 2.0]})
    with pytest.raises(ConfigError, match='3 values'):
        NodeConfig.from_mapping({'T_base_cam_xyz': [0.0, 0.0]})


def test_split_params_routes_core_and_node_fields():
    core, node = split_params({'max_features': 111, 'odom_frame': 'o', 'use_sim_time': True})
    assert core.max_features == 111 and node.odom_frame == 'o'
    with pytest.raises(ConfigError, match='unknown vo_node parameter'):
        split_params({'bogus': 1})


def test_core_imports_numpy_and_opencv_only():
    """The estimator core stays free of ROS, messages and bag libraries (pure core)."""
    import ast
    from pathlib import Path
    core = Path(__file__).resolve().parents[1] / 'ekf_vo' / 'core'
    allowed = {'numpy', 'cv2', 'ekf_vo', '__future__', 'logging', 'dataclasses', 'enum',
               'time', 'math', 'typing', 'collections', 'functools', 'itertools',
               'threading',   # stdlib only: the stream guards its inputs with a lock
               'concurrent',  # the local map's adjustment worker (core/local_map.py)
               'bisect',      # CameraInfo by stamp (core/pairing.py)
               # the adjustment's worker process (core/ba_process.py): stdlib only
               'os', 'pickle', 'signal', 'struct', 'subprocess', 'sys'}
    lazy_ok = {('multiview.py', 'scipy')}   # bundle adjustment, imported in the function
    for path in core.glob('*.py'):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            for name in names:
                top = name.split('.')[0]
                assert top in allowed or (path.name, top) in lazy_ok, \
                    f'{path.name} imports {name}'
