"""The fixed-step engine: timing on message stamps, rejection of bad input, time jumps."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cloe_ros.core.algorithms import make_estimator
from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine
from cloe_ros.core.estimator import (
    SM_GAINS_TABLE1,
    CloeEstimator,
    ConfigError,
    EstimatorConfig,
)
from cloe_ros.core.kinematics import state_to_odometry, wrap_angle, yaw_quaternion
from cloe_ros.core.samples import OdometrySample, PathSample, PoseSample
from cloe_ros.core.simulator import QuadrotorSimulator, get_scenario
from cloe_ros.core.timeline import UNPAIRED_SPAN_NS

T0 = 1_700_000_000 * NS  # an epoch-like start, as on real recordings


def odom(stamp_ns, zeta, frame='world'):
    p, q, v, w = state_to_odometry(zeta)
    return OdometrySample(stamp_ns, frame, 'base_link', p, q, v, w)


def ref(stamp_ns, r, frame='world'):
    return PoseSample(stamp_ns, frame, np.array([r[0], r[1], r[3]]), yaw_quaternion(r[2]))


def simulated_flight():
    """20 s of the position scenario sampled at 100 Hz (odometry) and 50 Hz (reference)."""
    sim = QuadrotorSimulator(get_scenario('position'), dt=1e-3)
    res = sim.run(20.0)
    return res.t[::10], res.zeta[::10, 0], res.reference[::10, 0]


@pytest.fixture(scope='module')
def flight():
    return simulated_flight()


def messages(flight, odom_every=1, ref_every=2):
    t, zeta, r = flight
    odoms = [(T0 + round(t[k] * NS), odom(T0 + round(t[k] * NS), zeta[k]))
             for k in range(0, len(t), odom_every)]  # fmt: skip
    refs = [(T0 + round(t[k] * NS), ref(T0 + round(t[k] * NS), r[k]))
            for k in range(0, len(t), ref_every)]  # fmt: skip
    return odoms, refs


def run(engine, sequence):
    out = []
    for kind, sample in sequence:
        reason = (engine.add_odometry if kind == 'odom' else engine.add_reference)(sample)
        assert reason is None, reason
        out.extend(engine.advance())
    return out


def in_time_order(odoms, refs):
    seq = [(s, 0, 'odom', m) for s, m in odoms] + [(s, 1, 'ref', m) for s, m in refs]
    return [(kind, m) for _, _, kind, m in sorted(seq, key=lambda x: (x[0], x[1]))]


def test_steps_on_the_grid_of_message_time(flight):
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig(rate=100.0))
    out = run(engine, in_time_order(odoms, refs)) + engine.finish()
    stamps = np.array([e.stamp_ns for e in out])
    assert np.all(np.diff(stamps) == NS // 100)
    assert stamps[0] == T0 and stamps[-1] == odoms[-1][0]
    assert len(out) == len(odoms)
    assert engine.stats.steps == len(out)
    # a 100 Hz CLOE-SM follows the measurements closely after the first seconds
    err = np.array([np.linalg.norm(e.error) for e in out if e.stamp_ns > T0 + 5 * NS])
    assert np.max(err) < 0.05


def test_result_does_not_depend_on_how_the_topics_interleave(flight):
    odoms, refs = messages(flight)
    base = VehicleEngine(EngineConfig())
    expected = run(base, in_time_order(odoms, refs)) + base.finish()
    rng = np.random.default_rng(3)
    for _ in range(3):
        # merge the two ordered streams at random: each topic stays in order
        i = j = 0
        seq = []
        while i < len(odoms) or j < len(refs):
            if j >= len(refs) or (i < len(odoms) and rng.random() < 0.6):
                seq.append(('odom', odoms[i][1]))
                i += 1
            else:
                seq.append(('ref', refs[j][1]))
                j += 1
        engine = VehicleEngine(EngineConfig())
        got = run(engine, seq) + engine.finish()
        assert [e.stamp_ns for e in got] == [e.stamp_ns for e in expected]
        np.testing.assert_array_equal(
            np.array([e.zeta_hat for e in got]), np.array([e.zeta_hat for e in expected])
        )


def test_engine_equals_the_core_estimator_on_grid_samples(flight):
    """Odometry exactly on the grid: the engine runs the same steps as CloeEstimator with
    zeta(t_k+1) and the reference of t_k. (CLOE: the sign terms of CLOE-SM would turn the
    round-off of the odometry conversions into O(h alpha) differences.)"""
    t, zeta, r = flight
    odoms, refs = messages(flight, ref_every=1)
    cfg = EstimatorConfig('cloe', l_initial=0.0)
    engine = VehicleEngine(EngineConfig(rate=100.0, estimator=cfg))
    out = run(engine, in_time_order(odoms, refs)) + engine.finish()
    est = CloeEstimator(cfg, zeta[0])
    for k in range(1, len(t)):
        est.step(zeta[k][None], r[k][None], 0.01)
    np.testing.assert_allclose(out[-1].zeta_hat, est.zeta_hat[0], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(out[-1].theta_hat, est.theta_hat[0], rtol=1e-9, atol=1e-11)


def _bad_messages(odoms):
    """Bad samples and where to insert them (after the odometry message with that index)."""
    s, good = odoms[300]
    nan = OdometrySample(s + NS // 200, 'world', 'base_link', np.array([np.nan, 0, 0]),
                         good.orientation, good.linear, good.angular)  # fmt: skip
    zero_q = OdometrySample(s + NS // 200, 'world', 'base_link', good.position,
                            np.zeros(4), good.linear, good.angular)  # fmt: skip
    frame = OdometrySample(s + NS // 200, 'map', 'base_link', good.position,
                           good.orientation, good.linear, good.angular)  # fmt: skip
    return [
        (300, 'odom', nan, 'non-finite odometry'),
        (300, 'odom', zero_q, 'invalid quaternion'),
        (300, 'odom', frame, 'wrong frame'),
        (300, 'odom', good, 'duplicate stamp'),
        (301, 'odom', odoms[299][1], 'out-of-order stamp'),
        (400, 'ref', PoseSample(odoms[400][0], 'world', np.array([np.inf, 0, 1]),
                                np.array([0, 0, 0, 1.0])), 'non-finite reference'),
        (400, 'ref', PoseSample(odoms[400][0], 'map', np.zeros(3), np.array([0, 0, 0, 1.0])),
         'wrong reference frame'),
    ]  # fmt: skip


def test_bad_input_is_rejected_counted_and_never_reaches_the_estimator(flight):
    odoms, refs = messages(flight, ref_every=1)
    clean = VehicleEngine(EngineConfig())
    expected = run(clean, in_time_order(odoms, refs)) + clean.finish()

    engine = VehicleEngine(EngineConfig())
    bad = _bad_messages(odoms)
    got = []
    for kind, sample in in_time_order(odoms, refs):
        add = engine.add_odometry if kind == 'odom' else engine.add_reference
        assert add(sample) is None
        got.extend(engine.advance())
        if kind != 'odom':
            continue
        index = next(i for i, (s, _) in enumerate(odoms) if s == sample.stamp_ns)
        for where, bad_kind, bad_sample, reason in bad:
            if where == index:
                add = engine.add_odometry if bad_kind == 'odom' else engine.add_reference
                assert add(bad_sample) == reason
    got.extend(engine.finish())
    assert dict(engine.stats.rejected) == {reason: 1 for *_, reason in bad}
    np.testing.assert_array_equal(
        np.array([e.zeta_hat for e in got]), np.array([e.zeta_hat for e in expected])
    )


def test_forward_time_jump_restarts_the_estimator_and_keeps_the_model(flight):
    odoms, refs = messages(flight)
    gap = 3 * NS
    shifted = [(s + gap, OdometrySample(s + gap, *[getattr(m, f) for f in (
        'frame_id', 'child_frame_id', 'position', 'orientation', 'linear', 'angular')]))
        for s, m in odoms[1000:]]  # fmt: skip
    shifted_refs = [(s + gap, PoseSample(s + gap, m.frame_id, m.position, m.orientation))
                    for s, m in refs if s >= odoms[1000][0]]  # fmt: skip
    first = [(s, m) for s, m in refs if s < odoms[1000][0]]
    engine = VehicleEngine(EngineConfig(max_gap=1.0))
    out = run(engine, in_time_order(odoms[:1000] + shifted, first + shifted_refs))
    out += engine.finish()
    stamps = np.array([e.stamp_ns for e in out])
    assert engine.stats.time_jumps == 1
    jump = np.flatnonzero(np.diff(stamps) > NS // 100)
    assert len(jump) == 1 and stamps[jump[0] + 1] - stamps[jump[0]] == gap + NS // 100
    before, after = out[jump[0]], out[jump[0] + 1]
    np.testing.assert_array_equal(after.zeta_hat, after.measured)  # re-initialised on the data
    np.testing.assert_array_equal(after.theta_hat, before.theta_hat)  # model kept


def test_a_new_max_gap_at_run_time_decides_the_next_jump(flight):
    """update_config (the node's runtime change of a timing tolerance) reaches the timeline: a
    2 s hole is a time jump for max_gap 1 s, and not once max_gap is 3 s."""
    odoms, refs = messages(flight)
    holed = odoms[:500] + odoms[700:]  # (2 s of odometry never came)
    jumps = {}
    for max_gap in (1.0, 3.0):
        engine = VehicleEngine(EngineConfig(max_gap=1.0))
        sequence = in_time_order(holed, refs)
        run(engine, sequence[:400])
        engine.update_config(replace(engine.config, max_gap=max_gap))
        run(engine, sequence[400:])
        assert engine.config.max_gap == max_gap
        jumps[max_gap] = engine.stats.time_jumps
    assert jumps == {1.0: 1, 3.0: 0}


def test_backward_time_jump_starts_a_new_timeline(flight):
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig())
    out = run(engine, in_time_order(odoms[:1500], refs[:750]))
    # the source restarts from the beginning (e.g. a simulation restarted with its /clock)
    out2 = run(engine, in_time_order(odoms[:300], refs[:150]))
    assert engine.stats.time_jumps == 1
    assert out2 and out2[-1].stamp_ns < out[-1].stamp_ns
    assert not engine.stats.rejected
    # the new timeline predicts at prediction_rate too (its periods are earlier than the old
    # timeline's last: they start over), not only once it passes the old timeline's time
    predicted = [e.stamp_ns for e in out2 if e.prediction is not None]
    period = round(NS / engine.config.prediction.rate)
    assert len(predicted) >= 3 * NS // period - 1
    assert set(np.diff(predicted[1:])) == {period}


def test_stopped_reference_is_held_after_the_timeout(flight):
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig(reference_timeout=0.25))
    out = run(engine, in_time_order(odoms, refs[:200]))  # reference stops at 4 s
    last_ref = refs[199][0]
    # steps went on past the last reference, lagging the odometry by at most the timeout
    assert out[-1].stamp_ns >= odoms[-1][0] - round(0.25 * NS) - NS // 100
    assert out[-1].stamp_ns > last_ref + 10 * NS
    out += engine.finish()
    assert out[-1].stamp_ns == odoms[-1][0]


def test_steps_between_references_wait_only_for_a_reference_that_is_due(flight):
    """10 Hz references, 100 Hz odometry, each reference sent with the odometry of its stamp.
    With reference_wait 'due' a step runs once its odometry is in, but for the one at which the
    next reference is due (90 ms after the last: it waits 10 ms); with 'stamps' every step waits
    for the next reference. Both give the
    same estimates; a reference that comes early, after the odometry of its stamp, applies from
    the next step."""
    odoms, refs = messages(flight, ref_every=10)
    seq = in_time_order(odoms[:1000], refs[:100])
    lag = {}
    for wait in ('due', 'stamps'):
        engine = VehicleEngine(EngineConfig(reference_wait=wait))
        out, behind = [], []
        for kind, m in seq:
            (engine.add_odometry if kind == 'odom' else engine.add_reference)(m)
            out += engine.advance()
            if kind == 'odom' and out:
                behind.append(m.stamp_ns - out[-1].stamp_ns)
        lag[wait] = (np.array(behind[20:]), out)
    due, stamps = lag['due'][0], lag['stamps'][0]
    # (the step 90 ms after a reference waits for the next: 10 ms, or 20 ms when the learnt
    # interval's round-off puts the step 90 ms after a reference at the limit)
    assert due.max() <= 2 * NS // 100 and np.mean(due == 0) > 0.8
    assert np.mean(stamps) > 0.04 * NS  # (up to 90 ms, about 45 ms on average)
    # ('due' is ahead at the end: the steps after the last reference do not wait for another)
    assert_same_estimates(lag['due'][1][: len(lag['stamps'][1])], lag['stamps'][1])
    # a reference 30 ms after the last one (due at 90 ms), after the odometry of its stamp
    engine = VehicleEngine(EngineConfig())
    early = refs[20][0] + 30 * NS // 1000
    out = []
    for kind, m in seq:
        if kind == 'ref' and m.stamp_ns > early:
            break
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(m)
        if kind == 'odom' and m.stamp_ns == early:
            r = ref(early, np.array([9.0, 0.0, 0.0, 1.0]))
            out += engine.advance()
            assert out[-1].stamp_ns == early and out[-1].reference[0] != 9.0
            assert engine.add_reference(r) is None
        out += engine.advance()
    after = [e for e in out if e.stamp_ns > early]
    assert after and all(e.reference[0] == 9.0 for e in after)


def assert_same_estimates(got, want):
    assert [e.stamp_ns for e in got] == [e.stamp_ns for e in want]
    for name in ('zeta_hat', 'theta_hat', 'reference'):
        np.testing.assert_array_equal(np.array([getattr(e, name) for e in got]),
                                      np.array([getattr(e, name) for e in want]), err_msg=name)


def test_yaw_is_unwrapped_across_pi():
    """A vehicle yawing steadily through +-pi: measured and estimated yaw stay continuous."""
    engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig('cloe_sm')))
    out = []
    for k in range(600):
        t = k * NS // 100
        yaw = 3.0 + 0.5 * k / 100  # crosses pi at t = 0.28 s and goes on to 6 rad
        zeta = np.zeros(12)
        zeta[[8, 9, 10]] = wrap_angle(yaw), 0.5, 1.0
        assert engine.add_odometry(odom(T0 + t, zeta)) is None
        r = np.array([0, 0, wrap_angle(yaw), 1.0])
        assert engine.add_reference(ref(T0 + t, r)) is None
        out.extend(engine.advance())
    yaw_hat = np.array([e.zeta_hat[8] for e in out])
    assert np.max(np.abs(np.diff(yaw_hat))) < 0.1
    assert yaw_hat[-1] == pytest.approx(3.0 + 0.5 * 5.99, abs=0.05)
    assert np.max(np.abs([e.reference[2] - e.measured[8] for e in out])) < 0.01


def test_reset_forgets_the_model_and_reinitialises(flight):
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    # a paper algorithm, whose identifier starts from zero (cloe_iv's starts from its prior)
    engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig('cloe_sm', l_initial=1.0)))
    out = run(engine, seq[:1200])
    assert np.any(out[-1].theta_hat != 0)
    engine.reset()
    after = run(engine, seq[1200:])
    assert engine.stats.resets == 1
    np.testing.assert_array_equal(after[0].theta_hat, np.zeros(16))
    np.testing.assert_array_equal(after[0].zeta_hat, after[0].measured)
    assert after[0].stamp_ns == out[-1].stamp_ns + NS // 100


def test_after_a_reset_the_inputs_kept_are_in_the_frame_they_came_in(flight):
    """The estimates of inputs that wait across a reset are in the frame those inputs came in;
    the next input sets the frame, and one in another frame drops them."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    engine = VehicleEngine(EngineConfig())
    run(engine, seq[:600])
    for kind, sample in seq[600:606]:  # (inputs of a batch not stepped yet)
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(sample)
    engine.reset()
    assert engine.advance() and engine.world_frame == 'world'
    # a source restarted in another frame: the inputs still waiting are dropped
    for kind, sample in seq[606:612]:
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(sample)
    engine.reset()
    moved = [(k, replace(m, frame_id='map')) for k, m in seq[612:700]]
    out = run(engine, moved)
    assert engine.world_frame == 'map' and not engine.stats.rejected
    assert out and out[0].stamp_ns >= moved[0][1].stamp_ns


@pytest.mark.parametrize(
    'kwargs, message',
    [
        ({'rate': 0.0}, r'rate must be within \[1, 2000\], got 0.0'),
        ({'rate': float('nan')}, 'rate must be within'),
        ({'max_gap': -1.0}, 'max_gap must be within'),
        ({'reference_timeout': 1e9}, 'reference_timeout must be within'),
        # (1 would accept a zero quaternion, which has no orientation: no yaw to take)
        ({'quaternion_tolerance': 1.0}, r'quaternion_tolerance must be within \[0, 1\)'),
    ],
)
def test_invalid_engine_config_is_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        EngineConfig(**kwargs)


def _iv_engine(seq, **estimator):
    engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig('cloe_iv', **estimator)))
    return engine, run(engine, seq)


