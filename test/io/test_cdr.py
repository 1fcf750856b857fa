"""The lean CDR codec (io/cdr.py) against the general one (rosbags): the same samples from every
input message of the sample bags and of the corpus, the same bytes for every output layout, and
a clear error for bytes that are not the message."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from cloe_ros.core.samples import OdometrySample, PathSample, PoseSample
from cloe_ros.io import cdr, messages
from cloe_ros.io.messages import TYPESTORE, MessageError
from cloe_ros.io.reader import BagReader
from test.corpus import B2, B3

REPO = Path(__file__).resolve().parents[2]
BAGS = [REPO / 'bags' / 'position', REPO / 'bags' / 'trajectory']
CORPUS = [b for b in (B2, B3) if b.is_dir()]  # two real flights (the golden test runs all)


def _xyz(v):
    return [v.x, v.y, v.z]


def _general_odometry(raw):
    msg = TYPESTORE.deserialize_cdr(raw, messages.ODOMETRY)
    pose, twist = msg.pose, msg.twist
    return (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, msg.header.frame_id,
            msg.child_frame_id, _xyz(pose.pose.position),
            [*_xyz(pose.pose.orientation), pose.pose.orientation.w], _xyz(twist.twist.linear),
            _xyz(twist.twist.angular), list(pose.covariance), list(twist.covariance))  # fmt: skip


def _lean_odometry(raw):
    s = cdr.decode_odometry(raw)
    return (s.stamp_ns, s.frame_id, s.child_frame_id, *(list(a) for a in (
        s.position, s.orientation, s.linear, s.angular, s.pose_covariance,
        s.twist_covariance)))  # fmt: skip


@pytest.mark.parametrize('bag', BAGS + CORPUS, ids=lambda p: p.name)
def test_every_input_message_decodes_as_rosbags_decodes_it(bag):
    """Every odometry and reference message: the same stamp, frames and values, and encoding the
    sample again gives rosbags' bytes for the message."""
    counted = {'odom': 0, 'reference': 0}
    with BagReader(bag) as reader:
        types = {name: info.msgtype for name, info in reader.topics.items()}
        for topic, _, raw in reader.messages():
            if types[topic] == messages.ODOMETRY:
                assert _lean_odometry(raw) == _general_odometry(raw)
                msg = TYPESTORE.deserialize_cdr(raw, messages.ODOMETRY)
                again = bytes(TYPESTORE.serialize_cdr(msg, messages.ODOMETRY))
                assert cdr.encode_odometry(cdr.decode_odometry(raw)) == again
                counted['odom'] += 1
            elif types[topic] == messages.POSE_STAMPED:
                msg = TYPESTORE.deserialize_cdr(raw, messages.POSE_STAMPED)
                s = cdr.decode_pose_stamped(raw)
                assert s.stamp_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                assert s.frame_id == msg.header.frame_id
                assert list(s.position) == _xyz(msg.pose.position)
                o = msg.pose.orientation
                assert list(s.orientation) == [o.x, o.y, o.z, o.w]
                again = bytes(TYPESTORE.serialize_cdr(msg, messages.POSE_STAMPED))
                assert cdr.encode_pose_stamped(s) == again
                counted['reference'] += 1
    assert counted['odom'] > 100 and counted['reference'] > 10


FRAMES = ['', 'w', 'map', 'odom', 'world', 'odom_frame_12']


