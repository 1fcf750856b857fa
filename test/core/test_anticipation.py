"""The parts of anticipation with a known answer: intent fits, the guard's weights, the radius's
coverage, the virtual reference, the physical envelope."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.anticipation import (
    AnticipationConfig,
    CoverageRadius,
    Ensemble,
    HarmonicFits,
    History,
    Propagation,
    SimplexWeights,
    VirtualReference,
    answer,
    clip_to_envelope,
    harmonic_fit,
    harmonic_fits,
    last_jump,
    linear_fit,
    median,
    run,
    run_together,
    simplex_weights,
    turn_positions,
)
from cloe_ros.core.identifier import cascade_prior
from cloe_ros.core.model import BLOCKS, discretise, system_matrices
from cloe_ros.errors import ConfigError


def test_a_circle_is_extrapolated_by_the_shared_frequency_fit():
    w = 2 * np.pi / 7.0
    t = np.linspace(-3.0, 0.0, 61)
    circle = np.column_stack([1.5 + np.cos(w * t), -0.5 + np.sin(w * t)])
    ahead = np.linspace(0.0, 5.0, 11)
    out = harmonic_fit(t, circle, ahead, 2 * np.pi / np.geomspace(1.5, 30.0, 400), joint=True)
    truth = np.column_stack([1.5 + np.cos(w * ahead), -0.5 + np.sin(w * ahead)])
    np.testing.assert_allclose(out, truth, atol=0.02)


def test_one_solve_gives_each_column_its_own_fit_and_the_joint_fit():
    rng = np.random.default_rng(3)
    t = np.linspace(-6.0, 0.0, 121)
    y = np.column_stack([np.cos(0.9 * t), 2 * np.sin(0.9 * t), 0.4 * np.cos(2.1 * t), 0.2 * t])
    y += 0.01 * rng.standard_normal(y.shape)
    ahead, omegas = np.linspace(0.0, 3.0, 7), 2 * np.pi / np.geomspace(1.5, 30.0, 60)
    separate, joint = harmonic_fits(t, y, ahead, omegas, np.array([0, 1]))
    for c in range(4):  # a column's fit is the one it gets alone
        np.testing.assert_allclose(separate[:, c], harmonic_fit(t, y[:, [c]], ahead, omegas)[:, 0],
                                   rtol=0, atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(joint, harmonic_fit(t, y[:, :2], ahead, omegas, joint=True),
                               rtol=0, atol=1e-12)  # fmt: skip


def test_the_history_interpolates_every_channel_as_np_interp():
    rng = np.random.default_rng(4)
    history = History(2.0, 100.0)
    for k in range(350):  # more than its buffer holds: the newest rows move to its front
        t = 0.01 * k + 0.002 * rng.random()
        history.append(t, rng.standard_normal(12), rng.standard_normal(12), rng.standard_normal(4),
                       rng.standard_normal(4))  # fmt: skip
    t, data = history.ordered('t'), history.ordered('measured')
    inside = rng.uniform(t[0], t[-1], size=(4, 5))
    edges = np.array([t[0], t[-1], t[7], t[0] - 1e-10, t[-1] + 1e-10])
    for times in (inside, edges, t[3:4], np.array([0.5 * (t[3] + t[4])])):
        got = history.at(times, 'measured', [0, 4, 10])
        want = np.stack([np.interp(times, t, data[:, c]) for c in (0, 4, 10)], axis=-1)
        np.testing.assert_array_equal(got, want)
    outside = np.array([t[0] - 1e-6, t[-1] + 1e-6, np.nan])
    assert np.isnan(history.at(outside, 'measured', [0, 4])).all()
    assert np.isnan(history.at(outside[:1], 'measured', list(range(12)))).all()


def test_the_history_holds_the_latest_steps_in_order_across_its_buffers_moves():
    """Appended well past its buffer's length (the newest rows move to its front several times),
    and cleared on the way, the history holds exactly the last ``capacity`` steps, oldest first,
    and its views are those steps' values."""
    rng = np.random.default_rng(5)
    history = History(0.5, 100.0)
    steps = []
    for k in range(5 * len(history.t)):
        if k == 2 * len(history.t) + 3:
            history.clear()
            steps.clear()
        step = (0.01 * k, *rng.standard_normal((2, 12)), *rng.standard_normal((2, 4)))
        history.append(*step)
        steps.append(step)
        held = steps[-history.capacity :]
        for c, name in enumerate(History.COLUMNS):
            np.testing.assert_array_equal(history.ordered(name), np.array([s[c] for s in held]))
        recent = history.last(0.1)
        np.testing.assert_array_equal(history.t[recent], [s[0] for s in held[-11:]])


