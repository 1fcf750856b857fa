"""CDR <-> samples for the topics of the interface contract (README), without rclpy.

The nodes (raw subscriptions and raw publishing) and the offline tools (bags) both go through these
functions, so the same bytes give the same samples and the same estimates give the same bytes.
The contract's messages and the outputs go through the lean codec (io/cdr.py); the others through
the rosbags type store of ROS 2 Jazzy, ``TYPESTORE``, and its message classes (``Odometry``,
``Header``, ...), all made on first use: the type store's import and construction take about
0.15 s of CPU, which ``cloe infer``, whose messages all have a lean codec, does not spend.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np

from cloe_ros.core.samples import (
    MAX_STAMP_NS,
    MIN_STAMP_NS,
    OdometrySample,
    PathSample,
    PoseSample,
)
from cloe_ros.io import cdr
from cloe_ros.io.errors import MessageError

ODOMETRY = 'nav_msgs/msg/Odometry'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
PATH = 'nav_msgs/msg/Path'
FLOAT64_MULTI_ARRAY = 'std_msgs/msg/Float64MultiArray'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
CLOCK = 'rosgraph_msgs/msg/Clock'
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
STRING = 'std_msgs/msg/String'
PARAMETER_EVENT = 'rcl_interfaces/msg/ParameterEvent'

#: The message classes of the type store this module offers, by name (``messages.Odometry``).
_CLASSES = {
    'Time': 'builtin_interfaces/msg/Time',
    'Header': 'std_msgs/msg/Header',
    'Point': 'geometry_msgs/msg/Point',
    'Quaternion': 'geometry_msgs/msg/Quaternion',
    'Vector3': 'geometry_msgs/msg/Vector3',
    'Pose': 'geometry_msgs/msg/Pose',
    'PoseStamped': POSE_STAMPED,
    'PoseWithCovariance': 'geometry_msgs/msg/PoseWithCovariance',
    'Twist': 'geometry_msgs/msg/Twist',
    'TwistWithCovariance': 'geometry_msgs/msg/TwistWithCovariance',
    'Odometry': ODOMETRY,
    'Path': PATH,
    'MultiArrayDimension': 'std_msgs/msg/MultiArrayDimension',
    'MultiArrayLayout': 'std_msgs/msg/MultiArrayLayout',
    'Float64MultiArray': FLOAT64_MULTI_ARRAY,
    'KeyValue': 'diagnostic_msgs/msg/KeyValue',
    'DiagnosticStatus': 'diagnostic_msgs/msg/DiagnosticStatus',
    'DiagnosticArray': DIAGNOSTIC_ARRAY,
    'Clock': CLOCK,
    'ColorRGBA': 'std_msgs/msg/ColorRGBA',
    'Duration': 'builtin_interfaces/msg/Duration',
    'Marker': 'visualization_msgs/msg/Marker',
    'MarkerArray': MARKER_ARRAY,
    'MeshFile': 'visualization_msgs/msg/MeshFile',
    'CompressedImage': 'sensor_msgs/msg/CompressedImage',
    'String': STRING,
}


@cache
def typestore():
    """rosbags' type store of ROS 2 Jazzy (``TYPESTORE``), made on first use."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def __getattr__(name: str):
    """``TYPESTORE`` and the message classes of ``_CLASSES``, on first use."""
    if name == 'TYPESTORE':
        return typestore()
    msgtype = _CLASSES.get(name)
    if msgtype is None:
        msg = f'module {__name__!r} has no attribute {name!r}'
        raise AttributeError(msg)
    return typestore().types[msgtype]


def stamp_to_ns(stamp) -> int:
    """A header stamp in ns; a ``nanosec`` of 1e9 or more is not a valid stamp."""
    nanosec = int(stamp.nanosec)
    if nanosec >= 1_000_000_000:
        msg = f'invalid stamp: nanosec {nanosec} is not below 1e9 (sec {int(stamp.sec)})'
        raise MessageError(msg)
    return int(stamp.sec) * 1_000_000_000 + nanosec


def ns_to_time(ns: int):
    """The builtin_interfaces/Time of ``ns``; a :class:`MessageError` beyond its range."""
    ns = int(ns)
    if not MIN_STAMP_NS <= ns <= MAX_STAMP_NS:
        msg = f'stamp {ns} ns is beyond what a ROS message carries (int32 seconds, 2038-01-19)'
        raise MessageError(msg)
    sec, nanosec = divmod(ns, 1_000_000_000)
    return typestore().types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)


