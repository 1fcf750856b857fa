"""Metrics against closed-form signals."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.metrics import (
    itae,
    parameter_error,
    rmse_norm,
    subsystem_itae,
    subsystem_rmse,
)


def test_rmse_of_constant_and_sinusoid():
    t = np.linspace(0.0, 10.0, 100001)
    err = np.zeros((len(t), 12))
    err[:, 0] = 3.0
    err[:, 4] = 4.0
    assert rmse_norm(err) == pytest.approx(5.0)
    err = np.zeros((len(t), 12))
    err[:, 1] = 2.0 * np.sin(2 * np.pi * t)  # RMS of A sin over whole periods is A / sqrt(2)
    assert rmse_norm(err) == pytest.approx(np.sqrt(2.0), rel=1e-4)


def test_subsystem_rmse_groups_states():
    err = np.zeros((10, 12))
    err[:, [0, 4, 10]] = 1.0  # position
    err[:, 3] = 2.0  # theta_dot: rates
    sub = subsystem_rmse(err)
    assert sub['position'] == pytest.approx(np.sqrt(3.0))
    assert sub['rates'] == pytest.approx(2.0)
    assert sub['velocity'] == 0.0 and sub['angles'] == 0.0


def test_itae_closed_forms():
    t = np.linspace(0.0, 5.0, 50001)
    const = np.zeros((len(t), 3))
    const[:, 2] = -2.0  # ||e|| = 2  ->  int t 2 dt = T^2
    assert itae(t, const) == pytest.approx(25.0, rel=1e-9)
    ramp = np.zeros((len(t), 3))
    ramp[:, 0] = t  # ||e|| = t  ->  int t^2 dt = T^3 / 3
    assert itae(t, ramp) == pytest.approx(125.0 / 3.0, rel=1e-6)
    decay = np.exp(-t)[:, None] * np.array([[0.6, 0.8, 0.0]])  # int t e^-t = 1 - (T+1) e^-T
    assert itae(t, decay) == pytest.approx(1.0 - 6.0 * np.exp(-5.0), rel=1e-6)


def test_subsystem_itae_uses_only_its_states():
    t = np.linspace(0.0, 2.0, 2001)
    err = np.zeros((len(t), 12))
    err[:, 8] = 1.0  # psi belongs to the Euler angles
    out = subsystem_itae(t, err)
    assert out['angles'] == pytest.approx(2.0)
    assert out['position'] == out['velocity'] == out['rates'] == 0.0


def test_parameter_error_per_block():
    truth = np.arange(1.0, 17.0)
    est = truth.copy()
    est[:5] *= 1.1  # x-theta off by 10 %
    err = parameter_error(est, truth)
    assert err['x_theta'] == pytest.approx(0.1)
    assert err['y_phi'] == err['psi'] == err['z'] == 0.0
    assert err['all'] == pytest.approx(0.1 * np.linalg.norm(truth[:5]) / np.linalg.norm(truth))