def test_a_line_is_extrapolated_by_the_linear_fit():
    t = np.linspace(-1.0, 0.0, 21)
    y = np.column_stack([0.3 + 0.7 * t, -2.0 * t])
    np.testing.assert_allclose(linear_fit(t, y, np.array([1.0, 2.0])), [[1.0, -2.0], [1.7, -4.0]])


def test_the_fits_start_after_the_last_jump_of_the_reference():
    r = np.zeros((50, 3))
    r[:, 0] = 0.01 * np.arange(50)
    assert last_jump(r) == 0
    r[30:, 1] += 1.0  # a 1 m step of the setpoint
    assert last_jump(r) == 30


def test_minimum_variance_weights_of_independent_candidates():
    # independent errors of variance 1 and 4: w = (4, 1) / 5
    s = np.array([[[1.0, 0.0], [0.0, 4.0]]])
    np.testing.assert_allclose(simplex_weights(s, np.ones(2, bool), shrink=0.0), [[0.8, 0.2]])
    # a candidate not allowed gets nothing
    np.testing.assert_allclose(simplex_weights(s, np.array([False, True])), [[0.0, 1.0]])


def test_weights_stay_on_the_simplex_when_the_unconstrained_optimum_is_negative():
    # strongly correlated candidates, the second worse: the unconstrained solution shorts it
    s = np.array([[[1.0, 1.9], [1.9, 4.0]]])
    w = simplex_weights(s, np.ones(2, bool), shrink=0.0)
    assert np.all(w >= 0) and np.isclose(w.sum(), 1.0)
    np.testing.assert_allclose(w, [[1.0, 0.0]])


def test_each_horizons_weights_are_those_it_gets_alone():
    rng = np.random.default_rng(5)
    a = rng.standard_normal((40, 5, 3)) + 2.0 * rng.standard_normal((1, 5, 3))
    s = a @ np.swapaxes(a, 1, 2)  # some horizons need several active-set rounds, some one
    allowed = np.array([True, True, False, True, True])
    together = simplex_weights(s, allowed)
    for k in range(len(s)):
        np.testing.assert_array_equal(together[k], simplex_weights(s[k : k + 1], allowed)[0])
    assert np.allclose(together.sum(axis=1), 1.0) and (together >= 0).all()
    assert (together[:, 2] == 0).all()


#: A truth of 0 at every time of the ensembles' tests: its times, values and channel.
AT_REST = (np.array([-1.0, 100.0]), np.zeros((2, 1)), [0])


def test_the_ensemble_learns_which_candidate_is_right_at_each_horizon():
    """Candidate A is exact up to 1 s and then off by 1 m; B is off by 0.3 m everywhere."""
    offsets = np.array([0.5, 1.0, 2.0, 5.0])
    ens = Ensemble(('a', 'b'), offsets, 1, score_time=5.0, period=0.2, max_pending=40)
    rng = np.random.default_rng(0)
    for i in range(200):
        t = 0.2 * i
        a = np.where(offsets <= 1.0, 0.0, 1.0)[:, None] + 0.01 * rng.normal(size=(4, 1))
        b = np.full((4, 1), 0.3) * rng.choice([-1, 1], size=(4, 1))
        ens.add(t, np.stack([a, b]))
        ens.score(t - 0.2, t, *AT_REST)
    w = ens.weights()
    assert w[0, 0] > 0.95 and w[1, 0] > 0.95  # A at 0.5 s and 1 s
    assert w[2, 1] > 0.85 and w[3, 1] > 0.85  # B at 2 s and 5 s


def test_unscored_horizons_take_the_growth_of_the_scored_ones():
    """Only the 0.5 s and 1 s horizons have scores: A's error doubles from 0.5 to 1 s (it
    extrapolates), B's stays; at 5 s the guard must already prefer B."""
    offsets = np.array([0.5, 1.0, 2.0, 5.0])
    ens = Ensemble(('a', 'b'), offsets, 1, score_time=5.0, period=0.2, max_pending=40)
    for i in range(9):  # 1.6 s: the 2 s and 5 s horizons have no score yet
        t = 0.2 * i
        a = np.array([[0.1], [0.2], [0.4], [1.0]]) * (-1) ** i
        b = np.full((4, 1), 0.25) * (-1) ** (i + 1)
        ens.add(t, np.stack([a, b]))
        ens.score(t - 0.2, t, *AT_REST)
    assert ens.scored[:2].all() and not ens.scored[2:].any()
    w = ens.weights()
    assert w[0, 0] > 0.5 and w[3, 1] > 0.8, w


