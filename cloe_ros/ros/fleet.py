"""Which vehicles a node infers: shards, and namespaces found in the ROS graph. No rclpy.

A vehicle belongs to shard ``crc32(namespace) mod shard_count``: the namespace's UTF-8 bytes
hashed by zlib's CRC-32, the same in every process and on every host (Python's ``hash`` of a
string changes from one process to the next).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Sequence

from cloe_ros.io import messages
from cloe_ros.io.dataset import vehicle_namespaces


def shard_of(namespace: str, shard_count: int) -> int:
    """The shard of the vehicle whose namespace (absolute, '/' for the root) is ``namespace``."""
    return zlib.crc32(namespace.encode('utf-8')) % shard_count


def check_shard(shard_index: int, shard_count: int) -> str | None:
    """Why ``shard_index`` cannot be used with ``shard_count`` (None when it can)."""
    if not 0 <= shard_index < shard_count:
        return (
            f'must be below shard_count ({shard_count}), got {shard_index}: the shards of '
            f'{shard_count} node(s) are 0 to {shard_count - 1}'
        )
    return None


def graph_namespaces(topics: Iterable[tuple[str, Sequence[str]]]) -> list[str]:
    """Absolute namespaces ('/' for the root) that have an ``odom`` (nav_msgs/msg/Odometry) and a
    ``reference`` (geometry_msgs/msg/PoseStamped) topic, from ``get_topic_names_and_types()``;
    as ``cloe infer`` finds vehicles in a bag."""
    types = {}
    for name, msgtypes in topics:
        for wanted in (messages.ODOMETRY, messages.POSE_STAMPED):
            if wanted in msgtypes:
                types[name] = wanted
    return [ns or '/' for ns in vehicle_namespaces(types)]
