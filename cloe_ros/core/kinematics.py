"""Exact rigid-body kinematics between odometry and the model state.

Conventions (REP-103 / REP-105): world frame ENU, body frame FLU, attitude as ZYX Euler angles
``R = Rz(psi) Ry(theta) Rx(phi)`` (roll phi, pitch theta, yaw psi), quaternions ``(x, y, z, w)``
as in ``geometry_msgs/Quaternion``. Odometry carries the pose in the world frame and the twist in
the body frame: linear = body velocity (m/s), angular = body rates ``(p, q, r)`` (rad/s). The
model state uses world-frame velocities and Euler-angle rates; the conversions below are exact (no
small-angle shortcut). All functions accept arrays with any leading batch shape.
"""

from __future__ import annotations

import math

import numpy as np

from cloe_ros.core.model import N_STATES

TWO_PI = 2.0 * np.pi


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle (rad) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % TWO_PI - np.pi


def unwrap_near(angle: np.ndarray | float, previous: np.ndarray | float) -> np.ndarray | float:
    """The representative of ``angle`` (rad) closest to ``previous`` (continuous yaw)."""
    return previous + wrap_angle(np.asarray(angle) - previous)


def unwrap_near_one(angle: float, previous: float) -> float:
    """:func:`unwrap_near` of two floats, with scalar math (the same arithmetic: Python's float
    ``%`` is numpy's)."""
    return previous + ((angle - previous + math.pi) % TWO_PI - math.pi)


def _floats(values) -> list[float]:
    """The entries of a short vector as Python floats (an array's through ``tolist``: far
    cheaper than iterating it)."""
    return values.tolist() if isinstance(values, np.ndarray) else [float(c) for c in values]


def quaternion_to_euler(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles ``(roll, pitch, yaw)`` (..., 3) of unit quaternions ``(x, y, z, w)``."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def euler_to_quaternion(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` (..., 4) of ZYX Euler angles (rad)."""
    cr, sr = np.cos(0.5 * np.asarray(roll)), np.sin(0.5 * np.asarray(roll))
    cp, sp = np.cos(0.5 * np.asarray(pitch)), np.sin(0.5 * np.asarray(pitch))
    cy, sy = np.cos(0.5 * np.asarray(yaw)), np.sin(0.5 * np.asarray(yaw))
    return np.stack(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ],
        axis=-1,
    )


def euler_to_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotation matrix body -> world (..., 3, 3) of ZYX Euler angles (rad)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rot = np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )
    return rot


