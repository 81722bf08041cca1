"""Shared fixtures. ROS tests: one DDS domain per module (ekf_vo.ros.harness.domain_id_for,
the scheme benchmarks use too) and a fresh rclpy Context per test, so tests and parallel
runs do not cross-talk."""
import pytest
import rclpy
from rclpy.context import Context

from ekf_vo.ros.harness import Harness, domain_id_for


@pytest.fixture
def domain_id(request: pytest.FixtureRequest) -> int:
    """The test module's DDS domain."""
    return domain_id_for(request.module.__name__)


@pytest.fixture
def context(domain_id: int, monkeypatch: pytest.MonkeyPatch):
    """An initialised rclpy Context on the test module's domain."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain_id))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def harness(request: pytest.FixtureRequest, context: Context):
    """A driver node (ekf_vo.ros.harness.Harness) in `context`, in the test module's
    NAMESPACE when it defines one."""
    h = Harness(context=context, namespace=getattr(request.module, 'NAMESPACE', None))
    yield h
    h.close()
