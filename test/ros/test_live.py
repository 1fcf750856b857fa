"""`cloe live`: the package's topics relayed to a Foxglove WebSocket client.

Publishers in this process send the package's messages (encoded by its own encoders) on the
interface contract's topics, for two vehicles; the relay runs in-process on the same private
domain, and a WebSocket client (the ``websockets`` package, speaking the Foxglove protocol)
checks the advertised channels (topic, ``cdr``, ``ros2msg`` schema with the full definition) and
one message per channel, byte for byte.
"""

from __future__ import annotations

import json
import struct
import subprocess
import threading
import time

import numpy as np
import pytest
from ros_helpers import executable, private_domain, reserve_domain_id, ros_env

from cloe_ros.core.samples import OdometrySample, PathSample, PoseSample
from cloe_ros.io import messages
from cloe_ros.ros.common import qos

foxglove = pytest.importorskip('foxglove', reason='cloe live needs foxglove-sdk')
websockets_client = pytest.importorskip('websockets.sync.client')

pytestmark = pytest.mark.ros

SUBPROTOCOL = 'foxglove.sdk.v1'  # what foxglove-sdk's server speaks
STAMP = 1_700_000_000 * 10**9


def contract_messages(vehicle: str) -> dict[str, tuple[str, bytes]]:
    """topic -> (type, CDR) for one vehicle's inputs and outputs."""
    q = np.array([0.0, 0.0, 0.0, 1.0])
    odom = OdometrySample(STAMP, 'world', 'base_link', np.array([1.0, 2.0, 3.0]), q,
                          np.zeros(3), np.zeros(3))  # fmt: skip
    path = PathSample(STAMP, 'world', STAMP + np.arange(3) * 10**8,
                      np.tile([1.0, 2.0, 3.0], (3, 1)), np.tile(q, (3, 1)))  # fmt: skip
    out = {
        f'{vehicle}/odom': (messages.ODOMETRY, messages.encode_odometry(odom)),
        f'{vehicle}/reference': (
            messages.POSE_STAMPED,
            messages.encode_pose_stamped(PoseSample(STAMP, 'world', np.ones(3), q)),
        ),
        f'{vehicle}/cloe/state': (messages.ODOMETRY, messages.encode_odometry(odom)),
        f'{vehicle}/cloe/prediction': (messages.PATH, messages.encode_path(path)),
        f'{vehicle}/cloe/parameters': (
            messages.FLOAT64_MULTI_ARRAY,
            messages.encode_float64_multi_array(['theta.a', 'theta.b'], np.array([1.0, 2.0])),
        ),
    }
    return out


def expected_messages() -> dict[str, tuple[str, bytes]]:
    out = {**contract_messages('/uav1'), **contract_messages('/uav2')}
    status = messages.Status(0, 'cloe_inference: /uav1', 'ok', '/uav1', (('steps', '1'),))
    out['/diagnostics'] = (messages.DIAGNOSTIC_ARRAY, messages.encode_diagnostics(STAMP, [status]))
    try:
        from rclpy.serialization import serialize_message
        from visualization_msgs.msg import Marker, MarkerArray
    except ImportError:  # ros-jazzy-visualization-msgs not installed: no markers to relay
        return out
    marker = Marker(type=Marker.SPHERE, action=Marker.ADD, ns='prediction', id=1)
    marker.header.frame_id = 'world'
    marker.scale.x = marker.scale.y = marker.scale.z = 0.4
    out['/uav1/cloe/prediction_markers'] = (
        'visualization_msgs/msg/MarkerArray',
        serialize_message(MarkerArray(markers=[marker])),
    )
    return out


def recv_json(ws, deadline: float) -> dict | None:
    """The next text frame (JSON), skipping binary ones; None at the deadline."""
    while time.monotonic() < deadline:
        try:
            frame = ws.recv(timeout=max(0.05, deadline - time.monotonic()))
        except TimeoutError:
            return None
        if isinstance(frame, str):
            return json.loads(frame)
    return None


