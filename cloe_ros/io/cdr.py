"""Fixed-layout messages straight from and into CDR bytes, without building message objects.

The contract's inputs (``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``, ``nav_msgs/Path``)
and outputs are decoded and encoded here on the hot path of the node and of ``cloe infer``:
``struct`` for the header and strings, one ``numpy.frombuffer`` for the block of doubles. The
bytes and samples are those of the general rosbags codec (io/messages.py), which stays the reader
of everything else; the tests check both agree on every message of the sample bags.

CDR (XCDR1, little or big endian as the encapsulation header says): after the 4-byte header each
primitive is aligned to its own size, relative to the end of the header. A ``std_msgs/Header`` is
``int32 sec, uint32 nanosec, string frame_id`` and a string is ``uint32 length`` (with the NUL),
its bytes, and the NUL.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from cloe_ros.core.samples import (
    MAX_STAMP_NS,
    MIN_STAMP_NS,
    OdometrySample,
    PathSample,
    PoseSample,
)
from cloe_ros.io.errors import MessageError

NS = 1_000_000_000
LITTLE = b'\x00\x01\x00\x00'  # CDR_LE, the encapsulation rclpy and rosbags write
BIG = b'\x00\x00\x00\x00'  # CDR_BE
_ENDIAN = {LITTLE[:2]: '<', BIG[:2]: '>'}


class _Reader:
    """A cursor over the body of a CDR message (offsets relative to the end of its header)."""

    __slots__ = ('buf', 'end', 'fmt', 'pos', 'what')

    def __init__(self, raw: bytes | memoryview, what: str) -> None:
        buf = memoryview(raw).cast('B') if isinstance(raw, memoryview) else memoryview(raw)
        if len(buf) < 4:
            msg = f'cannot decode {len(buf)} bytes as {what}: shorter than a CDR header'
            raise MessageError(msg)
        fmt = _ENDIAN.get(bytes(buf[:2]))
        if fmt is None:
            msg = f'cannot decode {len(buf)} bytes as {what}: not a CDR encapsulation'
            raise MessageError(msg)
        self.buf, self.end, self.fmt, self.pos, self.what = buf, len(buf), fmt, 4, what

    def _fail(self, why: str) -> MessageError:
        return MessageError(f'cannot decode {self.end} bytes as {self.what}: {why}')

    def align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def _need(self, n: int) -> None:
        if self.pos + n > self.end:
            raise self._fail(f'truncated at byte {self.pos} (needs {n} more)')

    def uint32(self) -> int:
        self.align(4)
        self._need(4)
        (value,) = struct.unpack_from(self.fmt + 'I', self.buf, self.pos)
        self.pos += 4
        return value

    def stamp_ns(self) -> int:
        self.align(4)
        self._need(8)
        sec, nanosec = struct.unpack_from(self.fmt + 'iI', self.buf, self.pos)
        self.pos += 8
        if nanosec >= NS:
            raise self._fail(f'invalid stamp: nanosec {nanosec} is not below 1e9 (sec {sec})')
        return sec * NS + nanosec

    def string(self) -> str:
        n = self.uint32()
        if n == 0:
            raise self._fail('a string without its terminating NUL')
        self._need(n)
        data = self.buf[self.pos : self.pos + n]
        self.pos += n
        if data[-1] != 0:
            raise self._fail('a string without its terminating NUL')
        try:
            return bytes(data[:-1]).decode()
        except UnicodeDecodeError as err:
            raise self._fail(f'a string that is not UTF-8 ({err})') from err

    def doubles(self, n: int) -> np.ndarray:
        self.align(8)
        self._need(8 * n)
        out = np.frombuffer(self.buf, dtype=self.fmt + 'f8', count=n, offset=self.pos)
        self.pos += 8 * n
        return out.astype(float) if self.fmt == '>' else out.copy()

    def done(self) -> None:
        # rclpy may pad a message to a multiple of 4 bytes; anything more is not this type
        if self.end - self.pos > 3:
            raise self._fail(f'{self.end - self.pos} bytes left over')


_STAMP = struct.Struct('<iI')  # a stamp, little endian
_LENGTH = struct.Struct('<I')


def _quick_string(raw: bytes, at: int) -> tuple[str, int] | None:
    """The string whose length is at ``at`` (aligned to 4) of the little-endian ``raw``, and
    the offset just after it; None where the checking reader must decide (cut short, no
    terminating NUL, not UTF-8)."""
    if at + 4 > len(raw):
        return None
    (n,) = _LENGTH.unpack_from(raw, at)
    after = at + 4 + n
    if not n or after > len(raw) or raw[after - 1] != 0:
        return None
    try:
        return raw[at + 4 : after - 1].decode(), after
    except UnicodeDecodeError:
        return None


def _quick_doubles(raw: bytes, at: int, n: int) -> np.ndarray | None:
    """The ``n`` little-endian doubles from ``at`` (aligned up to 8) that end ``raw`` (but for
    rclpy's padding to 4); None where they do not."""
    start = at + (-(at - 4)) % 8
    left = len(raw) - start - 8 * n
    if not 0 <= left <= 3:
        return None
    return np.frombuffer(raw, dtype='<f8', count=n, offset=start).copy()


def _quick_header(raw: bytes) -> tuple[int, str, int] | None:
    """The common case of a message that starts with a ``std_msgs/Header``, little endian:
    ``(stamp ns, frame, offset just after the frame)``, with a few struct calls; None where the
    checking reader (:class:`_Reader`) must decode it, and say what is wrong."""
    if len(raw) < 16 or raw[:2] != LITTLE[:2]:
        return None
    sec, nanosec = _STAMP.unpack_from(raw, 4)
    frame = _quick_string(raw, 12) if nanosec < NS else None
    return None if frame is None else (sec * NS + nanosec, *frame)


def decode_odometry(raw: bytes | memoryview) -> OdometrySample:
    """A ``nav_msgs/msg/Odometry`` (85 doubles after two strings)."""
    if type(raw) is not bytes:
        raw = bytes(raw)
    head = _quick_header(raw)
    if head is not None:  # (then the child frame and one frombuffer)
        stamp, frame, at = head
        child = _quick_string(raw, at + (-at) % 4)
        d = None if child is None else _quick_doubles(raw, child[1], 85)
        if d is not None:
            return OdometrySample(stamp, frame, child[0], d[0:3], d[3:7], d[43:46], d[46:49],
                                  d[7:43], d[49:85])  # fmt: skip
    r = _Reader(raw, 'nav_msgs/msg/Odometry')
    stamp = r.stamp_ns()
    frame, child = r.string(), r.string()
    d = r.doubles(85)
    r.done()
    return OdometrySample(stamp, frame, child, d[0:3], d[3:7], d[43:46], d[46:49],
                          d[7:43], d[49:85])  # fmt: skip


def decode_pose_stamped(raw: bytes | memoryview) -> PoseSample:
    """A ``geometry_msgs/msg/PoseStamped`` (7 doubles after one string)."""
    if type(raw) is not bytes:
        raw = bytes(raw)
    head = _quick_header(raw)
    if head is not None:
        stamp, frame, at = head
        d = _quick_doubles(raw, at, 7)
        if d is not None:
            return PoseSample(stamp, frame, d[0:3], d[3:7])
    r = _Reader(raw, 'geometry_msgs/msg/PoseStamped')
    stamp = r.stamp_ns()
    frame = r.string()
    d = r.doubles(7)
    r.done()
    return PoseSample(stamp, frame, d[0:3], d[3:7])


def path_length(raw: bytes | memoryview) -> int:
    """The number of poses of a ``nav_msgs/msg/Path``, read before any of them is decoded."""
    r = _Reader(raw, 'nav_msgs/msg/Path')
    r.stamp_ns()
    r.string()
    return r.uint32()


def decode_path(raw: bytes | memoryview, max_poses: int | None = None) -> PathSample:
    """A ``nav_msgs/msg/Path``; more than ``max_poses`` poses is a :class:`MessageError` raised
    before they are decoded."""
    r = _Reader(raw, 'nav_msgs/msg/Path')
    stamp = r.stamp_ns()
    frame = r.string()
    n = r.uint32()
    if max_poses is not None and n > max_poses:
        raise r._fail(f'{n} poses, more than {max_poses}')
    if n * 64 > r.end:  # each pose takes at least 64 bytes
        raise r._fail(f'{n} poses cannot fit')
    stamps = np.empty(n, dtype=np.int64)
    values = np.empty((n, 7))
    for i in range(n):
        stamps[i] = r.stamp_ns()
        r.string()  # each pose's own frame: the path's, by the contract
        values[i] = r.doubles(7)
    r.done()
    return PathSample(stamp, frame, stamps, values[:, :3], values[:, 3:])


def _time_bytes(stamp_ns: int) -> bytes:
    """A ``builtin_interfaces/Time``, little-endian: ``int32 sec, uint32 nanosec``."""
    stamp_ns = int(stamp_ns)
    if not MIN_STAMP_NS <= stamp_ns <= MAX_STAMP_NS:
        msg = (f'stamp {stamp_ns} ns is beyond what a ROS message carries (int32 seconds, '
               '2038-01-19)')  # fmt: skip
        raise MessageError(msg)
    return struct.pack('<iI', *divmod(stamp_ns, NS))


class _Writer:
    """Little-endian CDR, built into one bytearray."""

    __slots__ = ('buf',)

    def __init__(self) -> None:
        self.buf = bytearray(LITTLE)

    def align(self, size: int) -> None:
        self.buf += bytes(-(len(self.buf) - 4) % size)

    def stamp(self, stamp_ns: int) -> None:
        self.align(4)
        self.buf += _time_bytes(stamp_ns)

    def string(self, text: str) -> None:
        data = text.encode()
        self.align(4)
        self.buf += struct.pack('<I', len(data) + 1) + data + b'\x00'

    def uint32(self, value: int) -> None:
        self.align(4)
        self.buf += struct.pack('<I', value)

    def doubles(self, values) -> None:
        self.align(8)
        self.buf += np.ascontiguousarray(values, dtype='<f8').tobytes()

    def pack(self, align: int, fmt: struct.Struct, *values) -> None:
        self.align(align)
        self.buf += fmt.pack(*values)


_ZEROS36 = np.zeros(36)


def encode_string(text: str) -> bytes:
    """A ``std_msgs/String``."""
    w = _Writer()
    w.string(text)
    return bytes(w.buf)


def encode_diagnostic_array(stamp_ns: int, statuses: Sequence) -> bytes:
    """CDR of a ``diagnostic_msgs/msg/DiagnosticArray`` (its header's frame empty) from
    ``statuses``, each with ``level`` (a byte), ``name``, ``message``, ``hardware_id`` and
    ``values`` (key, value pairs): :class:`~cloe_ros.io.messages.Status`."""
    w = _Writer()
    w.stamp(stamp_ns)
    w.string('')
    w.uint32(len(statuses))
    for status in statuses:
        level = int(status.level)
        if not 0 <= level <= 255:
            msg = f'a DiagnosticStatus level is a byte, got {level}'
            raise MessageError(msg)
        w.buf.append(level)  # (a byte: no alignment)
        w.string(status.name)
        w.string(status.message)
        w.string(status.hardware_id)
        w.uint32(len(status.values))
        for key, value in status.values:
            w.string(key)
            w.string(value)
    return bytes(w.buf)


def encode_odometry(sample: OdometrySample) -> bytes:
    """CDR of a ``nav_msgs/msg/Odometry``; covariances default to zeros (unknown)."""
    w = _Writer()
    w.stamp(sample.stamp_ns)
    w.string(sample.frame_id)
    w.string(sample.child_frame_id)
    pose_cov = _ZEROS36 if sample.pose_covariance is None else sample.pose_covariance
    twist_cov = _ZEROS36 if sample.twist_covariance is None else sample.twist_covariance
    w.doubles(np.concatenate([
        np.asarray(sample.position, float), np.asarray(sample.orientation, float),
        np.asarray(pose_cov, float).ravel(), np.asarray(sample.linear, float),
        np.asarray(sample.angular, float), np.asarray(twist_cov, float).ravel(),
    ]))  # fmt: skip
    return bytes(w.buf)


@lru_cache(maxsize=256)
def _odometry_frames(frame_id: str, child_frame_id: str) -> bytes:
    """The bytes of an Odometry between its stamp and its 85 doubles: the two frames, padded."""
    w = _Writer()
    w.stamp(0)
    w.string(frame_id)
    w.string(child_frame_id)
    w.align(8)
    return bytes(w.buf[12:])


def encode_odometry_values(stamp_ns: int, frame_id: str, child_frame_id: str,
                           values: np.ndarray) -> bytes:  # fmt: skip
    """:func:`encode_odometry` from the message's 85 doubles (85,) in field order (position,
    orientation, pose covariance, linear, angular, twist covariance)."""
    values = np.ascontiguousarray(values, dtype='<f8')
    if values.shape != (85,):
        msg = f'an Odometry carries 85 doubles, got {values.shape}'
        raise ValueError(msg)
    return (LITTLE + _time_bytes(stamp_ns) + _odometry_frames(frame_id, child_frame_id)
            + values.tobytes())  # fmt: skip


def encode_pose_stamped(sample: PoseSample) -> bytes:
    """CDR of a ``geometry_msgs/msg/PoseStamped``."""
    w = _Writer()
    w.stamp(sample.stamp_ns)
    w.string(sample.frame_id)
    w.doubles(np.concatenate([sample.position, sample.orientation]))
    return bytes(w.buf)


def encode_path(sample: PathSample) -> bytes:
    """CDR of a ``nav_msgs/msg/Path`` whose poses carry their own stamps and the path's frame,
    its poses written as structured arrays (stamp, frame, padding to 8, seven doubles)."""
    w = _Writer()
    w.stamp(sample.stamp_ns)
    w.string(sample.frame_id)
    stamps = np.asarray(sample.stamps_ns, dtype=np.int64)
    n = len(stamps)
    w.uint32(n)
    if n == 0:
        return bytes(w.buf)
    if stamps.min() < MIN_STAMP_NS or stamps.max() > MAX_STAMP_NS:
        w.stamp(int(stamps.max() if stamps.max() > MAX_STAMP_NS else stamps.min()))  # raises
    frame = sample.frame_id.encode() + b'\x00'
    # each pose's doubles end 8-aligned, so every pose after the first starts at the same
    # alignment: two structured arrays, the first pose and the others
    first = _pose_dtype(len(w.buf) - 4, len(frame))
    rest = _pose_dtype(len(w.buf) - 4 + first.itemsize, len(frame))
    values = np.concatenate([sample.positions, sample.orientations], axis=1)
    head = _fill(np.zeros(1, dtype=first), stamps[:1], frame, values[:1])
    tail = _fill(np.zeros(n - 1, dtype=rest), stamps[1:], frame, values[1:])
    return bytes(w.buf) + head.tobytes() + tail.tobytes()


def _pose_dtype(offset: int, frame_len: int) -> np.dtype:
    """A PoseStamped (its frame ``frame_len`` bytes with the NUL) starting at body ``offset`` (a
    multiple of 4): stamp, frame, padding to 8, seven doubles; padded to a multiple of 4."""
    values = offset + 12 + frame_len
    values += -values % 8
    end = values + 56
    return np.dtype({
        'names': ['sec', 'nanosec', 'len', 'frame', 'values'],
        'formats': ['<i4', '<u4', '<u4', f'V{frame_len}', ('<f8', (7,))],
        'offsets': [0, 4, 8, 12, values - offset],
        'itemsize': end - offset,
    })  # fmt: skip


def _fill(poses: np.ndarray, stamps: np.ndarray, frame: bytes, values: np.ndarray) -> np.ndarray:
    poses['sec'], poses['nanosec'] = np.divmod(stamps, NS)
    poses['len'] = len(frame)
    poses['frame'] = np.frombuffer(frame, dtype=f'V{len(frame)}')[0]
    poses['values'] = values
    return poses


class MultiArrayLayout:
    """The bytes of a ``std_msgs/msg/Float64MultiArray``'s layout, built once: encoding a message
    is then the layout, the data's length and its doubles."""

    def __init__(self, dims: Sequence[tuple[str, int, int]], data_offset: int = 0) -> None:
        w = _Writer()
        w.uint32(len(dims))
        for label, size, stride in dims:
            w.string(label)
            w.uint32(size)
            w.uint32(stride)
        w.uint32(data_offset)
        self._head = bytes(w.buf)

    def encode(self, data: np.ndarray) -> bytes:
        data = np.ascontiguousarray(data, dtype='<f8').ravel()
        w = _Writer()
        w.buf = bytearray(self._head)
        w.uint32(len(data))
        if len(data):  # (no padding before an empty sequence, as rosbags writes it)
            w.align(8)
        return bytes(w.buf) + data.tobytes()


class NamedValuesLayout:
    """The bytes of a ``rcl_interfaces/msg/ParameterEvent`` carrying fixed names as doubles
    (io/messages.py ``encode_named_values``), built once per source and names: encoding a message
    is then a copy, the stamp and the doubles written in place.

    Each ``Parameter`` is ``string name`` and a ``ParameterValue``: ``uint8 type`` (3, double),
    ``bool``, ``int64``, ``float64 double_value``, ``string`` and five empty sequences; where the
    doubles fall depends only on the names, not on the values or the stamp.
    """

    PARAMETER_DOUBLE = 3

    def __init__(self, source: str, names: Sequence[str]) -> None:
        w = _Writer()
        w.buf += bytes(8)  # the stamp, written per message
        w.string(source)
        w.uint32(len(names))
        at = []
        for name in names:
            w.string(name)
            w.buf += bytes((self.PARAMETER_DOUBLE, 0))  # type, bool_value
            w.align(8)
            w.buf += bytes(8)  # integer_value
            at.append(len(w.buf))
            w.buf += bytes(8)  # double_value
            w.string('')  # string_value
            for _ in range(5):  # byte, bool, integer, double, string arrays: empty
                w.uint32(0)
        w.uint32(0)  # changed_parameters
        w.uint32(0)  # deleted_parameters
        self._template = bytes(w.buf)
        self._bytes = (np.asarray(at, dtype=np.intp)[:, None] + np.arange(8)).ravel()
        self.size = len(names)

    def encode(self, stamp_ns: int, values: np.ndarray) -> bytes:
        values = np.ascontiguousarray(values, dtype='<f8').ravel()
        if values.size != self.size:
            msg = f'{self.size} names for {values.size} values'
            raise ValueError(msg)
        buf = bytearray(self._template)
        buf[4:12] = _time_bytes(stamp_ns)
        np.frombuffer(buf, dtype=np.uint8)[self._bytes] = values.view(np.uint8)
        return bytes(buf)


# ------------------------------------------------------------- visualization_msgs/MarkerArray

MARKER_ADD, MARKER_SPHERE, MARKER_LINE_STRIP = 0, 2, 4
_MARKER_KIND = struct.Struct('<iii')  # id, type, action
_COLOR_LIFETIME = struct.Struct('<4fiI?')  # color (RGBA), lifetime (sec, nanosec), frame_locked
#: A marker's fields after its points, all empty: colors, texture_resource, texture (header stamp
#: 0, frame '', format '', no data), uv_coordinates, text, mesh_resource, mesh_file ('', no
#: data), mesh_use_embedded_materials false. Every one is 4-aligned, so the same bytes follow
#: any points.
_MARKER_TAIL = struct.pack(
    '<I' 'I1s3x' 'iI' 'I1s3x' 'I1s3x' 'I' 'I' 'I1s3x' 'I1s3x' 'I1s3x' 'I' '?',
    0, 1, b'', 0, 0, 1, b'', 1, b'', 0, 0, 1, b'', 1, b'', 1, b'', 0, False,
)


def _marker(w: _Writer, head: bytes, ns: str, marker_id: int, kind: int, scale: float, rgba,
            lifetime: tuple[int, int], n_points: int) -> tuple[int, int, int]:  # fmt: skip
    """One ``visualization_msgs/msg/Marker`` (action ADD, identity orientation, at the origin,
    ``n_points`` points of zero) into ``w``; ``head`` is its header's bytes (stamp and frame),
    written 4-aligned. Returns where its stamp, its pose and its points start in ``w``."""
    w.align(4)
    stamp_at = len(w.buf)
    w.buf += head
    w.string(ns)
    w.pack(4, _MARKER_KIND, marker_id, kind, MARKER_ADD)
    w.align(8)
    pose_at = len(w.buf)
    w.doubles((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, scale, scale, scale))  # pose, scale
    w.pack(4, _COLOR_LIFETIME, *rgba, *lifetime, False)
    w.uint32(n_points)
    if n_points:
        w.align(8)
    points_at = len(w.buf)
    w.buf += bytes(24 * n_points)
    w.align(4)
    w.buf += _MARKER_TAIL
    return stamp_at, pose_at, points_at


class PredictionMarkersLayout:
    """The bytes of the ``visualization_msgs/msg/MarkerArray`` of
    :func:`encode_prediction_markers` for one frame, number of poses, lifetime and sphere
    spacing, built once: encoding a prediction is then a copy, its stamp, positions and sphere
    diameters written in place."""

    def __init__(self, frame_id: str, n_poses: int, lifetime_ns: int, every: int) -> None:
        head = _Writer()
        head.stamp(0)
        head.string(frame_id)
        head = bytes(head.buf[4:])  # (4-aligned at its start, so it is the same bytes anywhere)
        lifetime = divmod(int(lifetime_ns), NS)
        self.spheres = np.arange(every - 1, n_poses, every)
        w = _Writer()
        w.uint32(1 + len(self.spheres))
        stamp_at, _, points_at = _marker(w, head, 'prediction', 0, MARKER_LINE_STRIP, 0.02,
                                         (0.1, 0.5, 1.0, 0.9), lifetime, n_poses)  # fmt: skip
        stamps, doubles = [stamp_at], [points_at + 8 * np.arange(3 * n_poses)]
        for i in range(1, len(self.spheres) + 1):
            stamp_at, pose_at, _ = _marker(w, head, 'prediction_radius', i, MARKER_SPHERE, 0.0,
                                           (0.1, 0.5, 1.0, 0.15), lifetime, 0)  # fmt: skip
            stamps.append(stamp_at)
            doubles += [pose_at + 8 * np.arange(3), pose_at + 8 * np.arange(7, 10)]
        self._template = bytes(w.buf)
        self._stamp_bytes = (np.array(stamps)[:, None] + np.arange(8)).ravel()
        self._double_bytes = (np.concatenate(doubles)[:, None] + np.arange(8)).ravel()
        self.n_poses = n_poses

    def encode(self, stamp_ns: int, positions: np.ndarray, radii: np.ndarray) -> bytes:
        positions = np.asarray(positions, dtype=float)
        if positions.shape != (self.n_poses, 3):
            msg = f'{self.n_poses} poses of 3 coordinates, got positions {positions.shape}'
            raise ValueError(msg)
        diameters = 2.0 * np.asarray(radii, dtype=float)[self.spheres]
        spheres = np.concatenate([positions[self.spheres], np.repeat(diameters[:, None], 3, 1)],
                                 axis=1)  # fmt: skip
        values = np.concatenate([positions.ravel(), spheres.ravel()]).astype('<f8')
        buf = bytearray(self._template)
        view = np.frombuffer(buf, dtype=np.uint8)
        view[self._stamp_bytes] = np.tile(np.frombuffer(_time_bytes(stamp_ns), np.uint8),
                                          len(self.spheres) + 1)  # fmt: skip
        view[self._double_bytes] = values.view(np.uint8)
        return bytes(buf)


@lru_cache(maxsize=64)
def _markers_layout(frame_id: str, n_poses: int, lifetime_ns: int,
                    every: int) -> PredictionMarkersLayout:  # fmt: skip
    return PredictionMarkersLayout(frame_id, n_poses, lifetime_ns, every)


def encode_prediction_markers(
    stamp_ns: int, frame_id: str, positions: np.ndarray, radii: np.ndarray, lifetime_ns: int,
    every: int = 5,
) -> bytes:  # fmt: skip
    """CDR of the ``visualization_msgs/msg/MarkerArray`` of
    :func:`cloe_ros.io.messages.encode_prediction_markers`: a line strip of ``positions`` (K, 3)
    and a sphere of diameter ``2 radii[k]`` at every ``every``-th pose."""
    layout = _markers_layout(frame_id, len(positions), int(lifetime_ns), every)
    return layout.encode(stamp_ns, positions, radii)
