"""ekf_vo.ros.params on real rclpy nodes: descriptors, override checks, runtime validation."""
from __future__ import annotations

import dataclasses

import pytest
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from ekf_vo.config import ConfigError, MapNodeConfig, NodeConfig, VoConfig, describe
from ekf_vo.ros.params import declare_from_dataclass, install_validation

pytestmark = pytest.mark.ros


@pytest.fixture
def node(context: Context):
    n = Node('params_test', context=context)
    yield n
    n.destroy_node()


def _field(cls: type, name: str) -> dataclasses.Field:
    return next(f for f in dataclasses.fields(cls) if f.name == name)


def test_descriptors_carry_description_ranges_and_choices(node: Node) -> None:
    core = declare_from_dataclass(node, VoConfig)
    ros = declare_from_dataclass(node, NodeConfig)
    assert core == VoConfig()
    assert ros == NodeConfig()
    assert isinstance(ros.T_base_cam_xyzw, tuple)

    d = node.describe_parameter('max_features')
    assert d.description == describe(_field(VoConfig, 'max_features'))
    assert d.type == Parameter.Type.INTEGER.value
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (20, 5000)

    d = node.describe_parameter('pixel_sigma_px')
    assert d.type == Parameter.Type.DOUBLE.value
    assert d.floating_point_range[0].from_value == pytest.approx(0.01)
    assert d.floating_point_range[0].to_value == pytest.approx(50.0)
    assert 'unit: px' in d.description

    d = node.describe_parameter('estimator')
    assert d.type == Parameter.Type.STRING.value
    assert d.additional_constraints == 'one of: ekf, iekf, epnp'

    d = node.describe_parameter('T_base_cam_xyzw')
    assert d.type == Parameter.Type.DOUBLE_ARRAY.value
    assert list(node.get_parameter('T_base_cam_xyzw').value) == [-0.5, 0.5, -0.5, 0.5]

    d = node.describe_parameter('one_point_ransac')
    assert d.type == Parameter.Type.BOOL.value
    assert not d.integer_range and not d.floating_point_range


def test_overrides_are_read_and_checked(context: Context) -> None:
    n = Node('params_override', context=context,
             cli_args=['--ros-args', '-p', 'publish_rate_hz:=5.0', '-p', 'odom_frame:=world'])
    try:
        cfg = declare_from_dataclass(n, MapNodeConfig)
        assert cfg == MapNodeConfig(publish_rate_hz=5.0, odom_frame='world')
    finally:
        n.destroy_node()

    cases = [
        ([Parameter('publish_rate_hz', value=500.0)], 'out of range'),
        ([Parameter('publish_rate_hz', value=5)], 'decimal point'),   # int for a double
    ]
    for overrides, expected in cases:
        n = Node('params_bad', context=context, parameter_overrides=overrides)
        try:
            with pytest.raises(ConfigError, match=expected) as info:
                declare_from_dataclass(n, MapNodeConfig)
            assert 'publish_rate_hz' in str(info.value)
        finally:
            n.destroy_node()

    # A check only the dataclass knows (unit quaternion) also fails the declaration.
    n = Node('params_quat', context=context, parameter_overrides=[
        Parameter('T_base_cam_xyzw', value=[0.0, 0.0, 0.0, 2.0])])
    try:
        with pytest.raises(ConfigError, match='unit quaternion'):
            declare_from_dataclass(n, NodeConfig)
    finally:
        n.destroy_node()


def test_a_field_name_belongs_to_one_class(node: Node) -> None:
    declare_from_dataclass(node, NodeConfig)
    with pytest.raises(ConfigError, match='only one config class'):
        declare_from_dataclass(node, MapNodeConfig)   # odom_frame is in both


def test_runtime_changes_validated_and_reported(node: Node) -> None:
    declare_from_dataclass(node, VoConfig)
    declare_from_dataclass(node, NodeConfig)
    core_changes: list[VoConfig] = []
    node_changes: list[NodeConfig] = []
    install_validation(node, VoConfig, core_changes.append)
    install_validation(node, NodeConfig, node_changes.append)

    # Rejected by the descriptor range (rclpy) ...
    [res] = node.set_parameters([Parameter('max_features', value=10)])
    assert not res.successful and 'max_features' in res.reason and 'range' in res.reason
    # ... by the dataclass (choices, quaternion norm) ...
    [res] = node.set_parameters([Parameter('estimator', value='ukf')])
    assert not res.successful and 'not one of' in res.reason
    [res] = node.set_parameters([Parameter('T_base_cam_xyzw', value=[0.0, 0.0, 0.0, 3.0])])
    assert not res.successful and 'unit quaternion' in res.reason
    # ... or by type.
    [res] = node.set_parameters([Parameter('max_features', value='many')])
    assert not res.successful
    assert node.get_parameter('max_features').value == 300
    assert core_changes == [] and node_changes == []

    [res] = node.set_parameters([Parameter('max_features', value=500)])
    assert res.successful
    assert [c.max_features for c in core_changes] == [500]
    assert node_changes == []           # the other class's callback ignores the change

    res = node.set_parameters_atomically([Parameter('estimator', value='iekf'),
                                          Parameter('queue_size', value=5),
                                          Parameter('T_base_cam_xyz', value=[0.1, 0.0, 0.2])])
    assert res.successful
    assert core_changes[-1].estimator == 'iekf' and core_changes[-1].max_features == 500
    assert node_changes[-1].queue_size == 5
    assert node_changes[-1].T_base_cam_xyz == (0.1, 0.0, 0.2)

    # An atomic change with one bad value is rejected as a whole.
    res = node.set_parameters_atomically([Parameter('estimator', value='epnp'),
                                          Parameter('queue_size', value=1000)])
    assert not res.successful
    assert node.get_parameter('estimator').value == 'iekf'
    assert len(core_changes) == 2 and len(node_changes) == 1


def test_map_node_applies_new_rate(context: Context) -> None:
    from ekf_vo.ros.map_node import MapNode

    n = MapNode(context=context)
    try:
        assert n.config == MapNodeConfig()
        assert n._timer.timer_period_ns == 1_000_000_000
        [res] = n.set_parameters([Parameter('publish_rate_hz', value=1000.0)])
        assert not res.successful
        [res] = n.set_parameters([Parameter('publish_rate_hz', value=20.0)])
        assert res.successful
        assert n.config.publish_rate_hz == 20.0
        assert n._timer.timer_period_ns == 50_000_000
    finally:
        n.destroy_node()