@pytest.mark.parametrize('frame', FRAMES)
def test_output_layouts_are_rosbags_bytes(frame):
    """Every alignment a frame name can give, and paths of 0 to 4 poses."""
    rng = np.random.default_rng(len(frame))
    for child in ('', 'base_link'):
        o = OdometrySample(1_700_000_000_123_456_789, frame, child, *rng.normal(size=(4, 3)),
                           rng.normal(size=36), rng.normal(size=36))  # fmt: skip
        o = OdometrySample(o.stamp_ns, frame, child, o.position, rng.normal(size=4), o.linear,
                           o.angular, o.pose_covariance, o.twist_covariance)  # fmt: skip
        general = messages.Odometry(
            header=messages.Header(stamp=messages.ns_to_time(o.stamp_ns), frame_id=frame),
            child_frame_id=child,
            pose=messages.PoseWithCovariance(pose=_general_pose(o.position, o.orientation),
                                             covariance=o.pose_covariance),
            twist=messages.TwistWithCovariance(
                twist=messages.Twist(linear=messages.Vector3(*o.linear),
                                     angular=messages.Vector3(*o.angular)),
                covariance=o.twist_covariance),
        )  # fmt: skip
        assert cdr.encode_odometry(o) == bytes(TYPESTORE.serialize_cdr(general, messages.ODOMETRY))
    for n in range(5):
        stamps = 1_700_000_000 * 10**9 + 10**8 * np.arange(1, n + 1, dtype=np.int64)
        path = PathSample(1_700_000_000 * 10**9, frame, stamps, rng.normal(size=(n, 3)),
                          rng.normal(size=(n, 4)))  # fmt: skip
        general = messages.Path(
            header=messages.Header(stamp=messages.ns_to_time(path.stamp_ns), frame_id=frame),
            poses=[messages.PoseStamped(
                header=messages.Header(stamp=messages.ns_to_time(int(s)), frame_id=frame),
                pose=_general_pose(p, q)) for s, p, q in zip(stamps, path.positions,
                                                             path.orientations)])  # fmt: skip
        raw = bytes(TYPESTORE.serialize_cdr(general, messages.PATH))
        assert cdr.encode_path(path) == raw
        back = cdr.decode_path(raw)
        np.testing.assert_array_equal(back.stamps_ns, stamps)
        np.testing.assert_array_equal(back.positions, path.positions)
        assert cdr.path_length(raw) == n
    for dims in ([], [('a', 1)], [('pose', 3), ('stamp_s,radius_m', 2)]):
        size = int(np.prod([d[1] for d in dims])) if dims else 0
        data = rng.normal(size=size)
        strides = np.cumprod([d[1] for d in dims][::-1])[::-1] if dims else []
        general = messages.Float64MultiArray(
            layout=messages.MultiArrayLayout(dim=[
                messages.MultiArrayDimension(label=label, size=n, stride=int(st))
                for (label, n), st in zip(dims, strides)], data_offset=0), data=data)  # fmt: skip
        raw = bytes(TYPESTORE.serialize_cdr(general, messages.FLOAT64_MULTI_ARRAY))
        assert cdr.MultiArrayLayout([(lb, n, int(st)) for (lb, n), st in zip(dims, strides)]
                                    ).encode(data) == raw  # fmt: skip


@pytest.mark.parametrize('source', FRAMES)
def test_named_values_are_rosbags_bytes(source):
    """``cloe/parameters_named``: the layout built once per source and names gives the bytes of
    the ParameterEvent rosbags builds from message objects, for every alignment a source or a
    name can give, and decodes back to the values."""
    rng = np.random.default_rng(len(source))
    names = ['', 'a', 'theta_hat.x_theta.a_x', 'status.yaw', 'model.coupling.theta_x', 'abcdefg']
    for n in (0, 1, 2, len(names)):
        values = rng.normal(size=n) * 10.0 ** rng.integers(-6, 6, n)
        stamp = 1_700_000_000_987_654_321 + n
        empty = np.zeros(0)
        general = TYPESTORE.types['rcl_interfaces/msg/ParameterEvent'](
            stamp=messages.ns_to_time(stamp), node=source, changed_parameters=[],
            deleted_parameters=[], new_parameters=[
                TYPESTORE.types['rcl_interfaces/msg/Parameter'](
                    name=name, value=TYPESTORE.types['rcl_interfaces/msg/ParameterValue'](
                        type=3, bool_value=False, integer_value=0, double_value=float(v),
                        string_value='', byte_array_value=np.zeros(0, np.uint8),
                        bool_array_value=np.zeros(0, bool),
                        integer_array_value=np.zeros(0, np.int64), double_array_value=empty,
                        string_array_value=[]))
                for name, v in zip(names[:n], values)])  # fmt: skip
        raw = bytes(TYPESTORE.serialize_cdr(general, messages.PARAMETER_EVENT))
        layout = cdr.NamedValuesLayout(source, names[:n])
        assert layout.encode(stamp, values) == raw
        assert layout.encode(stamp, values) == raw  # the template is not changed by a message
        back = messages.decode_named_values(messages.encode_named_values(stamp, source,
                                                                         names[:n], values))
        assert back[:3] == (stamp, source, names[:n])
        np.testing.assert_array_equal(back[3], values)
    with pytest.raises(ValueError, match='6 names for 2 values'):
        cdr.NamedValuesLayout(source, names).encode(0, np.zeros(2))