def test_scores_of_one_horizon_due_together_are_weighed_in_in_order():
    """Scored in one call over a long span (a horizon due for several predictions at once), the
    ensemble ends where scoring after every prediction ends, and returns the same scores."""
    offsets = np.array([0.2, 0.6, 1.0])
    rng = np.random.default_rng(4)
    paths = rng.normal(size=(12, 2, 3, 2))
    times = np.linspace(-1.0, 4.0, 5001)
    truth = (times, np.column_stack([np.sin(times), np.cos(times)]), [0, 1])
    step, once = (Ensemble(('a', 'b'), offsets, 2, score_time=1.0, period=0.2, max_pending=40)
                  for _ in range(2))  # fmt: skip
    by_step = []
    for i, path in enumerate(paths):
        for ens in (step, once):
            ens.add(0.2 * i, path)
        by_step.append(step.score(0.2 * i - 0.2, 0.2 * i, *truth))
    at_once = [once.score(-0.2, 0.2 * (len(paths) - 1), *truth)]
    np.testing.assert_allclose(once.cross, step.cross, rtol=1e-14, atol=0)
    assert once.scored.tolist() == step.scored.tolist() == [True] * 3
    # the same (prediction, horizon) scores, whichever call gave them
    flat = lambda out: sorted((round(t0, 9), int(k), tuple(sq)) for s in out  # noqa: E731
                              for t0, k, sq in zip(s.issued, s.horizons, s.squared))  # fmt: skip
    assert len(flat(at_once)) == len(flat(by_step)) == sum(int(np.sum(0.2 * i + offsets <= 2.2
                                                                      + 1e-9)) for i in range(12))
    np.testing.assert_allclose([s[2] for s in flat(at_once)], [s[2] for s in flat(by_step)],
                               rtol=1e-14)  # fmt: skip


def test_scores_are_the_interpolated_errors_weighed_in_one_by_one():
    """The ensemble's cross-products, written out: each due pose's error against the truth
    interpolated as ``np.interp`` does, weighed in pose by pose (by slot, then horizon; the
    first at a horizon with weight 1); poses beyond the truth's span or on a NaN truth are not
    scored, and a prediction whose poses are all due is forgotten."""
    rng = np.random.default_rng(11)
    offsets = np.array([0.1, 0.3, 0.7])
    ens = Ensemble(('a', 'b', 'c'), offsets, 2, score_time=0.8, period=0.2, max_pending=6)
    times = np.sort(rng.uniform(0.0, 2.0, 300))
    truth = rng.normal(size=(300, 3))
    truth[150, 2] = np.nan  # a pose that needs this sample is not scored
    paths = rng.normal(size=(9, 3, 3, 2))
    for i, path in enumerate(paths):
        ens.add(0.2 * i, path)
    kept = [6, 7, 8, 3, 4, 5]  # the prediction in each of the 6 slots (the oldest dropped)
    got = ens.score(0.25, 2.2, times, truth, [0, 2])
    cross, scored, want = np.zeros((3, 3, 3)), np.zeros(3, dtype=bool), []
    alpha = 1.0 - np.exp(-0.2 / 0.8)
    for slot, i in enumerate(kept):  # by slot, then horizon
        for k, when in enumerate(0.2 * i + offsets):
            if not (0.25 + 1e-9 < when <= 2.2 + 1e-9) or when > times[-1] + 1e-9:
                continue
            actual = np.array([np.interp(when, times, truth[:, c]) for c in (0, 2)])
            if not np.isfinite(actual).all():
                continue
            err = paths[i, :, k] - actual
            weight = alpha if scored[k] else 1.0
            cross[k] += weight * (err @ err.T - cross[k])
            scored[k] = True
            want.append((slot, 0.2 * i, k, (err**2).sum(axis=1)))
    assert 10 < len(want) < 18  # (some poses beyond the truth, one on its NaN)
    np.testing.assert_array_equal(got.slots, [w[0] for w in want])
    np.testing.assert_array_equal(got.issued, [w[1] for w in want])
    np.testing.assert_array_equal(got.horizons, [w[2] for w in want])
    np.testing.assert_allclose(got.squared, [w[3] for w in want], rtol=1e-13)
    np.testing.assert_allclose(ens.cross, cross, rtol=1e-12, atol=1e-15)
    assert ens.scored.tolist() == scored.tolist()
    # every prediction issued by 2.2 - 0.7 s has had all its poses due: forgotten
    assert ens.score(2.2, 2.2, times, truth, [0, 2]).slots.size == 0
    assert np.isnan(ens._pending_t).sum() == sum(0.2 * i + 0.7 <= 2.2 + 1e-9 for i in kept)


