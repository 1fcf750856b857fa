"""Odometry <-> model state conversions against independent computations."""

from __future__ import annotations

import numpy as np

from cloe_ros.core.kinematics import (
    body_rates_to_euler_rates,
    euler_rates_to_body_rates,
    euler_to_quaternion,
    euler_to_rotation,
    euler_to_rotation_one,
    odometry_to_state,
    quaternion_to_euler,
    quaternion_to_euler_one,
    quaternion_yaw,
    quaternion_yaw_one,
    state_to_odometry,
    unwrap_near,
    wrap_angle,
)


def _quat_to_rot(q):
    """Rotation matrix of a unit quaternion (x, y, z, w) by the textbook formula."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def _rot_axis(axis, angle):
    c, s = np.cos(angle), np.sin(angle)
    if axis == 'x':
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 'y':
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_euler_quaternion_rotation_agree():
    rng = np.random.default_rng(3)
    for _ in range(50):
        roll, pitch, yaw = rng.uniform(-1.4, 1.4), rng.uniform(-1.4, 1.4), rng.uniform(-3.1, 3.1)
        r_zyx = _rot_axis('z', yaw) @ _rot_axis('y', pitch) @ _rot_axis('x', roll)
        np.testing.assert_allclose(euler_to_rotation(roll, pitch, yaw), r_zyx, atol=1e-12)
        one = euler_to_rotation_one(roll, pitch, yaw)
        np.testing.assert_allclose(one, euler_to_rotation(roll, pitch, yaw), rtol=0, atol=1e-15)
        q = euler_to_quaternion(roll, pitch, yaw)
        np.testing.assert_allclose(_quat_to_rot(q), r_zyx, atol=1e-12)
        np.testing.assert_allclose(quaternion_to_euler(q), [roll, pitch, yaw], atol=1e-9)


def test_body_rates_match_rotation_derivative():
    """omega_body = vee(R^T R_dot) with R_dot by central differences of Euler angle paths."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        euler = rng.uniform([-1, -1, -3], [1, 1, 3])
        rates = rng.normal(size=3)
        h = 1e-6
        rp = euler_to_rotation(*(euler + h * rates))
        rm = euler_to_rotation(*(euler - h * rates))
        r = euler_to_rotation(*euler)
        skew = r.T @ (rp - rm) / (2 * h)
        omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        np.testing.assert_allclose(euler_rates_to_body_rates(euler, rates), omega, atol=1e-6)
        np.testing.assert_allclose(body_rates_to_euler_rates(euler, omega), rates, atol=1e-6)


def test_odometry_state_roundtrip_batch():
    rng = np.random.default_rng(5)
    zeta = rng.normal(size=(7, 12)) * 0.5
    zeta[:, 8] = rng.uniform(-3.1, 3.1, size=7)
    position, q, v_body, w_body = state_to_odometry(zeta)
    back = odometry_to_state(position, q, v_body, w_body)
    np.testing.assert_allclose(back, zeta, atol=1e-10)
    # the body velocity rotated back is the world velocity
    r = euler_to_rotation(zeta[:, 6], zeta[:, 2], zeta[:, 8])
    np.testing.assert_allclose(np.einsum('nij,nj->ni', r, v_body), zeta[:, [1, 5, 11]], atol=1e-12)


def test_odometry_normalises_quaternion():
    q = 2.0 * euler_to_quaternion(0.1, -0.2, 0.3)
    zeta = odometry_to_state(np.zeros(3), q, np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(zeta[[6, 2, 8]], [0.1, -0.2, 0.3], atol=1e-12)


def test_yaw_unwrapping_is_continuous_across_pi():
    raw = wrap_angle(np.linspace(2.5, 10.0, 400))  # crosses +pi twice
    unwrapped = [raw[0]]
    for a in raw[1:]:
        unwrapped.append(unwrap_near(a, unwrapped[-1]))
    np.testing.assert_allclose(unwrapped, np.linspace(2.5, 10.0, 400), atol=1e-12)


def test_scalar_conversions_equal_the_array_ones():
    """The node's single-sample fast path and the batched version agree."""
    from cloe_ros.core.kinematics import odometry_to_state_one, state_to_odometry_one

    rng = np.random.default_rng(9)
    for _ in range(200):
        zeta = rng.normal(size=12) * 0.6
        zeta[8] = rng.uniform(-3.14, 3.14)
        fast = state_to_odometry_one(zeta)
        for a, b in zip(fast, state_to_odometry(zeta)):
            np.testing.assert_allclose(a, b, atol=1e-12)
        q = fast[1] * rng.uniform(0.95, 1.05)  # not quite unit, as received
        np.testing.assert_allclose(
            odometry_to_state_one(fast[0], q, fast[2], fast[3]),
            odometry_to_state(fast[0], q, fast[2], fast[3]),
            atol=1e-12,
        )


def test_the_tilt_check_reads_roll_and_pitch_of_a_quaternion_not_quite_unit():
    """The engine's tilt check (the Euler rates are singular at pitch +-pi/2;
    :func:`~cloe_ros.core.kernels.odometry_state`) agrees with the full conversion, on
    quaternions as received (norm off by up to 5 %): with no tilt allowed, every sample is
    refused for its tilt, with its roll and pitch."""
    from cloe_ros.core import kernels

    rng = np.random.default_rng(4)
    inf, zeros = np.inf, np.zeros(3)
    for _ in range(200):
        euler = rng.uniform([-3.1, -1.5, -3.1], [3.1, 1.5, 3.1])
        q = euler_to_quaternion(*euler) * rng.uniform(0.95, 1.05)
        detail = np.empty(2)
        verdict = kernels.odometry_state(zeros, q, zeros, zeros, 0.1, inf, inf, inf, 0.0,
                                         np.empty(12), detail)  # fmt: skip
        assert verdict == kernels.BAD_TILT
        np.testing.assert_allclose(detail, euler[:2], atol=1e-9)


def test_one_quaternion_to_euler_equals_the_array_version():
    """The scalar conversion (the engine's reference yaw, the odometry fast path) and the batched
    one agree, yaw across +-pi and pitch near +-pi/2 included."""
    rng = np.random.default_rng(11)
    euler = rng.uniform([-3.14, -1.57, -3.14], [3.14, 1.57, 3.14], size=(300, 3))
    q = euler_to_quaternion(euler[:, 0], euler[:, 1], euler[:, 2])
    batched = quaternion_to_euler(q)
    for qi, expected, yaw in zip(q, batched, quaternion_yaw(q)):
        np.testing.assert_allclose(quaternion_to_euler_one(qi), expected, atol=1e-12)
        assert abs(quaternion_yaw_one(qi) - yaw) <= 1e-12
    np.testing.assert_allclose(batched, euler, atol=1e-6)