def _general_markers(stamp_ns, frame_id, positions, radii, lifetime_ns, every=5):
    """The prediction markers built as rosbags message objects (the general codec)."""
    m = messages
    sec, nanosec = divmod(lifetime_ns, 1_000_000_000)

    def marker(ns, marker_id, kind, position, scale, rgba, points=()):
        return m.Marker(
            header=m.Header(stamp=m.ns_to_time(stamp_ns), frame_id=frame_id), ns=ns,
            id=marker_id, type=kind, action=0, pose=_general_pose(position, (0, 0, 0, 1.0)),
            scale=m.Vector3(x=scale, y=scale, z=scale), color=m.ColorRGBA(*rgba),
            lifetime=m.Duration(sec=sec, nanosec=nanosec), frame_locked=False,
            points=[m.Point(*map(float, p)) for p in points], colors=[], texture_resource='',
            texture=m.CompressedImage(header=m.Header(stamp=m.Time(sec=0, nanosec=0),
                                                      frame_id=''),
                                      format='', data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text='', mesh_resource='',
            mesh_file=m.MeshFile(filename='', data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False,
        )  # fmt: skip

    markers = [marker('prediction', 0, 4, np.zeros(3), 0.02, (0.1, 0.5, 1.0, 0.9), positions)]
    for i, k in enumerate(range(every - 1, len(positions), every), start=1):
        markers.append(marker('prediction_radius', i, 2, positions[k], 2.0 * float(radii[k]),
                              (0.1, 0.5, 1.0, 0.15)))  # fmt: skip
    return bytes(TYPESTORE.serialize_cdr(m.MarkerArray(markers=markers), messages.MARKER_ARRAY))


@pytest.mark.parametrize('frame', ['world', 'map', 'odom_7', ''])
@pytest.mark.parametrize('poses', [0, 1, 4, 5, 12, 30])
def test_prediction_markers_are_rosbags_bytes(frame, poses):
    rng = np.random.default_rng(poses)
    positions, radii = rng.normal(size=(poses, 3)), rng.random(poses)
    stamp = 1_700_000_000_123_456_789
    raw = messages.encode_prediction_markers(stamp, frame, positions, radii, 1_500_000_000)
    assert raw == _general_markers(stamp, frame, positions, radii, 1_500_000_000)
    back = TYPESTORE.deserialize_cdr(raw, messages.MARKER_ARRAY).markers
    assert len(back) == 1 + poses // 5
    points = np.array([[p.x, p.y, p.z] for p in back[0].points]).reshape(-1, 3)
    np.testing.assert_array_equal(points, positions)


def _general_pose(p, q):
    return messages.Pose(position=messages.Point(*map(float, p)),
                         orientation=messages.Quaternion(*map(float, q)))  # fmt: skip


def _odometry_bytes(frame='world'):
    return cdr.encode_odometry(OdometrySample(5 * 10**9, frame, 'base_link', np.zeros(3),
                                              np.array([0, 0, 0, 1.0]), np.zeros(3),
                                              np.zeros(3)))  # fmt: skip


@pytest.mark.parametrize(('mangle', 'reason'), [
    (lambda b: b[:40], 'truncated'),
    (lambda b: b[:2], 'shorter than a CDR header'),
    (lambda b: b'\x07\x07' + b[2:], 'not a CDR encapsulation'),
    (lambda b: b[:8] + struct.pack('<I', 10**9) + b[12:], 'nanosec 1000000000 is not below 1e9'),
    (lambda b: b[:16] + b'\xff\xfe' + b[18:], 'not UTF-8'),
    (lambda b: b[:21] + b'x' + b[22:], 'terminating NUL'),
    (lambda b: b + bytes(16), 'bytes left over'),
])  # fmt: skip
def test_bytes_that_are_not_odometry_are_a_clear_error(mangle, reason):
    with pytest.raises(MessageError, match=reason):
        messages.decode_odometry(mangle(_odometry_bytes()))
    # the same header in a reference: its quick path takes none of them either
    pose = cdr.encode_pose_stamped(PoseSample(5 * 10**9, 'world', np.zeros(3),
                                              np.array([0, 0, 0, 1.0])))  # fmt: skip
    with pytest.raises(MessageError, match=reason):
        messages.decode_pose_stamped(mangle(pose))


@pytest.mark.parametrize('frame', FRAMES)
def test_a_reference_decodes_as_rosbags_decodes_it_whatever_its_frames_length(frame):
    """Every alignment of the pose after the frame name, little and big endian (the big one
    through the checking reader), as bytes and as a memoryview."""
    rng = np.random.default_rng(len(frame))
    q = rng.normal(size=4)
    stamp = 1_700_000_000_123_456_789
    sample = PoseSample(stamp, frame, rng.normal(size=3), q / np.linalg.norm(q))
    raw = cdr.encode_pose_stamped(sample)
    msg = TYPESTORE.deserialize_cdr(raw, messages.POSE_STAMPED)
    big = bytes(TYPESTORE.serialize_cdr(msg, messages.POSE_STAMPED, little_endian=False))
    for given in (raw, memoryview(raw), big):
        got = cdr.decode_pose_stamped(given)
        assert (got.stamp_ns, got.frame_id) == (sample.stamp_ns, frame)
        assert list(got.position) == list(sample.position)
        assert list(got.orientation) == list(sample.orientation)


def test_pose_bytes_are_not_odometry_and_big_endian_decodes():
    pose = cdr.encode_pose_stamped(PoseSample(1, 'world', np.ones(3), np.array([0, 0, 0, 1.0])))
    with pytest.raises(MessageError, match='cannot decode 84 bytes as nav_msgs/msg/Odometry'):
        messages.decode_odometry(pose)
    msg = TYPESTORE.deserialize_cdr(_odometry_bytes(), messages.ODOMETRY)
    big = bytes(TYPESTORE.serialize_cdr(msg, messages.ODOMETRY, little_endian=False))
    assert big[:2] == b'\x00\x00'
    assert _lean_odometry(big) == _lean_odometry(_odometry_bytes())


def test_a_huge_plan_is_refused_before_its_poses_are_decoded():
    """The pose count is read first: 20k poses claimed in a 40-byte message, or more than the
    bound, fail at once."""
    poses = np.tile([0, 0, 0, 1.0], (3, 1))
    path = cdr.encode_path(
        PathSample(1, 'world', np.arange(1, 4, dtype=np.int64), np.zeros((3, 3)), poses)
    )
    with pytest.raises(MessageError, match='3 poses, more than 2'):
        messages.decode_path(path, max_poses=2)
    count_at = 4 + 8 + 4 + len(b'world\x00') + 2  # header, then the count aligned to 4
    lying = path[:count_at] + struct.pack('<I', 20_000) + path[count_at + 4:]
    with pytest.raises(MessageError, match='20000 poses cannot fit'):
        messages.decode_path(lying)


@pytest.mark.parametrize('text', ['', 'a', 'abcd', 'theta_hat.x_theta.a_x\nz', 'héllo ✓'])
def test_a_string_is_rosbags_bytes(text):
    want = bytes(TYPESTORE.serialize_cdr(TYPESTORE.types[messages.STRING](data=text),
                                         messages.STRING))  # fmt: skip
    assert messages.encode_string(text) == want
    assert messages.decode_string(want) == text


@pytest.mark.parametrize('statuses', [
    [],
    [messages.Status(messages.OK, '', '', '', ())],
    [messages.Status(messages.WARN, 'cloe_inference: /uav1', 'running; 2 input(s) rejected',
                     '/uav1', (('algorithm', 'cloe_iv'), ('rejected: wrong frame', '2'),
                               ('odom_silent_s', ''))),
     messages.Status(messages.ERROR, 'nœud: /ü', 'ĉu ĝi funkcias? 飛行', 'x' * 7, (('k', 'v'),)),
     messages.Status(messages.STALE, 'a', 'bc', 'def', ())],
])  # fmt: skip
def test_diagnostics_are_rosbags_bytes(statuses):
    types = TYPESTORE.types
    general = types[messages.DIAGNOSTIC_ARRAY](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=1_700_000_000, nanosec=123),
            frame_id=''),
        status=[types['diagnostic_msgs/msg/DiagnosticStatus'](
            level=s.level, name=s.name, message=s.message, hardware_id=s.hardware_id,
            values=[types['diagnostic_msgs/msg/KeyValue'](key=k, value=v) for k, v in s.values])
            for s in statuses],
    )  # fmt: skip
    raw = messages.encode_diagnostics(1_700_000_000 * 10**9 + 123, statuses)
    assert raw == bytes(TYPESTORE.serialize_cdr(general, messages.DIAGNOSTIC_ARRAY))
    assert messages.decode_diagnostics(raw) == (1_700_000_000 * 10**9 + 123, statuses)
    with pytest.raises(MessageError, match='level is a byte, got 256'):
        messages.encode_diagnostics(0, [messages.Status(256, '', '', '', ())])
