"""What a person running vo_node by hand sees: unknown parameters named with the closest
known one, the compressed transport following the remapped image topic (image_transport's
convention), a warning naming the topic when no image arrives, and the tracking state
changes logged once each."""
from __future__ import annotations

import pytest
from sensor_msgs.msg import CompressedImage

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames

pytestmark = pytest.mark.ros
DOMAIN = domain_id_for(__name__)


def test_vo_node_tells_a_user_what_is_wrong_and_what_it_does(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text('vo_node:\n  ros__parameters:\n    max_featurez: 200\n')
    node = NodeProcess('ekf_vo.ros.vo_node', [
        '--params-file', str(params), '-p', 'bogus_param:=1',
        '-p', 'image_transport:=compressed', '-r', 'image:=/camx/image',
        '-r', 'camera_info:=/camx/camera_info', '-r', 'odom:=/odom',
        '-p', 'reliable_qos:=true'], DOMAIN, tmp_path / 'vo_node.log')
    h = Harness(DOMAIN)
    try:
        node.wait_for_output('vo_node ready')
        node.wait_for_output("unknown parameter 'max_featurez' ignored; did you mean "
                             "'max_features'?")
        node.wait_for_output("unknown parameter 'bogus_param' ignored")
        # the compressed transport is <remapped image topic>/compressed
        probe = h.node.create_publisher(CompressedImage, '/camx/image/compressed', 10)
        assert h.spin_until(lambda: probe.get_subscription_count() > 0, 20.0), \
            'vo_node does not subscribe /camx/image/compressed'
        node.wait_for_output('no image on /camx/image/compressed since start', timeout=15)
        # the state changes, once each
        info, frames = load_demo_frames()
        feed = Feeder(h, info, compressed=True, prefix='/camx')
        feed.wait_connected()
        feed.publish(frames[:60], lambda k, stamp, gray: feed.conv.numpy_to_compressed(
            gray, 'png', stamp, 'camera_optical'), rate_hz=20.0)
        node.wait_for_output('initialising -> tracking', timeout=20)
    finally:
        h.close()
        assert node.stop() == 0
    out = node.output()
    assert out.count('started -> initialising') == 1
    assert out.count('initialising -> tracking') == 1
