"""cloe_inference as a process on a domain of its own, seen through DDS: what it loses is counted
(``message_lost``), which vehicles it takes (listed, discovered, its shard), and what it says
about vehicles nothing publishes for.

Every wait is on a condition the node reports, with a timeout a loaded machine meets; nothing is
timed.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeProcess, private_domain, spin_until

from cloe_ros.io.messages import decode_diagnostics

pytestmark = pytest.mark.ros


@pytest.fixture
def ros():
    with private_domain('inference_graph_test') as ros:
        yield ros


class Diagnostics:
    """The last status per name on /diagnostics, each message decoded once."""

    def __init__(self, ros) -> None:
        self.statuses: dict[str, object] = {}
        ros.node.create_subscription(DiagnosticArray, '/diagnostics', self._take, 100, raw=True)

    def _take(self, raw: bytes) -> None:
        for status in decode_diagnostics(raw)[1]:
            self.statuses[status.name] = status

    def values(self, name: str) -> dict[str, str]:
        status = self.statuses.get(name)
        return {} if status is None else dict(status.values)


def odometry(k: int) -> Odometry:
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = 1000 + k // 100, (k % 100) * 10_000_000
    m.header.frame_id, m.child_frame_id = 'world', 'base_link'
    m.pose.pose.position.z = 1.0
    m.pose.pose.orientation.w = 1.0
    return m


def test_messages_lost_in_dds_are_counted_per_topic(ros, tmp_path: Path) -> None:
    """The node is stopped (SIGSTOP) while a reliable publisher whose history holds 10 messages
    publishes 3000 odometry messages; the ones overwritten before the node took them are lost.
    Once it runs again, /diagnostics counts them under odom_lost, and what it received plus what
    it lost is what was published (reliable delivery: every other message arrives)."""
    n = 3000
    pub = ros.node.create_publisher(
        Odometry, '/odom', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    diagnostics = Diagnostics(ros)
    node = NodeProcess('cloe_inference', {'diagnostics_period': 0.2}, ros.domain, tmp_path)
    name = 'cloe_inference: /'
    try:
        assert spin_until(ros.executor, lambda: pub.get_subscription_count() >= 1, 60), (
            node.output()
        )
        assert spin_until(ros.executor, lambda: diagnostics.values(name), 60), node.output()
        os.kill(node.proc.pid, signal.SIGSTOP)
        try:
            for k in range(n):
                pub.publish(odometry(k))
        finally:
            os.kill(node.proc.pid, signal.SIGCONT)

        def counts() -> tuple[int, int]:
            values = diagnostics.values(name)
            return int(values['odom_received']), int(values['odom_lost'])

        assert spin_until(ros.executor, lambda: sum(counts()) >= n, 120), (counts(), node.output())
        received, lost = counts()
        print(f'published {n}: the node received {received} and counts {lost} lost')
        assert lost > 0 and received + lost == n
        values = diagnostics.values(name)
        assert values['reference_lost'] == '0' and values['reference_plan_lost'] == '0'
        assert diagnostics.statuses[name].level == 1  # WARN
        assert f'lost in DDS: {lost} odom' in diagnostics.statuses[name].message
        assert node.stop(signal.SIGINT) == 0
    finally:
        if node.proc.poll() is None:
            os.kill(node.proc.pid, signal.SIGCONT)
        node.stop(signal.SIGKILL)