@pytest.fixture
def relay_on_a_domain():
    """A private domain with publishers of ``expected_messages()`` (10 Hz, reliable; the
    parameters transient local, published once) and the relay serving on a free port."""
    from cloe_ros.ros.live_relay import Latch, LiveRelay
    from cloe_ros.ros.player_node import message_class

    expected = expected_messages()
    with private_domain('live_probe') as ros:
        pubs = {}
        for topic, (msgtype, _) in expected.items():
            latched = topic.endswith('/parameters')
            pubs[topic] = ros.node.create_publisher(
                message_class(msgtype), topic, qos(depth=10, transient_local=latched)
            )
        for topic, pub in pubs.items():
            if topic.endswith('/parameters'):
                pub.publish(expected[topic][1])  # once, before the relay exists

        def publish() -> None:
            for topic, pub in pubs.items():
                if not topic.endswith('/parameters'):
                    pub.publish(expected[topic][1])

        ros.node.create_timer(0.1, publish)
        context = foxglove.Context()
        latch = Latch()
        server = foxglove.start_server(
            host='127.0.0.1', port=0, context=context, server_listener=latch
        )
        relay = LiveRelay(context, context=ros.ctx, discovery_period=0.2, latch=latch)
        ros.executor.add_node(relay)
        spinner = threading.Thread(target=ros.executor.spin, daemon=True)
        spinner.start()
        try:
            yield expected, server.port, relay
        finally:
            server.stop()
            ros.executor.shutdown()
            spinner.join(timeout=10)
            relay.destroy_node()


def test_channels_and_one_message_per_channel(relay_on_a_domain):
    expected, port, relay = relay_on_a_domain
    url = f'ws://127.0.0.1:{port}'
    with websockets_client.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=60) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        deadline = time.monotonic() + 60
        channels = {}
        info = recv_json(ws, deadline)
        assert info is not None and info['op'] == 'serverInfo', info
        while not set(expected) <= set(channels):
            msg = recv_json(ws, deadline)
            assert msg is not None, f'advertised {sorted(channels)}, missing ' + str(
                sorted(set(expected) - set(channels))
            )
            if msg['op'] == 'advertise':
                channels.update({c['topic']: c for c in msg['channels']})
        assert '/rosout' not in channels and '/parameter_events' not in channels
        for topic, (msgtype, _) in expected.items():
            c = channels[topic]
            assert (c['encoding'], c['schemaEncoding'], c['schemaName']) == (
                'cdr',
                'ros2msg',
                msgtype,
            ), c
            definition, _ = messages.TYPESTORE.generate_msgdef(msgtype, ros_version=2)
            assert c['schema'] == definition
        subscriptions = {k: topic for k, topic in enumerate(sorted(expected))}
        ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': k, 'channelId': channels[topic]['id']} for k, topic in subscriptions.items()
        ]}))  # fmt: skip
        got: dict[str, bytes] = {}
        while set(got) != set(expected) and time.monotonic() < deadline:
            try:
                frame = ws.recv(timeout=max(0.05, deadline - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                sub_id, _log_time = struct.unpack_from('<IQ', frame, 1)
                got.setdefault(subscriptions[sub_id], frame[13:])
    assert set(got) == set(expected), f'no message on {sorted(set(expected) - set(got))}'
    for topic, (_, raw) in expected.items():
        assert got[topic] == raw, topic  # the CDR as published
    # the latched parameters, published once before the relay existed, came through its
    # transient-local subscription and were sent again when the client subscribed
    assert relay.relayed['/uav1/cloe/parameters'] == 1


def test_cloe_live_on_a_port_in_use(tmp_path):
    """As a process: a port another server holds ends `cloe live` with one ERROR line."""
    holder = foxglove.start_server(host='127.0.0.1', port=0, context=foxglove.Context())
    port = holder.port
    try:
        proc = subprocess.run(
            [executable('cloe'), 'live', '--host', '127.0.0.1', '--port', str(port)],
            env=ros_env(reserve_domain_id(), tmp_path / 'ros_log'),
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
    finally:
        holder.stop()
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f'ERROR: cannot serve on 127.0.0.1:{port}: ' in proc.stderr
    assert 'Address already in use' in proc.stderr and 'Traceback' not in proc.stderr


def test_cloe_live_refuses_a_bad_port(capsys):
    from cloe_ros.cli.main import main

    assert main(['live', '--port', '70000']) == 1
    assert 'ERROR: --port must be within [0, 65535], got 70000' in capsys.readouterr().err
