"""Shared fixtures. ROS tests: one DDS domain per module (its DOMAIN_ID) and a fresh rclpy
Context per test, so tests and parallel runs do not cross-talk."""
import pytest
import rclpy
from rclpy.context import Context


@pytest.fixture
def context(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch):
    """An initialised rclpy Context on the test module's DOMAIN_ID."""
    domain_id = request.module.DOMAIN_ID
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain_id))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)
