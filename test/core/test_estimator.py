"""CLOE / CLOE-SM numerics against independent computations."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.linalg import expm

from cloe_ros.core.estimator import (
    SM_EXPONENTS,
    SM_GAINS_TABLE1,
    CloeEstimator,
    ConfigError,
    EstimatorConfig,
)
from cloe_ros.core.model import BLOCK_SLICES, BLOCKS, system_matrices
from cloe_ros.core.simulator import ProbingSignal, get_scenario, true_parameters

THETA = true_parameters()


def reference_step(zeta_hat, theta_hat, gain_l, zeta, r, h, cfg, implicit=True):
    """docs/method.md written out for one vehicle, explicit matrices (the test's own version)."""
    a, b = system_matrices(theta_hat)
    e = zeta - zeta_hat
    lam = np.zeros(12) if cfg.algorithm == 'cloe' else np.array(cfg.sm_gains)
    f = a @ zeta_hat + b @ r + lam * np.abs(e) ** np.array(cfg.sm_exponents) * np.sign(e)
    if implicit:
        new_zeta_hat = (zeta_hat + h * (f + gain_l * zeta)) / (1 + h * gain_l)
    else:
        new_zeta_hat = zeta_hat + h * (f + gain_l * e)
    new_theta = theta_hat.copy()
    for block, sl in zip(BLOCKS, BLOCK_SLICES):
        phi = np.concatenate([zeta_hat[list(block.states)], [r[block.reference]]])
        new_theta[sl] += h * cfg.gamma_theta * e[block.last] * phi
    new_l = gain_l + h * cfg.gamma_l * e**2
    return new_zeta_hat, new_theta, new_l


def linear_closed_loop(theta, t, r):
    """Exact ZOH samples of zeta' = A zeta + B r (reference held between samples)."""
    a, b = system_matrices(theta)
    h = t[1] - t[0]
    m = np.zeros((16, 16))
    m[:12, :12], m[:12, 12:] = a, b
    e = expm(m * h)
    ad, bd = e[:12, :12], e[:12, 12:]
    zeta = np.zeros((len(t), 12))
    zeta[0, 10] = 1.0
    for k in range(len(t) - 1):
        zeta[k + 1] = ad @ zeta[k] + bd @ r[k]
    return zeta


def _reference(t):
    return get_scenario('hover').reference(t) + ProbingSignal()(t)


@pytest.mark.parametrize('algorithm', ['cloe', 'cloe_sm'])
def test_step_matches_the_equations_written_out(algorithm):
    rng = np.random.default_rng(11)
    cfg = EstimatorConfig(algorithm, gamma_theta=3.0, gamma_l=2.0)
    est = CloeEstimator(cfg, rng.normal(size=12))
    est.theta_hat[:] = rng.normal(size=16)
    est.gain_l[:] = rng.uniform(0, 5, size=12)
    zh, th, gl = est.zeta_hat[0].copy(), est.theta_hat[0].copy(), est.gain_l[0].copy()
    for _ in range(5):
        zeta, r, h = rng.normal(size=12), rng.normal(size=4), 0.01
        zh, th, gl = reference_step(zh, th, gl, zeta, r, h, cfg)
        est.step(zeta[None], r[None], h)
        np.testing.assert_allclose(est.zeta_hat[0], zh, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(est.theta_hat[0], th, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(est.gain_l[0], gl, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('algorithm', ['cloe', 'cloe_sm'])
@pytest.mark.parametrize('gated', [False, True])
def test_the_compiled_step_keeps_numpys_order_bit_for_bit(algorithm, gated):
    """The step is one compiled call since 2026-12-06; before, its identifier and gain updates
    were numpy's in-place products. Those, written out here after the same observer kernels,
    give the same bits on three vehicles over 50 steps (element-wise products only: IEEE's on
    any machine), with and without a held channel."""
    from cloe_ros.core import kernels
    from cloe_ros.core.estimator import KNOWN_A, KNOWN_C, PARAM_CHANNEL, StepBuffers
    from cloe_ros.core.model import BLOCK_STARTS, PARAM_ROW, REGRESSOR_INDEX, UNKNOWN_ROWS

    rng = np.random.default_rng(5)
    n, h = 3, 0.01
    est = CloeEstimator(EstimatorConfig(algorithm), rng.normal(size=(n, 12)))
    est.theta_hat[:] = rng.normal(size=(n, 16))
    zh, th, gl = est.zeta_hat.copy(), est.theta_hat.copy(), est.gain_l.copy()
    buf = StepBuffers.allocate(n)
    for _ in range(50):
        zeta, r = zh + 0.1 * rng.normal(size=(n, 12)), rng.normal(size=(n, 4))
        tracked = rng.random((n, 4)) < 0.7 if gated else None
        est.step(zeta, r, h, tracked)
        e = zeta - zh
        kernels.observer_drift(zh, th, r, KNOWN_C, KNOWN_A, REGRESSOR_INDEX, BLOCK_STARTS,
                               UNKNOWN_ROWS, buf.w, buf.phi, buf.grad, buf.rows,
                               buf.f)  # fmt: skip
        kernels.observer_update(zh, buf.f, gl, zeta, h, est.lambda_, est.use_sm, est.exponents, e)
        grad = e[:, PARAM_ROW] * buf.phi * est.gamma_theta * h
        if gated:
            grad *= tracked.astype(float)[:, PARAM_CHANNEL]
        th += grad
        gl += np.square(e) * est.gamma_l * h
        for got, want in ((est.zeta_hat, zh), (est.theta_hat, th), (est.gain_l, gl)):
            assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize('algorithm', ['cloe', 'cloe_sm'])
def test_true_theta_tracks_the_linear_closed_loop(algorithm):
    """With Theta_hat = Theta frozen the estimate converges onto the exact linear trajectory, and
    the remaining error is the O(h) discretization error: it halves when h halves."""
    finals = []
    for h in (2e-3, 1e-3):
        t = np.arange(0.0, 20.0 + h / 2, h)
        r = _reference(t)
        zeta = linear_closed_loop(THETA, t, r)
        cfg = EstimatorConfig(algorithm, gamma_theta=0.0, gamma_l=0.0, l_initial=5.0,
                              theta_initial=tuple(THETA))  # fmt: skip
        est = CloeEstimator(cfg, zeta[0] + 0.1)  # start 0.1 off on every state
        err = np.empty(len(t))
        for k in range(1, len(t)):
            est.step(zeta[k][None], r[k - 1][None], h)
            err[k] = np.linalg.norm(zeta[k] - est.zeta_hat[0])
        assert err[1] > 0.05
        finals.append(np.max(err[t > 10.0]))
    # tracking, within the O(h) discretization error (probing up to 5.9 rad/s, h = 1 ms) ...
    assert finals[1] < 3e-3
    # ... which halves when h halves
    assert finals[0] / finals[1] == pytest.approx(2.0, rel=0.25)


def _paper_run(h, implicit, duration=30.0):
    t = np.arange(0.0, duration + h / 2, h)
    r = _reference(t)
    zeta = linear_closed_loop(THETA, t, r)
    cfg = EstimatorConfig('cloe', l_initial=0.0)
    zh, th, gl = zeta[0].copy(), np.zeros(16), np.zeros(12)
    for k in range(1, len(t)):
        zh, th, gl = reference_step(zh, th, gl, zeta[k], r[k - 1], h, cfg, implicit)
        if not np.all(np.isfinite(zh)) or np.max(np.abs(zh)) > 1e6:
            return np.inf
    return np.max(np.abs(zeta[-1] - zh))


def test_semi_implicit_step_stays_stable_at_20_hz_where_explicit_euler_diverges():
    assert _paper_run(0.05, implicit=False) == np.inf
    assert np.isfinite(_paper_run(0.05, implicit=True))
    # and the package's step is that semi-implicit step
    t = np.arange(0.0, 30.0 + 0.025, 0.05)
    r = _reference(t)
    zeta = linear_closed_loop(THETA, t, r)
    est = CloeEstimator(EstimatorConfig('cloe', l_initial=0.0), zeta[0])
    for k in range(1, len(t)):
        est.step(zeta[k][None], r[k - 1][None], 0.05)
    assert np.all(np.isfinite(est.zeta_hat)) and np.max(np.abs(zeta[-1] - est.zeta_hat[0])) < 1.0


def test_batch_equals_single_runs():
    rng = np.random.default_rng(12)
    n, steps, h = 5, 400, 0.005
    configs = [
        EstimatorConfig(alg, gamma_theta=g, l_initial=l0)
        for alg, g, l0 in zip(['cloe', 'cloe_sm'] * 3, [400, 100, 10, 400, 1], range(n))
    ]
    zeta = rng.normal(size=(steps, n, 12)).cumsum(axis=0) * 0.01
    r = rng.normal(size=(steps, n, 4)) * 0.1
    batch = CloeEstimator(configs, np.zeros(12))
    singles = [CloeEstimator(c, np.zeros(12)) for c in configs]
    for k in range(steps):
        batch.step(zeta[k], r[k], h)
        for i, s in enumerate(singles):
            s.step(zeta[k, i : i + 1], r[k, i : i + 1], h)
    for i, s in enumerate(singles):
        np.testing.assert_array_equal(batch.zeta_hat[i], s.zeta_hat[0])
        np.testing.assert_array_equal(batch.theta_hat[i], s.theta_hat[0])
        np.testing.assert_array_equal(batch.gain_l[i], s.gain_l[0])


def test_step_allocates_no_arrays():
    """No temporary array per step: the traced peak stays far below the smallest array the step
    could create for N = 4096 vehicles ((N, 4) float64 = 128 KiB); what remains is a few hundred
    bytes of Python objects, independent of N."""
    n = 4096
    est = CloeEstimator(EstimatorConfig('cloe_sm'), np.zeros(12), n_vehicles=n)
    zeta = np.full((n, 12), 0.01)
    r = np.zeros((n, 4))
    est.step(zeta, r, 0.001)  # warm-up
    tracemalloc.start()
    base, _ = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    for _ in range(100):
        est.step(zeta, r, 0.001)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak - base < 16 * 1024


def test_table1_gains_and_exponents_per_state():
    assert SM_GAINS_TABLE1[:4] == (0.12, 0.18, 0.24, 0.30)
    assert SM_GAINS_TABLE1[8:] == (0.24, 0.30, 0.24, 0.30)
    assert SM_EXPONENTS[:4] == (0.75, 0.5, 0.25, 0.0)
    assert SM_EXPONENTS[8:] == (0.5, 0.0, 0.5, 0.0)
    assert np.all(EstimatorConfig('cloe').lambda_ == 0.0)


@pytest.mark.parametrize(
    'kwargs, message',
    [
        ({'algorithm': 'kalman'}, "algorithm 'kalman' is not one of cloe, cloe_sm"),
        ({'gamma_theta': -1.0}, r'gamma_theta must be within \[0, 1e\+06\], got -1.0'),
        ({'l_initial': float('nan')}, r'l_initial must be within \[0, 10000\], got nan'),
        ({'sm_exponents': (1.0,) * 12}, r'sm_exponents must lie in \[0, 1\)'),
        ({'sm_gains': (0.1,) * 11}, 'sm_gains needs 12 numbers, one per state, got 11'),
        ({'l_min': 60.0}, r'l_min must be at most l_max \(50\), got 60.0'),
        ({'theta_initial': (0.0,) * 3}, 'theta_initial needs 16 entries, got 3'),
    ],
)
def test_invalid_configs_are_refused_with_a_reason(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        EstimatorConfig(**kwargs)
