"""The recent model-error offset of the predictions (fit_reference_offset and its use)."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.anticipation import AnticipationConfig, run_together
from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine
from cloe_ros.core.estimator import ConfigError, EstimatorConfig
from cloe_ros.core.identifier import generic_prior
from cloe_ros.core.kinematics import state_to_odometry, yaw_quaternion
from cloe_ros.core.model import discretise
from cloe_ros.core.prediction import (
    PredictionConfig,
    fit_reference_offset,
    fit_reference_offset_steps,
)
from cloe_ros.core.samples import OdometrySample, PoseSample

T0 = 1_700_000_000 * NS


def test_fit_recovers_the_offset_the_states_were_made_with():
    theta, coupling = generic_prior()
    ad, bd = discretise(theta, coupling, 0.1)
    rng = np.random.default_rng(3)
    refs = rng.normal(size=(6, 4)) * 0.3
    b_true = np.array([0.08, -0.05, 0.1, -0.2])
    states = [rng.normal(size=12) * 0.1]
    for k in range(5):
        states.append(ad @ states[-1] + bd @ (refs[k] + b_true))
    b = fit_reference_offset(ad, bd, np.array(states), refs, ridge=1e-9)
    np.testing.assert_allclose(b, b_true, rtol=1e-6)
    # states that follow the model exactly: no offset
    states = [states[0]]
    for k in range(5):
        states.append(ad @ states[-1] + bd @ refs[k])
    np.testing.assert_allclose(fit_reference_offset(ad, bd, np.array(states), refs), 0.0,
                               atol=1e-12)  # fmt: skip


def test_fit_without_data_or_with_nan_gives_no_offset():
    ad, bd = discretise(*generic_prior(), 0.1)
    assert not fit_reference_offset(ad, bd, np.zeros((1, 12)), np.zeros((1, 4))).any()
    states = np.zeros((4, 12))
    states[2, 0] = np.nan
    assert not fit_reference_offset(ad, bd, states, np.zeros((4, 4))).any()


def test_fits_answered_together_are_each_bitwise_the_fit_alone():
    """Six models' fits in one batched call (run_together), each bitwise the fit it gets alone;
    one window with a NaN is answered zeros without a request, beside them."""
    rng = np.random.default_rng(4)
    theta, coupling = generic_prior()
    problems = []
    for _ in range(6):
        ad, bd = discretise(theta * rng.uniform(0.8, 1.2, theta.shape), coupling, 0.1)
        problems.append((ad, bd, rng.normal(size=(6, 12)), rng.normal(size=(6, 4))))
    broken = problems[0][2].copy()
    broken[3, 1] = np.nan
    problems.append((*problems[0][:2], broken, problems[0][3]))
    together = run_together([fit_reference_offset_steps(*p) for p in problems])
    for p, got in zip(problems, together):
        np.testing.assert_array_equal(got, fit_reference_offset(*p))
    assert not together[-1].any() and together[0].any()


def _sinking_vehicle_predictions(
    disturbance_time: float, steps
) -> tuple[VehicleEngine, dict[int, np.ndarray]]:
    """A vehicle hovering at 1 m under a 1 m setpoint that, from t = 10 s, sinks at 0.5 m/s
    while the setpoint stays (as a landing logged late), sampled at 100 Hz on ``steps`` (indices
    of 10 ms). Returns the engine and its predictions by issue stamp."""
    # the closed loop's own prediction: no guard, no intent, the reference trusted
    engine = VehicleEngine(EngineConfig(
        estimator=EstimatorConfig('cloe_iv'),
        prediction=PredictionConfig(disturbance_time=disturbance_time),
        anticipation=AnticipationConfig(intent=False, guard=False, trust=False)))  # fmt: skip
    out = {}
    for k in steps:
        t = k / 100
        zeta = np.zeros(12)
        zeta[10], zeta[11] = (1.0, 0.0) if t < 10 else (1.0 - 0.5 * (t - 10), -0.5)
        stamp = T0 + k * NS // 100
        p, q, v, w = state_to_odometry(zeta)
        engine.add_odometry(OdometrySample(stamp, 'world', 'base_link', p, q, v, w))
        engine.add_reference(PoseSample(stamp, 'world', np.array([0.0, 0.0, 1.0]),
                                        yaw_quaternion(0.0)))  # fmt: skip
        for e in engine.advance():
            if e.prediction is not None:
                out[e.stamp_ns] = e.prediction[1]
    return engine, out


def _predictions_of_a_vehicle_leaving_its_setpoint(disturbance_time: float) -> np.ndarray:
    """The sinking vehicle's last prediction, issued at 10.6 s."""
    _, out = _sinking_vehicle_predictions(disturbance_time, range(1061))
    return out[max(out)]


def test_a_recent_model_error_carries_into_the_next_half_second_and_fades():
    held = _predictions_of_a_vehicle_leaving_its_setpoint(0.0)
    fitted = _predictions_of_a_vehicle_leaving_its_setpoint(0.5)
    actual_half_second = 1.0 - 0.5 * 1.1  # z at 11.1 s
    err_held = abs(held[4, 10] - actual_half_second)
    err_fitted = abs(fitted[4, 10] - actual_half_second)
    # the model alone pulls the vehicle back to its setpoint; the offset keeps it lower (a
    # constant offset on a stiff model cannot keep it sinking: 0.36 m off instead of 0.51 m)
    assert err_fitted < 0.8 * err_held, (err_fitted, err_held)
    # five seconds ahead, the offset has faded: both settle near the setpoint
    assert abs(fitted[-1, 10] - held[-1, 10]) < 0.02
    assert abs(fitted[4, 10] - held[4, 10]) > 0.05


def test_invalid_disturbance_time_is_refused():
    with pytest.raises(ConfigError, match='prediction_disturbance_time must be within'):
        PredictionConfig(disturbance_time=-1.0)
    with pytest.raises(ConfigError, match='prediction_disturbance_time must be within'):
        PredictionConfig(disturbance_time=float('nan'))


def _predictions_around_a_time_jump(disturbance_time: float) -> dict[int, np.ndarray]:
    """The sinking vehicle, whose odometry stops at 10.4 s and resumes at 12.4 s (a gap above
    ``max_gap``: the estimator restarts)."""
    engine, out = _sinking_vehicle_predictions(disturbance_time,
                                               [*range(1041), *range(1241, 1400)])  # fmt: skip
    assert engine.stats.time_jumps == 1
    return out


def test_the_recent_offset_starts_over_after_a_time_jump():
    """After a restart the window holds nothing from before the gap: until it has filled again
    (0.5 s), predictions are those without the correction."""
    with_offset = _predictions_around_a_time_jump(0.5)
    without = _predictions_around_a_time_jump(0.0)
    assert with_offset.keys() == without.keys()
    restart = T0 + 1241 * NS // 100
    for stamp in with_offset:
        same = np.array_equal(with_offset[stamp], without[stamp])
        if restart <= stamp < restart + NS // 2:
            assert same, (stamp - restart) / NS
    after = [s for s in with_offset if s >= restart + NS // 2]
    before = [s for s in with_offset if T0 + 10 * NS + NS // 5 <= s < restart]
    assert after and before
    # the vehicle was sinking on both sides of the gap: the correction is back once it can be
    assert not any(np.array_equal(with_offset[s], without[s]) for s in after + before)