def euler_to_rotation_one(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """:func:`euler_to_rotation` of one attitude (3, 3), by scalar trigonometry."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])  # fmt: skip


def body_rates_to_euler_rates(euler: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Euler-angle rates ``(roll_dot, pitch_dot, yaw_dot)`` from body rates ``(p, q, r)``.

    ``roll_dot = p + (q sin(roll) + r cos(roll)) tan(pitch)``,
    ``pitch_dot = q cos(roll) - r sin(roll)``,
    ``yaw_dot = (q sin(roll) + r cos(roll)) / cos(pitch)``. Singular at pitch = +-pi/2.
    """
    roll, pitch = euler[..., 0], euler[..., 1]
    p, q, r = omega[..., 0], omega[..., 1], omega[..., 2]
    sr, cr = np.sin(roll), np.cos(roll)
    cp = np.cos(pitch)
    s = q * sr + r * cr
    return np.stack([p + s * np.tan(pitch), q * cr - r * sr, s / cp], axis=-1)


def euler_rates_to_body_rates(euler: np.ndarray, euler_rates: np.ndarray) -> np.ndarray:
    """Body rates ``(p, q, r)`` from Euler-angle rates (inverse of the function above)."""
    roll, pitch = euler[..., 0], euler[..., 1]
    droll, dpitch, dyaw = euler_rates[..., 0], euler_rates[..., 1], euler_rates[..., 2]
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    return np.stack(
        [droll - dyaw * sp, dpitch * cr + dyaw * cp * sr, -dpitch * sr + dyaw * cp * cr], axis=-1
    )


def odometry_to_state(
    position: np.ndarray, quaternion: np.ndarray, v_body: np.ndarray, w_body: np.ndarray
) -> np.ndarray:
    """Model state ``zeta`` (..., 12) from an odometry sample (yaw wrapped to [-pi, pi)).

    Args:
        position: World position (..., 3), m.
        quaternion: Attitude body -> world (..., 4) as ``(x, y, z, w)``; normalised here.
        v_body: Linear velocity in the body frame (..., 3), m/s.
        w_body: Body rates ``(p, q, r)`` (..., 3), rad/s.

    """
    q = np.asarray(quaternion, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    euler = quaternion_to_euler(q)
    rot = euler_to_rotation(euler[..., 0], euler[..., 1], euler[..., 2])
    v_world = np.einsum('...ij,...j->...i', rot, v_body)
    rates = body_rates_to_euler_rates(euler, np.asarray(w_body, dtype=float))
    zeta = np.empty((*np.shape(position)[:-1], N_STATES))
    zeta[..., 0], zeta[..., 1] = position[..., 0], v_world[..., 0]
    zeta[..., 2], zeta[..., 3] = euler[..., 1], rates[..., 1]
    zeta[..., 4], zeta[..., 5] = position[..., 1], v_world[..., 1]
    zeta[..., 6], zeta[..., 7] = euler[..., 0], rates[..., 0]
    zeta[..., 8], zeta[..., 9] = euler[..., 2], rates[..., 2]
    zeta[..., 10], zeta[..., 11] = position[..., 2], v_world[..., 2]
    return zeta


def state_to_odometry(zeta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`odometry_to_state`: ``(position, quaternion, v_body, w_body)``."""
    zeta = np.asarray(zeta, dtype=float)
    position = zeta[..., [0, 4, 10]]
    roll, pitch, yaw = zeta[..., 6], zeta[..., 2], zeta[..., 8]
    euler = np.stack([roll, pitch, yaw], axis=-1)
    quaternion = euler_to_quaternion(roll, pitch, yaw)
    rot = euler_to_rotation(roll, pitch, yaw)
    v_body = np.einsum('...ji,...j->...i', rot, zeta[..., [1, 5, 11]])
    w_body = euler_rates_to_body_rates(euler, zeta[..., [7, 3, 9]])
    return position, quaternion, v_body, w_body


def yaw_quaternion(yaw: np.ndarray) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` of a pure yaw rotation (reference orientation)."""
    yaw = np.asarray(yaw, dtype=float)
    zeros = np.zeros_like(yaw)
    return np.stack([zeros, zeros, np.sin(0.5 * yaw), np.cos(0.5 * yaw)], axis=-1)


def quaternion_yaw(q: np.ndarray) -> np.ndarray:
    """Yaw (rad) of quaternions ``(x, y, z, w)`` (..., 4)."""
    return quaternion_to_euler(q)[..., 2]


def quaternion_to_euler_one(quaternion) -> tuple[float, float, float]:
    """:func:`quaternion_to_euler` for one unit quaternion ``(x, y, z, w)`` (not normalised
    here), with scalar math (the hot path of a single sample): ``(roll, pitch, yaw)``, rad."""
    x, y, z, w = _floats(quaternion)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(min(1.0, max(-1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def quaternion_yaw_one(quaternion) -> float:
    """:func:`quaternion_yaw` for one unit quaternion ``(x, y, z, w)`` (not normalised here),
    rad."""
    return quaternion_to_euler_one(quaternion)[2]


def odometry_to_state_one(
    position: np.ndarray, quaternion: np.ndarray, v_body: np.ndarray, w_body: np.ndarray
) -> np.ndarray:
    """:func:`odometry_to_state` for one sample, in one compiled call (the node's hot path: 1.9
    against 36 µs for the array version on a single sample): the quaternion normalised,
    ZYX Euler angles, the body velocity rotated into the world, the body rates turned into Euler
    rates (:func:`~cloe_ros.core.kernels.odometry_state`, its checks all passed); NaN where a
    value is not finite."""
    from cloe_ros.core import kernels  # (numba: imported by the paths that convert samples)

    zeta = np.empty(12)
    arrays = (np.asarray(a, dtype=float) for a in (position, quaternion, v_body, w_body))
    inf = math.inf
    if kernels.odometry_state(*arrays, inf, inf, inf, inf, inf, zeta, np.empty(2)):
        zeta[:] = np.nan
    return zeta


def state_to_odometry_one(
    zeta: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`state_to_odometry` for one state (12,), by scalar arithmetic in one compiled call
    (:func:`~cloe_ros.core.kernels.state_message`)."""
    from cloe_ros.core import kernels  # (numba: imported by the paths that write states)

    out = np.empty(85)
    kernels.state_message(np.asarray(zeta, dtype=float), out[:12], False, out)
    return out[0:3].copy(), out[3:7].copy(), out[43:46].copy(), out[46:49].copy()
