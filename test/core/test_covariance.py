"""The estimator's error statistics (cloe_ros.core.covariance): a closed-form case, the prior, the
REP-105 mapping against finite differences, and the calibration on a simulated flight with known
noise (the fraction of true errors inside 2 sigma)."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core import blas, covariance
from cloe_ros.core.covariance import PRIOR_SIGMA, ErrorCovariance, odometry_covariance
from cloe_ros.core.evaluation import GAUSSIAN_2SIGMA, covariance_coverage, run_engine
from cloe_ros.core.kinematics import state_to_odometry
from cloe_ros.core.simulator import (
    SCENARIOS,
    TYPICAL_NOISE,
    PaperDisturbance,
    QuadrotorSimulator,
)
from cloe_ros.io.config import build_configs


def test_a_first_order_filter_of_white_noise_has_its_closed_form_variance():
    """zeta = 0 measured with white noise R; zeta_hat_k = rho zeta_hat_k-1 + (1 - rho) z_k (the
    observer's implicit L step with f = 0): E[zeta_hat^2] = (1 - rho) / (1 + rho) R, although
    the output error's second moment is about R."""
    h, gain, sigma = 0.01, 50.0, np.linspace(0.001, 0.1, 12)
    rho = 1.0 / (1.0 + h * gain)
    rng = np.random.default_rng(3)
    stats = ErrorCovariance(h, time_constant=1e9)  # a plain running mean
    zeta_hat = np.zeros(12)
    for _ in range(40000):
        z = sigma * rng.normal(size=12)
        zeta_hat = rho * zeta_hat + (1.0 - rho) * z
        variance = stats.update(z, zeta_hat, np.full(12, gain))
    expected = (1.0 - rho) / (1.0 + rho) * sigma**2
    np.testing.assert_allclose(variance, expected, rtol=0.15)  # (about 4 % statistical)
    assert np.all(stats.second_moment > 2.0 * expected)  # what the raw statistic would say


def test_the_prior_until_enough_steps_and_after_a_reset():
    stats = ErrorCovariance(0.01, warmup=1.0)
    zeros = np.zeros(12)
    for _ in range(99):
        np.testing.assert_array_equal(stats.update(zeros, zeros + 1e-3, zeros), PRIOR_SIGMA**2)
    assert np.all(stats.update(zeros, zeros + 1e-3, zeros) < 1e-5)  # the 100th: statistics
    stats.reset()
    np.testing.assert_array_equal(stats.variance, PRIOR_SIGMA**2)


def test_the_twist_covariance_maps_through_the_body_jacobians():
    """Against finite differences of state_to_odometry: Cov_body = J diag J^T, J the derivative
    of the body twist with respect to the world velocity and the Euler rates."""
    zeta = np.array([1.0, 0.5, 0.3, 0.2, -2.0, -0.4, -0.25, 0.1, 2.5, 0.3, 1.2, 0.2])
    variance = np.linspace(1e-4, 2e-3, 12)
    pose, twist = odometry_covariance(zeta, variance)
    columns = [1, 5, 11, 7, 3, 9]  # vx, vy, vz, roll rate, pitch rate, yaw rate
    jac = np.empty((6, 6))
    for j, col in enumerate(columns):
        d = np.zeros(12)
        d[col] = 1e-6
        _, _, v1, w1 = state_to_odometry(zeta + d)
        _, _, v0, w0 = state_to_odometry(zeta - d)
        jac[:, j] = np.concatenate([v1 - v0, w1 - w0]) / 2e-6
    block = np.zeros((6, 6))
    block[:3, :3] = jac[:3, :3] @ np.diag(variance[columns[:3]]) @ jac[:3, :3].T
    block[3:, 3:] = jac[3:, 3:] @ np.diag(variance[columns[3:]]) @ jac[3:, 3:].T
    np.testing.assert_allclose(twist, block, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(np.diag(pose), variance[[0, 4, 10, 6, 2, 8]])
    assert np.count_nonzero(pose - np.diag(np.diag(pose))) == 0


def test_one_state_gives_the_batched_covariances():
    """``cloe/state`` takes one state at a time on a path of its own: it equals the batched
    path, state by state, to round-off."""
    rng = np.random.default_rng(3)
    zeta = rng.normal(size=(50, 12))
    zeta[:, [6, 2]] = rng.uniform(-1.3, 1.3, size=(50, 2))
    variance = rng.uniform(1e-6, 1e-2, size=(50, 12))
    pose, twist = odometry_covariance(zeta, variance)
    for k in range(50):
        one_pose, one_twist = odometry_covariance(zeta[k], variance[k])
        np.testing.assert_array_equal(one_pose, pose[k])
        np.testing.assert_allclose(one_twist, twist[k], rtol=1e-13, atol=1e-18)
        np.testing.assert_array_equal(one_twist, one_twist.T)


@pytest.fixture(scope='module')
def noisy_flight():
    """40 s of the position scenario, disturbed, with the evaluation's noise (2 mm, 1 cm/s,
    2 mrad, 0.01 rad/s), odometry and estimator at 100 Hz."""
    sim = QuadrotorSimulator(
        SCENARIOS['position'], disturbance=PaperDisturbance(), noise=TYPICAL_NOISE, dt=1 / 500,
        rng=np.random.default_rng(1),
    )  # fmt: skip
    res = sim.run(40.0)
    config, _ = build_configs({'algorithm': 'cloe_iv', 'rate': 100.0})
    run = run_engine(config, res.t[::5], res.measured[::5, 0], res.reference[::5, 0])
    return run, res.t, res.zeta[:, 0]


def test_the_covariance_covers_the_true_errors_at_about_the_gaussian_level(noisy_flight):
    """Per block, the fraction of true errors (estimate minus simulated truth) inside the 2-sigma
    interval is near the Gaussian 95.4 %, and inside the 2-sigma ellipsoid near 73.9 %: bands
    that a covariance ten times too small (about 50 % and 2 %) or ten times too large (100 %)
    leave, and the raw output-error statistic, about R here, also leaves (near 100 %)."""
    run, t, truth = noisy_flight
    coverage = covariance_coverage(run, t, truth)
    assert set(coverage) == {'position', 'attitude', 'velocity', 'rates'}
    for name, c in coverage.items():
        assert 0.85 <= c['interval_1d'] <= 0.995, (name, c)
        gaussian = GAUSSIAN_2SIGMA[3]
        assert gaussian - 0.25 <= c['ellipsoid_3d'] <= gaussian + 0.2, (name, c)
        assert c['count'] == len(run.t)
    assert np.isfinite(run.error_variance).all() and (run.error_variance > 0).all()


def test_the_statistics_of_many_vehicles_update_at_once_as_each_alone():
    rng = np.random.default_rng(0)
    k = 5
    alone = [ErrorCovariance(0.01) for _ in range(k)]
    together = [ErrorCovariance(0.01) for _ in range(k)]
    for step in range(600):
        measured = rng.normal(size=(k, 12))
        zeta_hat = measured + 0.01 * rng.normal(size=(k, 12))
        gains = rng.uniform(-1.0, 20.0, size=(k, 12))
        if step % 97 == 13:  # a vehicle's estimator restarts, another's statistics reset
            alone[step % k].restart()
            together[step % k].restart()
        if step % 211 == 50:
            alone[1].reset()
            together[1].reset()
        which = [i for i in range(k) if rng.random() < 0.8] or [0]  # not all step every time
        want = np.array([alone[i].update(measured[i], zeta_hat[i], gains[i]) for i in which])
        got = ErrorCovariance.update_many([together[i] for i in which], measured[which],
                                          zeta_hat[which], gains[which])  # fmt: skip
        np.testing.assert_array_equal(got, want)
        if step % 50 == 7:  # and one stepped alone after a batch goes on alike
            i = which[0]
            np.testing.assert_array_equal(
                together[i].update(measured[i], zeta_hat[i], gains[i]),
                alone[i].update(measured[i], zeta_hat[i], gains[i]),
            )
    assert all(c.count_d3 > 50 for c in together)  # (the statistics, not only the prior)


@pytest.mark.skipif(not blas.AVAILABLE, reason="numpy's OpenBLAS not found")
def test_the_compiled_update_is_the_numpy_code_bit_for_bit():
    """kernels_covariance.covariance_update against the numpy code of ErrorCovariance.update and
    update_many: the same variances and statistics, step by step, through restarts, resets,
    negative and non-finite gains and the warm-up."""
    rng = np.random.default_rng(3)
    k = 4
    pairs = {compiled: [ErrorCovariance(0.01, warmup=0.05) for _ in range(k)]
             for compiled in (True, False)}  # fmt: skip
    try:
        for step in range(400):
            measured = rng.normal(size=(k, 12)) * 10.0 ** rng.uniform(-3, 1)
            zeta_hat = measured + 0.01 * rng.normal(size=(k, 12))
            gains = rng.uniform(-1.0, 20.0, size=(k, 12))
            if step % 53 == 5:
                gains[step % k, step % 12] = np.nan
            which = [i for i in range(k) if rng.random() < 0.8] or [0]
            out = {}
            for compiled, covs in pairs.items():
                covariance.COMPILED = compiled
                if step % 97 == 13:
                    covs[step % k].restart()
                if step % 211 == 50:
                    covs[1].reset()
                if step % 3:
                    out[compiled] = ErrorCovariance.update_many(
                        [covs[i] for i in which], measured[which], zeta_hat[which], gains[which])
                else:
                    out[compiled] = np.array([covs[i].update(measured[i], zeta_hat[i], gains[i])
                                              for i in which])  # fmt: skip
            np.testing.assert_array_equal(out[True], out[False])
            for a, b in zip(*pairs.values()):
                np.testing.assert_array_equal(a._state, b._state)
                assert (a.count, a.count_d3, a._filled) == (b.count, b.count_d3, b._filled)
        assert covariance._KERNEL is not None  # (the compiled update ran)
        assert all(c.count_d3 > 50 for c in pairs[True])  # (statistics, not only the prior)
    finally:
        covariance.COMPILED = None