def test_new_observer_gains_keep_the_identifiers_state(flight):
    """cloe_iv: a change that does not concern the identifier (gains of the observer, a setting
    it does not use) applies at once and keeps the state and the identified model."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    engine, out = _iv_engine(seq[:1200])
    twin, _ = _iv_engine(seq[:1200])
    est = engine._est
    assert np.any(out[-1].theta_hat != 0) and est.identifier.status.any()
    # gamma_theta: used by the paper's algorithms only, the twin runs on as if unchanged
    engine.update_estimator(replace(engine.config.estimator, gamma_theta=10.0))
    assert engine.stats.resets == 0 and engine._est is est
    after, twin_after = run(engine, seq[1200:1800]), run(twin, seq[1200:1800])
    np.testing.assert_array_equal(after[-1].theta_hat, twin_after[-1].theta_hat)
    np.testing.assert_array_equal(after[-1].zeta_hat, twin_after[-1].zeta_hat)
    # the observer's own gains apply from the next step on, to the same identifier
    gains = tuple(2.0 * g for g in SM_GAINS_TABLE1)
    engine.update_estimator(replace(engine.config.estimator, sm_gains=gains, l_max=30.0))
    assert engine.stats.resets == 0 and engine._est is est
    np.testing.assert_array_equal(est.lambda_[0], gains)
    assert est.config.l_max == 30.0
    after = run(engine, seq[1800:2000])
    assert engine._est is est and est.gain_l.max() <= 30.0
    # the identifier's own settings restart it (documented), forgetting the model
    identifier = replace(engine.config.estimator.identifier, window=30.0)
    engine.update_estimator(replace(engine.config.estimator, identifier=identifier))
    assert engine.stats.resets == 1 and engine._est is None
    restarted = run(engine, seq[2000:2100])
    assert restarted[0].stamp_ns == after[-1].stamp_ns + NS // 100
    assert engine._est.identifier.config.window == 30.0


def test_a_new_ground_altitude_applies_to_the_predictions_too(flight):
    """``ground_altitude`` applies at once (the node's runtime setting): to the identifier, and
    to the reference trust of the predictions, as in an engine started with it."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    engine, _ = _iv_engine(seq[:600])
    twin, _ = _iv_engine(seq[:600], ground_altitude=5.0)  # (the flight is below 5 m)
    assert engine._anticipator.trust.status().reasons[0] != 'commanded to the ground'
    engine.update_estimator(replace(engine.config.estimator, ground_altitude=5.0))
    run(engine, seq[600:700]), run(twin, seq[600:700])
    for e in (engine, twin):
        assert e._anticipator.trust.status().reasons == ('commanded to the ground',) * 4


def test_an_unchanged_estimator_config_changes_nothing(flight):
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    engine, _ = _iv_engine(seq[:600])
    est = engine._est
    engine.update_estimator(replace(engine.config.estimator))
    assert engine.stats.resets == 0 and engine._est is est


# -- implausible values, numerical failures -------------------------------------------------------

IV = EngineConfig(estimator=EstimatorConfig('cloe_iv'))


def _with(sample, **fields):
    return replace(sample, stamp_ns=sample.stamp_ns + NS // 200, **fields)


def _pitched(angle):
    return np.array([0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2)])


@pytest.mark.parametrize(
    'kind, change, reason, detail',
    [
        ('odom', {'position': np.array([1e200, 0, 1])}, 'position beyond 100000 m', '1e+200 m'),
        ('odom', {'position': np.array([0, -2e5, 1])}, 'position beyond 100000 m', '200000 m'),
        ('odom', {'linear': np.array([0, 0, 5e3])}, 'velocity beyond 150 m/s', '5000 m/s'),
        ('odom', {'angular': np.array([2e3, 0, 0])}, 'angular rate beyond 100 rad/s',
         '2000 rad/s'),
        ('odom', {'orientation': _pitched(math.pi / 2)}, 'tilt beyond 80 deg, outside the model',
         'pitch 90.0 deg'),
        ('odom', {'orientation': _pitched(math.radians(81))},
         'tilt beyond 80 deg, outside the model', 'pitch 81.0 deg'),
        ('ref', {'position': np.array([1e200, 0, 1])}, 'reference position beyond 100000 m',
         '1e+200 m'),
        ('odom', {'orientation': np.array([0, 0, 0, 1.2])}, 'invalid quaternion', 'norm 1.2'),
        ('odom', {'frame_id': 'map'}, 'wrong frame', "received 'map', expected 'world'"),
    ],
)  # fmt: skip
def test_implausible_values_are_rejected_and_say_what_was_wrong(flight, kind, change, reason,
                                                                 detail):  # fmt: skip
    """cloe_iv: one absurd but finite odometry or reference (a reference at 1e200 m made the
    identifier's SVD fail; an odometry at 1e100 m left the estimate 1e76 off; a pitch of 90 deg,
    where the Euler rates are singular, threw it 1e13 off) is rejected, naming the bound and the
    value, and the estimates are those of the clean run."""
    odoms, refs = messages(flight, ref_every=1)
    odoms, refs = odoms[:700], refs[:700]
    clean = VehicleEngine(IV)
    expected = run(clean, in_time_order(odoms, refs))
    engine = VehicleEngine(IV)
    seq = in_time_order(odoms, refs)
    at = seq.index(('odom', odoms[500][1])) + 1
    out = run(engine, seq[:at])
    good = odoms[500][1] if kind == 'odom' else refs[500][1]
    add = engine.add_odometry if kind == 'odom' else engine.add_reference
    rejection = add(_with(good, **change))
    assert rejection == reason and detail in rejection.detail, rejection.describe()
    assert engine.take_rejections() == [reason]
    out += engine.advance() + run(engine, seq[at:])
    assert dict(engine.stats.rejected) == {reason: 1} and engine.stats.diverged == 0
    np.testing.assert_array_equal(
        np.array([e.zeta_hat for e in out]), np.array([e.zeta_hat for e in expected])
    )


class _FailingEstimator:
    """An estimator whose step ``fail_at`` raises as a singular matrix would (LinAlgError)."""

    def __init__(self, est, fail_at):
        self._est, self._fail_at, self._steps = est, fail_at, 0

    def __getattr__(self, name):
        return getattr(self._est, name)

    def step(self, *args):
        self._steps += 1
        if self._steps == self._fail_at:
            raise np.linalg.LinAlgError('SVD did not converge')
        self._est.step(*args)


def test_a_numerical_failure_in_a_step_counts_as_divergence_and_restarts(flight):
    odoms, refs = messages(flight)
    made = []

    def factory(*args):
        made.append(_FailingEstimator(make_estimator(*args), fail_at=200 if not made else 0))
        return made[-1]

    engine = VehicleEngine(IV, estimator_factory=factory)
    out = run(engine, in_time_order(odoms[:600], refs[:300]))
    assert engine.stats.diverged == 1 and engine.stats.resets == 0 and len(made) == 2
    stamps = np.array([e.stamp_ns for e in out])
    # the failed step publishes nothing; the estimator restarts on the next step's data
    gap = np.flatnonzero(np.diff(stamps) != NS // 100)
    assert len(gap) == 1 and stamps[gap[0] + 1] - stamps[gap[0]] == 2 * NS // 100
    np.testing.assert_array_equal(out[gap[0] + 1].zeta_hat, out[gap[0] + 1].measured)
    assert all(np.all(np.isfinite(e.zeta_hat)) for e in out)


# -- quaternions of references and plans; plans ---------------------------------------------------


def _plan(stamps, frame='world', q=None, position=(1.0, 2.0, 1.5)):
    stamps = np.asarray(stamps, dtype=np.int64)
    q = yaw_quaternion(0.3) if q is None else np.asarray(q)
    return PathSample(int(stamps[0]), frame, stamps, np.tile(position, (len(stamps), 1)),
                      np.tile(q, (len(stamps), 1)))  # fmt: skip


def test_reference_quaternions_are_normalised_before_the_yaw_is_taken(flight):
    """1.09 q(90 deg) is within the norm tolerance; unnormalised its yaw would be 99 deg."""
    odoms, refs = messages(flight, ref_every=1)
    engine = VehicleEngine(EngineConfig())
    seq = []
    for (_, o), (_, r) in zip(odoms[:100], refs[:100]):
        scaled = replace(r, orientation=1.09 * yaw_quaternion(math.pi / 2))
        seq += [('ref', scaled), ('odom', o)]
    out = run(engine, seq)
    assert out and all(abs(e.reference[2] - math.pi / 2) < 1e-12 for e in out)


def test_plans_are_checked_and_normalised_like_references(flight):
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(odoms[:300], refs[:150]))
    now = odoms[299][0]
    future = now + NS // 10 * np.arange(1, 51)
    assert engine.add_plan(_plan(future, q=[0, 0, 0, 0])) == 'invalid plan quaternion'
    rejection = engine.add_plan(_plan(future, q=1.5 * yaw_quaternion(math.pi / 2)))
    assert rejection == 'invalid plan quaternion' and 'norm 1.5' in rejection.detail
    assert engine._plan is None
    assert engine.add_plan(_plan(future, q=1.09 * yaw_quaternion(math.pi / 2))) is None
    np.testing.assert_allclose(engine._plan[1][:, 2], math.pi / 2, atol=1e-12)
    accepted = engine._plan
    # a plan wholly in the past (100 s ago) or with equal stamps does not replace it
    assert engine.add_plan(_plan(future - 100 * NS)) == 'stale plan'
    assert engine.add_plan(_plan(np.full(50, now + NS))) == 'plan stamps not increasing'
    assert engine.add_plan(_plan([now - NS, now])) == 'stale plan'  # no pose after the latest
    assert engine._plan is accepted
    assert engine.add_plan(_plan([now - NS, now + 1])) is None  # one pose ahead is enough
    assert engine.add_plan(_plan(future, position=(1e6, 0, 1))) == 'plan position beyond 100000 m'
    assert dict(engine.stats.rejected) == {
        'invalid plan quaternion': 2, 'stale plan': 2, 'plan stamps not increasing': 1,
        'plan position beyond 100000 m': 1}  # fmt: skip


def test_a_plan_before_any_odometry_or_reference_does_not_set_the_frame(flight):
    """With world_frame '' the first odometry or reference sets the frame; a plan in 'map'
    arriving first used to lock it to 'map' and every later input was rejected."""
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig())
    rejection = engine.add_plan(_plan([T0, T0 + NS], frame='map'))
    assert rejection == 'plan before the world frame' and "'map'" in rejection.detail
    assert engine.world_frame is None
    out = run(engine, in_time_order(odoms[:100], refs[:50]))
    assert engine.world_frame == 'world' and len(out) > 50
    assert dict(engine.stats.rejected) == {'plan before the world frame': 1}


