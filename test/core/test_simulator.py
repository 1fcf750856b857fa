"""The nonlinear simulator against independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.model import parameters_from_matrices, system_matrices
from cloe_ros.core.simulator import (
    PAPER_PRINTED_GAINS,
    SCENARIOS,
    ControllerGains,
    MeasurementNoise,
    NoDisturbance,
    PaperDisturbance,
    ProbingSignal,
    QuadrotorParams,
    QuadrotorSimulator,
    closed_loop_derivative,
    closed_loop_poles,
    get_scenario,
    model_to_plant,
    plant_to_model,
    true_parameters,
)


def _finite_difference_linearization(quad, gains, z0=1.0, eps=1e-6):
    """A (12, 12) and B (12, 4) in model-state order by central differences of the nonlinear
    closed loop at hover."""
    zeta0 = np.zeros(12)
    zeta0[10] = z0
    ref0 = np.array([0.0, 0.0, 0.0, z0])

    def f(zeta, ref):
        s = model_to_plant(zeta)[None]
        return plant_to_model(closed_loop_derivative(s, ref[None], np.zeros(6), quad, gains))[0]

    a = np.empty((12, 12))
    for j in range(12):
        d = np.zeros(12)
        d[j] = eps
        a[:, j] = (f(zeta0 + d, ref0) - f(zeta0 - d, ref0)) / (2 * eps)
    b = np.empty((12, 4))
    for j in range(4):
        d = np.zeros(4)
        d[j] = eps
        b[:, j] = (f(zeta0, ref0 + d) - f(zeta0, ref0 - d)) / (2 * eps)
    return a, b


@pytest.mark.parametrize(
    'quad, gains',
    [
        (QuadrotorParams(), ControllerGains()),
        (QuadrotorParams(mass=1.3, inertia=(0.02, 0.03, 0.05)),
         ControllerGains(k_px=0.2, k_vx=0.3, k_py=0.15, k_vy=0.25, k_pz=40.0, k_vz=9.0)),
    ],
)  # fmt: skip
def test_true_theta_is_the_hover_linearization(quad, gains):
    a_fd, b_fd = _finite_difference_linearization(quad, gains)
    a_model, b_model = system_matrices(true_parameters(quad, gains))
    # the whole structure, known rows and +-g coupling included, matches the nonlinear model
    np.testing.assert_allclose(a_fd, a_model, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(b_fd, b_model, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(
        parameters_from_matrices(a_fd, b_fd), true_parameters(quad, gains), rtol=1e-6
    )


def test_poles_stable_and_printed_gains_unstable():
    for name, poles in closed_loop_poles().items():
        assert np.all(poles.real < 0), name
    np.testing.assert_allclose(
        sorted(closed_loop_poles()['x_theta'], key=lambda z: (z.real, z.imag)),
        [-6.881 - 5.867j, -6.881 + 5.867j, -0.619 - 0.904j, -0.619 + 0.904j],
        atol=2e-3,
    )
    # the gains as printed, with the attitude gains as normalised torques (J = 1): unstable
    poles = closed_loop_poles(QuadrotorParams(inertia=(1.0, 1.0, 2.0)), PAPER_PRINTED_GAINS)
    assert np.max(poles['x_theta'].real) == pytest.approx(0.47, abs=0.01)


def test_paper_disturbance_values():
    d = PaperDisturbance()(np.array([0.0, 1.0]))
    assert d.shape == (2, 6)
    np.testing.assert_allclose(d[0], [0.01, 0.0, 0.01, 0.01, 0.0, 0.01])
    np.testing.assert_allclose(d[1, 2], 0.3 * np.sin(1.2) + 0.01 * np.cos(0.2), rtol=1e-12)
    np.testing.assert_array_equal(NoDisturbance()(np.array([1.0, 2.0])), np.zeros((2, 6)))


def test_scenarios_follow_the_paper():
    pos = get_scenario('position').reference(np.array([0.0, 4.0, 13.4, 50.0]))
    np.testing.assert_allclose(pos[:, 0], [0.0, 0.0, 0.6, 0.6])
    np.testing.assert_allclose(pos[:, 1], [0.0, 0.0, 1.0, 1.0])
    np.testing.assert_allclose(pos[:, 3], [0.05, 1.0, 1.0, 1.0])
    traj = get_scenario('trajectory').reference(np.array([10.0]))[0]
    w = 0.03
    np.testing.assert_allclose(
        traj, [1.6 * np.sin(w * 10), 3 * np.sin(w * 10) * np.cos(w * 10), np.pi / 16, 1.0]
    )
    with pytest.raises(ValueError, match="unknown scenario 'loop'; known: position"):
        get_scenario('loop')


def test_probing_signal_is_documented_sum_of_sines():
    p = ProbingSignal()
    t = np.linspace(0, 100, 20001)
    tau = p(t)
    for c in range(4):
        expected = sum(a * np.sin(w * t + ph) for a, w, ph in
                       zip(p.amplitudes[c], p.frequencies[c], p.phases[c]))  # fmt: skip
        np.testing.assert_allclose(tau[:, c], expected)
    # a few centimetres / hundredths of a radian
    assert np.max(np.abs(tau[:, [0, 1, 3]])) < 0.12 and np.max(np.abs(tau[:, 2])) < 0.06


def test_vehicle_tracks_the_position_scenario():
    sim = QuadrotorSimulator(SCENARIOS['position'], probing=ProbingSignal().scaled(0.0), dt=2e-3)
    res = sim.run(30.0)
    final = res.zeta[-1, 0]
    assert final[[0, 4, 10]] == pytest.approx([0.6, 1.0, 1.0], abs=2e-3)
    assert np.max(np.abs(res.zeta[:, 0, [2, 6]])) < 0.3  # small tilt all along


def test_rk4_converges_with_fourth_order():
    """Halving dt divides the end-point difference to a fine reference by about 16.

    Constant reference (the controller samples the reference once per step, which is first order
    in dt for a moving reference), a displaced start and the continuous disturbances.
    """

    def end(dt):
        sim = QuadrotorSimulator(get_scenario('hover'), disturbance=PaperDisturbance(),
                                 probing=ProbingSignal().scaled(0.0), dt=dt)  # fmt: skip
        sim.state[0, [0, 1, 2, 8]] = [0.5, -0.3, 0.2, 0.4]
        return sim.run(3.0).zeta[-1, 0]

    ref = end(1.25e-4)
    e1 = np.linalg.norm(end(2e-3) - ref)
    e2 = np.linalg.norm(end(1e-3) - ref)
    assert 8.0 < e1 / e2 < 24.0


def test_noise_is_seeded_and_has_the_requested_sigma():
    noise = MeasurementNoise(position=0.002, velocity=0.01, angle=0.002, rate=0.01)
    runs = []
    for _ in range(2):
        sim = QuadrotorSimulator(get_scenario('hover'), noise=noise,
                                 rng=np.random.default_rng(7), dt=5e-3)  # fmt: skip
        runs.append(sim.run(20.0))
    np.testing.assert_array_equal(runs[0].measured, runs[1].measured)
    residual = (runs[0].measured - runs[0].zeta)[:, 0]
    np.testing.assert_allclose(residual.std(axis=0), noise.sigma, rtol=0.05)


def test_batch_of_vehicles_with_offsets():
    offsets = np.array([[0.0, 0.0, 0.0], [2.0, -1.0, 0.5]])
    sim = QuadrotorSimulator(get_scenario('hover'), n_vehicles=2, offsets=offsets, dt=5e-3)
    res = sim.run(10.0)
    np.testing.assert_allclose(res.zeta[-1, 1, [0, 4, 10]] - res.zeta[-1, 0, [0, 4, 10]],
                               [2.0, -1.0, 0.5], atol=1e-3)  # fmt: skip


def test_invalid_simulator_settings_are_refused():
    with pytest.raises(ValueError, match='dt must be in'):
        QuadrotorSimulator(get_scenario('hover'), dt=0.5)
    with pytest.raises(ValueError, match='2 disturbances for 1 vehicles'):
        QuadrotorSimulator(get_scenario('hover'), disturbance=[NoDisturbance(), NoDisturbance()])