def _deserialize(raw: bytes | memoryview, msgtype: str):
    try:
        return typestore().deserialize_cdr(raw, msgtype)
    except Exception as err:
        msg = f'cannot decode {len(raw)} bytes as {msgtype}: {err}'
        raise MessageError(msg) from err


def decode_odometry(raw: bytes | memoryview) -> OdometrySample:
    """Decode a CDR ``nav_msgs/msg/Odometry`` (lean codec, io/cdr.py)."""
    return cdr.decode_odometry(raw)


def decode_pose_stamped(raw: bytes | memoryview) -> PoseSample:
    """Decode a CDR ``geometry_msgs/msg/PoseStamped`` (lean codec, io/cdr.py)."""
    return cdr.decode_pose_stamped(raw)


def path_length(raw: bytes | memoryview) -> int:
    """The pose count of a CDR ``nav_msgs/msg/Path``, read before any pose is decoded."""
    return cdr.path_length(raw)


def decode_path(raw: bytes | memoryview, max_poses: int | None = None) -> PathSample:
    """Decode a CDR ``nav_msgs/msg/Path`` (lean codec, io/cdr.py); more than ``max_poses``
    poses is a :class:`MessageError` raised before they are decoded."""
    return cdr.decode_path(raw, max_poses)


def decode_float64_multi_array(raw: bytes | memoryview) -> tuple[list[str], np.ndarray]:
    """Labels of the layout's dimensions and the data of a ``std_msgs/msg/Float64MultiArray``."""
    msg = _deserialize(raw, FLOAT64_MULTI_ARRAY)
    return [d.label for d in msg.layout.dim], np.asarray(msg.data, dtype=float)


def decode_clock(raw: bytes | memoryview) -> int:
    """The time (ns) of a ``rosgraph_msgs/msg/Clock``."""
    return stamp_to_ns(_deserialize(raw, CLOCK).clock)


def encode_odometry(sample: OdometrySample) -> bytes:
    """CDR of a ``nav_msgs/msg/Odometry``; covariances default to zeros (unknown)."""
    return cdr.encode_odometry(sample)


def encode_pose_stamped(sample: PoseSample) -> bytes:
    """CDR of a ``geometry_msgs/msg/PoseStamped``."""
    return cdr.encode_pose_stamped(sample)


def encode_path(sample: PathSample) -> bytes:
    """CDR of a ``nav_msgs/msg/Path`` whose poses carry their own (future) stamps."""
    return cdr.encode_path(sample)


@lru_cache(maxsize=64)
def _labelled_layout(labels: tuple[str, ...]) -> cdr.MultiArrayLayout:
    return cdr.MultiArrayLayout([(name, 1, 1) for name in labels])


def encode_float64_multi_array(labels: Sequence[str], data: np.ndarray) -> bytes:
    """CDR of a ``std_msgs/msg/Float64MultiArray`` naming every entry.

    The layout has one dimension per entry (size 1, stride 1): ``layout.dim[i].label`` names
    ``data[i]``. It is built once per set of labels.
    """
    data = np.asarray(data, dtype=np.float64)
    if len(labels) != data.size:
        msg = f'{len(labels)} labels for {data.size} values'
        raise ValueError(msg)
    return _labelled_layout(tuple(labels)).encode(data)


@lru_cache(maxsize=64)
def _shaped_layout(dims: tuple[tuple[str, int], ...]) -> cdr.MultiArrayLayout:
    sizes = [n for _, n in dims]
    strides = np.cumprod(sizes[::-1])[::-1]
    return cdr.MultiArrayLayout([(label, n, int(st)) for (label, n), st in zip(dims, strides)])


def encode_multi_array(dims: Sequence[tuple[str, int]], data: np.ndarray) -> bytes:
    """CDR of a ``std_msgs/msg/Float64MultiArray`` of shape ``[size for _, size in dims]``,
    row-major (``dim[i].stride`` the product of the sizes from ``i`` on), each dimension
    labelled."""
    data = np.ascontiguousarray(data, dtype=np.float64).ravel()
    dims = tuple((str(label), int(n)) for label, n in dims)
    sizes = [n for _, n in dims]
    if int(np.prod(sizes)) != data.size:
        msg = f'dimensions {sizes} for {data.size} values'
        raise ValueError(msg)
    return _shaped_layout(dims).encode(data)


