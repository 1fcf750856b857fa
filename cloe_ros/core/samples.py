"""Plain-array samples of the contract's input topics (README), independent of any ROS library.

The io layer fills them from CDR bytes; the engine consumes them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The range of the stamps a ROS message carries (builtin_interfaces/Time: int32 seconds, to
#: 2038-01-19, and nanoseconds), ns.
MIN_STAMP_NS = -(2**31) * 1_000_000_000
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999
NS = 1_000_000_000  # ns per s


@dataclass(frozen=True)
class OdometrySample:
    """A ``nav_msgs/Odometry``: pose in ``frame_id``, twist in the body frame (REP-105).

    Attributes:
        stamp_ns: Header stamp, ns.
        frame_id: World frame.
        child_frame_id: Body frame.
        position: (3,) m.
        orientation: (4,) quaternion ``(x, y, z, w)``.
        linear: Body-frame velocity (3,), m/s.
        angular: Body rates ``(p, q, r)`` (3,), rad/s.
        pose_covariance: (36,) row-major, or None (unknown).
        twist_covariance: (36,) row-major, or None (unknown).

    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position: np.ndarray
    orientation: np.ndarray
    linear: np.ndarray
    angular: np.ndarray
    pose_covariance: np.ndarray | None = None
    twist_covariance: np.ndarray | None = None


@dataclass(frozen=True)
class PoseSample:
    """A ``geometry_msgs/PoseStamped``: position (3,) m, orientation (4,) ``(x, y, z, w)``."""

    stamp_ns: int
    frame_id: str
    position: np.ndarray
    orientation: np.ndarray


@dataclass(frozen=True)
class PathSample:
    """A ``nav_msgs/Path``: K poses with their own stamps (ns), positions (K, 3), orientations
    (K, 4)."""

    stamp_ns: int
    frame_id: str
    stamps_ns: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