@pytest.mark.parametrize('scale', [0.01, 1.0])
def test_the_radius_covers_95_percent_of_errors_of_any_scale(scale):
    offsets = np.array([0.5, 1.0])
    rad = CoverageRadius(offsets, coverage=0.95)
    rng = np.random.default_rng(1)
    inside, n = 0, 0
    scales = np.ones(2)
    for i in range(3000):
        r = rad.radii(scales)
        e = scale * np.abs(rng.standard_t(3, size=2)) * np.array([1.0, 2.0])  # heavy tails
        if i >= 200:
            inside += np.count_nonzero(e <= r)
            n += 2
        rad.update(np.arange(2), e, r, scales)
    assert 0.93 <= inside / n <= 0.97, inside / n


def test_the_radius_is_finite_and_grows_beyond_the_scored_horizons():
    rad = CoverageRadius(np.array([0.5, 1.0, 2.0]), coverage=0.95)
    assert np.all(rad.radii(np.ones(3)) == rad.prior)  # nothing scored yet: the prior
    for _ in range(20):  # only the two first horizons are scored
        rad.update(np.arange(2), np.array([0.3, 0.1]), np.zeros(2), np.ones(2))
    r = rad.radii(np.array([1.0, 1.0, 3.0]))
    assert np.all(np.isfinite(r)) and np.all(r > 0)
    # a later pose is never more certain than an earlier one (the 1 s errors are the smaller)
    assert r[1] == r[0]
    # the last horizon takes the longest scored one's score (0.1), times its own scale (3)
    assert r[2] == pytest.approx(3.0 * 0.1)


def test_the_virtual_reference_makes_a_constant_velocity_motion_unforced():
    """Under its own virtual reference, a block moving at constant velocity has (to first order)
    no acceleration: the reference is where the closed loop's ramp response puts it."""
    theta = np.array([-8.0, -6.0, -40.0, -9.0, 8.0, -8.0, -6.0, -40.0, -9.0, 8.0,
                      -20.0, -6.0, 20.0, -30.0, -8.0, 30.0])  # fmt: skip
    coupling = np.array([9.81, -9.81])
    a, b = system_matrices(theta, coupling)
    virtual = VirtualReference()
    virtual.update(theta, coupling, BLOCKS)
    # z block (2nd order): z'' = -30 z - 8 z' + 30 r: gain 1, delay 8/30 s
    assert virtual.gain[3] == pytest.approx(1.0)
    assert virtual.delay[3] == pytest.approx(8.0 / 30.0)
    zeta = np.zeros(12)
    zeta[10], zeta[11] = 1.0, 0.5
    r = virtual.of(zeta)
    z_ddot = a[11] @ zeta + b[11] @ r
    assert z_ddot == pytest.approx(0.0, abs=1e-12)


def test_predictions_are_kept_within_reach_of_a_quadrotor():
    p0, v0 = np.zeros(3), np.array([1.0, 0.0, 0.0])
    offsets = np.array([0.5, 1.0, 5.0])
    far = np.array([[1e4, 0.0, 0.0], [0.5, 0.0, 0.0], [7e5, 2e5, 0.0]])
    out = clip_to_envelope(p0, v0, offsets, far, max_speed=150.0, max_acceleration=100.0)
    reach = np.minimum(1.0 * offsets + 50.0 * offsets**2, 150.0 * offsets)
    assert np.all(np.linalg.norm(out - p0, axis=1) <= reach + 1e-9)
    np.testing.assert_array_equal(out[1], far[1])  # inside: unchanged


def test_a_constant_turn_is_followed_by_the_turn_candidate():
    w, speed = 0.5, 1.0  # rad/s, m/s, counter-clockwise circle of radius 2 m
    zeta = np.zeros(12)
    zeta[1] = speed  # moving along +x at the bottom of the circle centred on (0, 2)
    zeta[2] = speed * w / 9.81  # theta: x_ddot = g theta = 0
    zeta[6] = -(speed * w) / 9.81  # phi: y_ddot = -g phi = v w (towards the centre)
    zeta[2] = 0.0
    out = turn_positions(zeta, np.array([9.81, -9.81]), np.array([np.pi / w]))
    np.testing.assert_allclose(out[0], [0.0, 4.0, 0.0], atol=1e-9)  # half a turn: the top