# -- time jumps and stamp outliers ----------------------------------------------------------------


def _stamped(sample, stamp_ns):
    return replace(sample, stamp_ns=stamp_ns)


def _run_with_a_glitch(flight, kind: str, index: int, offset_s: float):
    """The first 8 s of the flight, clean and with a copy of its ``kind`` ('odom' or 'ref')
    message ``index`` restamped by ``offset_s`` and sent right after it: (the engine of the
    glitched run, its estimates, the clean run's estimates)."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:800], refs[:400]
    seq = in_time_order(odoms, refs)
    clean = VehicleEngine(EngineConfig())
    expected = run(clean, seq) + clean.finish()
    stamp, sample = (odoms if kind == 'odom' else refs)[index]
    at = seq.index((kind, sample)) + 1
    glitch = _stamped(sample, stamp + round(offset_s * NS))
    engine = VehicleEngine(EngineConfig())
    out = run(engine, [*seq[:at], (kind, glitch), *seq[at:]]) + engine.finish()
    return engine, out, expected


@pytest.mark.parametrize('offset_s', [100.0, -5.0])
def test_a_single_odometry_stamp_off_the_timeline_is_an_outlier(flight, offset_s):
    """One odometry stamp 100 s ahead (or 5 s behind) is not a time jump: the next one continues
    the old timeline, so it is rejected as a stamp outlier; published stamps never go back (they
    went 4.99 -> 105.0 -> 5.01 s) and the estimates are those of the clean run."""
    engine, out, expected = _run_with_a_glitch(flight, 'odom', 500, offset_s)
    assert engine.stats.time_jumps == 0
    assert dict(engine.stats.rejected) == {'stamp outlier': 1}
    (rejection,) = engine.take_rejections()
    assert f'{offset_s:+g} s from the timeline' in rejection.detail, rejection.detail
    stamps = np.array([e.stamp_ns for e in out])
    assert np.all(np.diff(stamps) > 0)
    np.testing.assert_array_equal(
        np.array([e.zeta_hat for e in out]), np.array([e.zeta_hat for e in expected])
    )


@pytest.mark.parametrize('offset_s', [-5.0, 100.0])
def test_a_single_reference_stamp_off_the_timeline_is_an_outlier(flight, offset_s):
    """A reference 5 s before the latest one used to be taken silently, clearing the references;
    it is held aside, and counted as an outlier when the next one continues the timeline."""
    engine, out, expected = _run_with_a_glitch(flight, 'ref', 250, offset_s)
    assert engine.stats.time_jumps == 0
    assert dict(engine.stats.rejected) == {'reference stamp outlier': 1}
    np.testing.assert_array_equal(
        np.array([e.zeta_hat for e in out]), np.array([e.zeta_hat for e in expected])
    )


def _new_timeline(out):
    """The estimates from the first one stamped before its predecessor on (the old timeline's
    last steps, if any ran no earlier, come first: they are finished when the jump is
    confirmed)."""
    back = np.flatnonzero(np.diff([e.stamp_ns for e in out]) < 0)
    assert len(back) <= 1
    return out[back[0] + 1 :] if len(back) else out


def test_a_latched_reference_of_a_restarted_source_is_kept(flight):
    """A source restarted from t = 0 publishes its setpoint once (latched), before its first
    odometry: that reference belongs to the new timeline, and the estimator restarts on it."""
    t, zeta, r = flight
    hover = r[0]
    engine = VehicleEngine(EngineConfig())

    def timeline():
        return [('ref', ref(T0, hover))] + [
            ('odom', odom(T0 + round(t[k] * NS), zeta[k])) for k in range(300)
        ]

    first = run(engine, timeline())
    second = _new_timeline(run(engine, timeline()))
    assert engine.stats.time_jumps == 1 and not engine.stats.rejected
    assert len(second) == len(first) and second[0].stamp_ns == T0
    np.testing.assert_array_equal(second[0].zeta_hat, second[0].measured)


def test_a_restart_whose_references_come_first_keeps_them(flight):
    """References of the new timeline that arrive before its odometry (or between its first two
    odometry messages) are the new timeline's; those of the old one are dropped."""
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(odoms[:500], refs[:250]))
    # the restarted source: its first references, then the odometry with the rest interleaved
    seq = [('ref', m) for _, m in refs[:3]] + in_time_order(odoms[:400], refs[3:200])
    after = _new_timeline(run(engine, seq) + engine.finish())
    fresh = VehicleEngine(EngineConfig())
    alone = run(fresh, in_time_order(odoms[:400], refs[:200])) + fresh.finish()
    assert engine.stats.time_jumps == 1 and not engine.stats.rejected
    assert after[0].stamp_ns == T0
    assert [e.stamp_ns for e in after] == [e.stamp_ns for e in alone]
    np.testing.assert_array_equal(
        np.array([e.reference for e in after]), np.array([e.reference for e in alone])
    )


