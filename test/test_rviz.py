"""The shipped RViz2 configuration (rviz/ekf_vo.rviz) agrees with the nodes: every topic it
shows is one vo_node or map_node publishes (read from their source, so a renamed publisher
fails here), with a QoS that can receive it, in the frame the nodes publish in."""
import re
from pathlib import Path

import pytest
import yaml

from ekf_vo.config import MapNodeConfig, NodeConfig

REPO = Path(__file__).resolve().parents[1]
RVIZ = REPO / 'rviz' / 'ekf_vo.rviz'
NODES = [REPO / 'ekf_vo' / 'ros' / 'vo_node.py', REPO / 'ekf_vo' / 'ros' / 'map_node.py']

_NODE_NAME = re.compile(r"super\(\)\.__init__\(\s*'([^']+)'")
# create_publisher(Type, 'name', qos...) -- possibly over several lines
_PUBLISHER = re.compile(r"create_publisher\(\s*([\w.]+)\s*,\s*'([^']+)'\s*,\s*([\w.]+)")


def _resolve(name: str, node: str) -> str:
    """Topic name as seen from the root namespace (no namespace, no remapping)."""
    if name.startswith('~/'):
        return f'/{node}/{name[2:]}'
    return name if name.startswith('/') else '/' + name


def published_topics() -> dict[str, tuple[str, str]]:
    """{resolved topic: (message type, QoS expression)} over every create_publisher call."""
    topics = {}
    for path in NODES:
        source = path.read_text()
        names = _NODE_NAME.findall(source)
        assert len(names) == 1, f'{path.name}: cannot tell the node name'
        found = _PUBLISHER.findall(source)
        assert found, f'{path.name}: no create_publisher call found'
        for msg_type, topic, qos in found:
            topics[_resolve(topic, names[0])] = (msg_type, qos)
    return topics


def _rviz() -> dict:
    return yaml.safe_load(RVIZ.read_text())


def _displays(displays: list) -> list[dict]:
    """Every display, descending into display groups."""
    out = []
    for display in displays or []:
        out.append(display)
        out += _displays(display.get('Displays'))
    return out


def _topic(display: dict) -> str | None:
    topic = display.get('Topic')
    return topic.get('Value') if isinstance(topic, dict) else topic


def _display(cls: str) -> dict:
    found = [d for d in _displays(_rviz()['Visualization Manager']['Displays'])
             if d['Class'] == cls]
    assert len(found) == 1, f'expected one {cls} display, found {len(found)}'
    return found[0]


def test_the_publisher_scan_sees_the_node_topics():
    topics = published_topics()
    # a sanity check of the regex, not the source of truth for the test below
    assert {'/odom', '/landmarks', '/vo_node/path', '/vo_node/status',
            '/vo_node/debug_image', '/map_points'} <= set(topics)


def test_every_rviz_topic_is_published_by_a_node():
    topics = published_topics()
    shown = [(d['Name'], _topic(d))
             for d in _displays(_rviz()['Visualization Manager']['Displays'])]
    shown = [(name, topic) for name, topic in shown if topic is not None]
    assert len(shown) >= 4
    for name, topic in shown:
        assert topic in topics, f'display {name!r} shows {topic!r}, which no node publishes'


@pytest.mark.parametrize('cls, topic, msg_type', [
    ('rviz_default_plugins/Odometry', '/odom', 'Odometry'),
    ('rviz_default_plugins/Path', '/vo_node/path', 'Path'),
    ('rviz_default_plugins/PointCloud2', '/map_points', 'PointCloud2'),
    ('rviz_default_plugins/Image', '/vo_node/debug_image', 'Image'),
])
def test_each_display_shows_its_topic_with_the_right_type(cls, topic, msg_type):
    display = _display(cls)
    assert display['Enabled'] is True
    assert _topic(display) == topic
    assert published_topics()[topic][0] == msg_type


def test_the_odometry_display_shows_the_covariance():
    covariance = _display('rviz_default_plugins/Odometry')['Covariance']
    assert covariance['Value'] is True
    assert covariance['Position']['Value'] is True
    assert covariance['Orientation']['Value'] is True


def test_the_display_qos_can_receive_what_the_nodes_publish():
    topics = published_topics()
    for display in _displays(_rviz()['Visualization Manager']['Displays']):
        topic = _topic(display)
        if topic is None:
            continue
        qos = display['Topic']
        # a reliable subscription gets nothing from a best-effort (sensor data) publisher
        if topics[topic][1] == 'qos_profile_sensor_data':
            assert qos['Reliability Policy'] == 'Best Effort', display['Name']
    # map_node latches the map: RViz must ask for transient local to get it when late
    assert 'TRANSIENT_LOCAL' in NODES[1].read_text()
    assert _display('rviz_default_plugins/PointCloud2')['Topic']['Durability Policy'] == \
        'Transient Local'


def test_the_fixed_frame_is_the_default_odom_frame():
    fixed = _rviz()['Visualization Manager']['Global Options']['Fixed Frame']
    assert fixed == NodeConfig().odom_frame == MapNodeConfig().odom_frame


def test_setup_installs_the_rviz_configuration():
    assert re.search(r"\('share/' \+ PACKAGE \+ '/rviz', glob\('rviz/\*\.rviz'\)\)",
                     (REPO / 'setup.py').read_text())