def test_invalid_settings_are_refused_by_name():
    with pytest.raises(ConfigError, match='coverage'):
        AnticipationConfig(coverage=1.5)
    with pytest.raises(ConfigError, match='trust_ratio'):
        AnticipationConfig(trust_ratio=float('nan'))


def _solves(s, y, t, ahead, omegas):
    """Steps of two requests, the second built from the first's answer (as a prediction's)."""
    w = yield SimplexWeights(s, np.ones(s.shape[1], dtype=bool))
    separate, joint = yield HarmonicFits(t, y * (1.0 + w[0, 0]), ahead, omegas, np.array([0, 1]))
    return w, separate, joint


def test_requests_of_many_answered_together_get_the_answers_each_gets_alone():
    rng = np.random.default_rng(6)
    t = np.linspace(-6.0, 0.0, 121)
    ahead, omegas = np.linspace(0.0, 3.0, 7), 2 * np.pi / np.geomspace(1.5, 30.0, 60)
    problems = []
    for _ in range(5):
        a = rng.standard_normal((30, 4, 3))
        y = np.column_stack([np.cos(rng.uniform(0.3, 2) * t), np.sin(t), t, 0 * t + 1])
        problems.append((a @ np.swapaxes(a, 1, 2), y + 0.01 * rng.standard_normal(y.shape)))
    together = run_together([_solves(s, y, t, ahead, omegas) for s, y in problems])
    for (s, y), got in zip(problems, together):
        for a, b in zip(got, run(_solves(s, y, t, ahead, omegas))):
            np.testing.assert_array_equal(a, b)


def test_model_runs_answered_together_are_each_bitwise_the_run_alone():
    """Five models' runs over 50 steps in one stacked call: each the states of
    ``x = ad @ x + bd @ r`` stepped for that model alone, bit for bit."""
    rng = np.random.default_rng(7)
    theta, coupling = cascade_prior()
    requests = []
    for _ in range(5):
        ad, bd = discretise(theta * rng.uniform(0.8, 1.2, theta.shape), coupling, 0.1)
        requests.append(Propagation(ad, bd, rng.standard_normal(12),
                                    rng.standard_normal((50, 4))))  # fmt: skip
    together = answer(requests)
    for request, got in zip(requests, together):
        x, want = request.x0, []
        for r in request.refs:
            x = request.ad @ x + request.bd @ r
            want.append(x)
        np.testing.assert_array_equal(got, np.array(want))
        np.testing.assert_array_equal(got, answer([request])[0])


def _fit(t, y):
    yield HarmonicFits(t, y, np.linspace(0.0, 1.0, 3), np.array([1.0, 2.0]), np.array([0, 1]))
    return 'fitted'


def test_a_request_that_fails_fails_only_its_own_steps():
    t = np.linspace(-3.0, 0.0, 31)
    y = np.column_stack([np.cos(t), np.sin(t)])
    # the same kind and shape of request, but one's times do not match its samples: the batched
    # call fails, and each is answered again alone
    values = run_together([_fit(t, y), _fit(t[:-1], y), _fit(t, 2 * y)],
                          failures=(ValueError,))  # fmt: skip
    assert values[0] == values[2] == 'fitted'
    assert isinstance(values[1], ValueError)



def test_median_is_numpys_median():
    """The partition median the anticipation uses gives np.median's value bit for bit: odd and
    even lengths, ties, infinities, NaN (NaN out), and values of any magnitude."""
    rng = np.random.default_rng(7)
    cases = [np.array([2.5]), np.array([1.0, -1.0]), np.array([np.inf, 1.0, -np.inf]),
             np.array([np.inf, np.inf]), np.array([3.0, np.nan, 1.0]), np.array([1e308, 1e308])]
    for _ in range(2000):
        x = rng.standard_normal(int(rng.integers(1, 80))) * 10.0 ** float(rng.integers(-8, 8))
        cases.append(np.round(x, 1) if rng.random() < 0.3 else x)
    for x in cases:
        before = x.copy()
        got, want = median(x), float(np.median(x))
        assert got == want or (np.isnan(got) and np.isnan(want)), x
        np.testing.assert_array_equal(x, before)  # the input is left as it was