def test_one_input_without_the_other_is_kept_for_a_bounded_span(flight):
    """Odometry with no reference yet, and references whose odometry stopped, are kept for
    UNPAIRED_SPAN_NS back from the newest (the memory of a vehicle streaming one input stays
    bounded); an estimator that starts then gives what it gives on the inputs kept."""
    odoms, refs = messages(flight)  # 100 Hz odometry, 50 Hz references, 20 s
    late = [(s, m) for s, m in refs if s >= T0 + 15 * NS]  # no reference for 15 s
    engine = VehicleEngine(EngineConfig())
    run(engine, [('odom', m) for s, m in odoms if s < late[0][0]])
    assert not engine.started
    assert len(engine._timeline.odom) == UNPAIRED_SPAN_NS // (NS // 100) + 1  # (of 1500)
    got = run(engine, in_time_order([(s, m) for s, m in odoms if s >= late[0][0]], late))
    kept = [(s, m) for s, m in odoms if s >= late[0][0] - UNPAIRED_SPAN_NS]
    fresh = VehicleEngine(EngineConfig())
    want = run(fresh, in_time_order(kept, late))
    got, want = got + engine.finish(), want + fresh.finish()
    assert got and got[0].stamp_ns == late[0][0]
    assert [e.stamp_ns for e in got] == [e.stamp_ns for e in want]
    for name in ('zeta_hat', 'theta_hat', 'reference'):  # (the same to round-off: the yaw is
        np.testing.assert_allclose(  # unwrapped from other samples, the identifier amplifies it)
            np.array([getattr(e, name) for e in got]), np.array([getattr(e, name) for e in want]),
            rtol=1e-8, atol=1e-12, err_msg=name)  # fmt: skip

    # the odometry stops after 5 s, the references go on for 15 s
    engine = VehicleEngine(EngineConfig())
    out = run(engine, in_time_order(odoms[:500], [(s, m) for s, m in refs if s < odoms[500][0]]))
    run(engine, [('ref', m) for s, m in refs if s >= odoms[500][0]])
    assert engine.started and out
    assert len(engine._timeline.refs) <= UNPAIRED_SPAN_NS // (NS // 50) + 1  # (of 750)
    assert engine._timeline.refs[-1][0] == refs[-1][0]
