"""The 16-parameter closed-loop model: layout, matrices and their inverse."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core import model
from cloe_ros.core.model import (
    BLOCKS,
    GRAVITY,
    N_PARAMS,
    PARAMETER_NAMES,
    STATE_NAMES,
    parameters_from_matrices,
    system_matrices,
)


def test_layout_has_16_named_parameters_in_block_order():
    assert N_PARAMS == 16
    assert len(PARAMETER_NAMES) == 16
    assert PARAMETER_NAMES[:5] == (
        'x_theta.a_x', 'x_theta.a_x_dot', 'x_theta.a_theta', 'x_theta.a_theta_dot',
        'x_theta.b_x_d',
    )  # fmt: skip
    assert PARAMETER_NAMES[-3:] == ('z.a_z', 'z.a_z_dot', 'z.b_z_d')
    assert STATE_NAMES == (
        'x', 'x_dot', 'theta', 'theta_dot', 'y', 'y_dot', 'phi', 'phi_dot',
        'psi', 'psi_dot', 'z', 'z_dot',
    )  # fmt: skip


def test_known_rows_are_integrator_chains_with_tilt_coupling():
    a, b = system_matrices(np.zeros(16))
    expected = np.zeros((12, 12))
    expected[0, 1] = expected[2, 3] = 1.0  # x' = x_dot, theta' = theta_dot
    expected[1, 2] = GRAVITY  # x_ddot = +g theta
    expected[4, 5] = expected[6, 7] = 1.0
    expected[5, 6] = -GRAVITY  # y_ddot = -g phi
    expected[8, 9] = 1.0
    expected[10, 11] = 1.0
    np.testing.assert_array_equal(a, expected)
    np.testing.assert_array_equal(b, np.zeros((12, 4)))


def test_matrices_roundtrip_and_batch():
    rng = np.random.default_rng(1)
    theta = rng.normal(size=(3, 16))
    a, b = system_matrices(theta)
    assert a.shape == (3, 12, 12) and b.shape == (3, 12, 4)
    np.testing.assert_array_equal(parameters_from_matrices(a, b), theta)
    # the x-theta block's last row is theta_ddot = a . [x, x_dot, theta, theta_dot] + b x_d
    np.testing.assert_array_equal(a[1, 3, :4], theta[1, :4])
    assert b[1, 3, 0] == theta[1, 4]
    # only the four last rows depend on theta
    assert set(np.flatnonzero(np.any(b[0] != 0, axis=1))) == {3, 7, 9, 11}


def test_regressor_matches_matrices():
    """Theta . phi per block equals the last rows of A zeta + B r (the identifier's regressor)."""
    rng = np.random.default_rng(2)
    theta, zeta, r = rng.normal(size=16), rng.normal(size=12), rng.normal(size=4)
    a, b = system_matrices(theta)
    w = np.concatenate([zeta, r])
    phi = w[model.REGRESSOR_INDEX]
    rows = a @ zeta + b @ r
    for block, sl in zip(BLOCKS, model.BLOCK_SLICES):
        assert theta[sl] @ phi[sl] == pytest.approx(rows[block.last], rel=1e-12)


def test_shape_errors_name_the_argument():
    with pytest.raises(
        ValueError, match=r'theta: expected shape \(\.\.\., 16\) but found \(15,\)'
    ):
        system_matrices(np.zeros(15))