def encode_string(text: str) -> bytes:
    """CDR of a ``std_msgs/msg/String`` (lean codec, io/cdr.py)."""
    return cdr.encode_string(text)


def decode_string(raw: bytes | memoryview) -> str:
    """The text of a ``std_msgs/msg/String``."""
    return _deserialize(raw, STRING).data


@lru_cache(maxsize=256)
def _named_values_layout(source: str, labels: tuple[str, ...]) -> cdr.NamedValuesLayout:
    return cdr.NamedValuesLayout(source, labels)


def encode_named_values(
    stamp_ns: int, source: str, labels: Sequence[str], values: np.ndarray
) -> bytes:
    """CDR of a ``rcl_interfaces/msg/ParameterEvent`` carrying ``values`` as named doubles in
    ``new_parameters`` (``name`` = the label, ``value.double_value``), ``node`` = ``source``: a
    standard message whose array elements a viewer can pick by name (Foxglove:
    ``.new_parameters[:]{name=="theta_hat.x_theta.a_x"}.value.double_value``). The layout of
    each source and labels is built once (:class:`~cloe_ros.io.cdr.NamedValuesLayout`)."""
    return _named_values_layout(source, tuple(labels)).encode(stamp_ns, values)


def decode_named_values(raw: bytes | memoryview) -> tuple[int, str, list[str], np.ndarray]:
    """Stamp (ns), source, names and values of :func:`encode_named_values`' message."""
    msg = _deserialize(raw, PARAMETER_EVENT)
    names = [p.name for p in msg.new_parameters]
    values = np.array([p.value.double_value for p in msg.new_parameters], dtype=float)
    return stamp_to_ns(msg.stamp), msg.node, names, values


def encode_prediction_markers(
    stamp_ns: int, frame_id: str, positions: np.ndarray, radii: np.ndarray, lifetime_ns: int,
    every: int = 5,
) -> bytes:  # fmt: skip
    """CDR of a ``visualization_msgs/msg/MarkerArray`` drawing a prediction: the path as a line
    strip (``ns`` ``prediction``, id 0) and, at every ``every``-th pose, a translucent sphere of
    the pose's 95 % radius (``ns`` ``prediction_radius``, ids 1, 2, ...; diameter = 2 radius).

    Every marker is stamped with the prediction's issue time (a future stamp would make RViz
    look up a transform that does not exist yet) and lives ``lifetime_ns``, so a stale
    prediction disappears. Written straight into CDR (:func:`cloe_ros.io.cdr.
    encode_prediction_markers`), the bytes rosbags writes."""
    return cdr.encode_prediction_markers(stamp_ns, frame_id, positions, radii, lifetime_ns, every)


def encode_clock(ns: int) -> bytes:
    """CDR of a ``rosgraph_msgs/msg/Clock``."""
    store = typestore()
    return bytes(store.serialize_cdr(store.types[CLOCK](clock=ns_to_time(ns)), CLOCK))


#: DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True)
class Status:
    """One ``diagnostic_msgs/DiagnosticStatus``: level, name, message, hardware id, key/values."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...]


def encode_diagnostics(stamp_ns: int, statuses: Sequence[Status]) -> bytes:
    """CDR of a ``diagnostic_msgs/msg/DiagnosticArray`` (the lean codec's: rosbags' bytes, with
    no type store, :func:`~cloe_ros.io.cdr.encode_diagnostic_array`)."""
    return cdr.encode_diagnostic_array(stamp_ns, statuses)


def decode_diagnostics(raw: bytes | memoryview) -> tuple[int, list[Status]]:
    """Stamp (ns) and statuses of a ``diagnostic_msgs/msg/DiagnosticArray``."""
    msg = _deserialize(raw, DIAGNOSTIC_ARRAY)
    statuses = [
        Status(
            level=int.from_bytes(s.level, 'little')
            if isinstance(s.level, bytes)
            else int(s.level),
            name=s.name,
            message=s.message,
            hardware_id=s.hardware_id,
            values=tuple((kv.key, kv.value) for kv in s.values),
        )
        for s in msg.status
    ]
    return stamp_to_ns(msg.header.stamp), statuses
