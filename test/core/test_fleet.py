"""A fleet steps the vehicles that are due together, and each gets the estimates it gets alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine, prediction_offset_ns
from cloe_ros.core.estimator import EstimatorConfig
from cloe_ros.core.evaluation import T0_NS, run_engine
from cloe_ros.core.fleet import EstimatorPool, Fleet, PooledEstimator
from cloe_ros.core.prediction import PredictionConfig
from cloe_ros.errors import ConfigError
from cloe_ros.ros.fleet import shard_of
from test.core.test_engine import in_time_order, messages, simulated_flight

IV = EngineConfig(estimator=EstimatorConfig('cloe_iv'))
SM = EngineConfig(estimator=EstimatorConfig('cloe_sm'))


@pytest.fixture(scope='module')
def flight():
    return simulated_flight()


def moved(sequence, shift_ns=0, offset=(0.0, 0.0, 0.0), start_ns=None):
    """The same flight ``offset`` m away, ``shift_ns`` later, from ``start_ns`` on."""
    out = []
    for kind, m in sequence:
        stamp = m.stamp_ns + shift_ns
        if start_ns is not None and stamp < start_ns:
            continue
        out.append((kind, replace(m, stamp_ns=stamp, position=m.position + np.array(offset))))
    return out


def swarm(flight):
    """Four vehicles: the flight; 1.37 s later and 3 m away; 0.5 s later from 4 s on with a
    jump back in time (a restarted source) halfway; and one on CLOE-SM. As (name, config,
    inputs), inputs in time order."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    t0 = seq[0][1].stamp_ns
    jump = moved(seq, 500_000_000, start_ns=t0 + 4 * NS)
    half = len(jump) // 2
    jump = jump[:half] + moved(jump[half:], -7_993_000_000, offset=(1.0, 0.0, 0.0))
    return [
        ('/a', IV, seq),
        ('/b', IV, moved(seq, 1_370_000_000, offset=(3.0, 0.0, 0.0))),
        ('/c', IV, jump),
        ('/d', SM, seq),
    ]


def merged(vehicles):
    """Every vehicle's inputs in one stream, each vehicle's in its own order (as a node receives
    them): the j-th input of every vehicle, then the (j+1)-th."""
    stream = [(j, i, name, kind, m) for i, (name, _, seq) in enumerate(vehicles)
              for j, (kind, m) in enumerate(seq)]  # fmt: skip
    stream.sort(key=lambda x: (x[0], x[1]))
    return [(name, kind, m) for _, _, name, kind, m in stream]


def feed(engine, kind, m):
    reason = (engine.add_odometry if kind == 'odom' else engine.add_reference)(m)
    assert reason is None, reason


def alone(vehicles):
    out = {}
    for name, config, seq in vehicles:
        engine = VehicleEngine(config, name=name)
        out[name] = []
        for kind, m in seq:
            feed(engine, kind, m)
            out[name] += engine.advance()
        out[name] += engine.finish()
    return out


def assert_same(got, want):
    assert [e.stamp_ns for e in got] == [e.stamp_ns for e in want]
    for name in ('zeta_hat', 'theta_hat', 'gain_l', 'error_variance'):
        np.testing.assert_allclose(np.array([getattr(e, name) for e in got]),
                                   np.array([getattr(e, name) for e in want]),
                                   rtol=1e-9, atol=1e-9, err_msg=name)  # fmt: skip
    assert [e.prediction_status for e in got] == [e.prediction_status for e in want]
    for a, b in zip(got, want):
        assert (a.prediction is None) == (b.prediction is None)
        if b.prediction is not None:
            np.testing.assert_allclose(a.prediction[1], b.prediction[1], rtol=1e-9, atol=1e-9)


def in_fleet(vehicles, monkeypatch, every: int = 1):
    """Feed the vehicles' inputs to one fleet as a node receives them (:func:`merged`), a round
    of the fleet after every ``every``-th input and one at the end, then finish each vehicle.
    Returns the fleet, the estimates per vehicle, and the pool's steps as ``(keys, fed)``:
    ``fed`` when the step ran while an input was fed, not in a round."""
    steps = []
    feeding = [False]
    step = EstimatorPool.step

    def counted(self, keys, *args):
        steps.append((keys, feeding[0]))
        return step(self, keys, *args)

    monkeypatch.setattr(EstimatorPool, 'step', counted)
    fleet = Fleet()
    for name, config, _ in vehicles:
        fleet.add(VehicleEngine(config, name=name))
    out = {name: [] for name, _, _ in vehicles}
    for k, (name, kind, m) in enumerate(merged(vehicles)):
        feeding[0] = True
        feed(fleet.engines[name], kind, m)
        feeding[0] = False
        if k % every == 0:
            for v, estimates in fleet.advance().items():
                out[v] += estimates
    for v, estimates in fleet.advance().items():
        out[v] += estimates
    for name, engine in fleet.engines.items():
        out[name] += engine.finish()
    return fleet, out, steps


def test_vehicles_stepped_together_get_the_estimates_each_gets_alone(flight, monkeypatch):
    vehicles = swarm(flight)
    # (inputs of several vehicles, and of several steps, between two rounds)
    fleet, out, steps = in_fleet(vehicles, monkeypatch, every=7)
    sizes = [len(keys) for keys, _ in steps]
    want = alone(vehicles)
    for name, _, _ in vehicles:
        assert_same(out[name], want[name])
    assert sum(e.prediction is not None for e in out['/c']) > 20  # (after the jump back too)
    assert fleet.engines['/c'].stats.resets == 0 and fleet.engines['/c'].stats.steps > 0
    # the three cloe_iv vehicles share one estimator and were stepped three at a time
    assert isinstance(fleet.engines['/a'].estimator, PooledEstimator)
    assert fleet.engines['/a'].estimator.pool is fleet.engines['/b'].estimator.pool
    assert fleet.engines['/d'].estimator.pool is not fleet.engines['/a'].estimator.pool
    assert max(sizes) == 3 and sizes.count(3) > 1000


def test_a_vehicle_that_diverges_in_a_batch_restarts_alone(flight):
    """One vehicle's statistics overflow (poisoned here): it counts a divergence and restarts;
    the others step on as if nothing happened."""
    vehicles = swarm(flight)[:2]
    fleet = Fleet()
    for name, config, _ in vehicles:
        fleet.add(VehicleEngine(config, name=name))
    out = {name: [] for name, _, _ in vehicles}
    poisoned = False
    for name, kind, m in merged(vehicles):
        feed(fleet.engines[name], kind, m)
        for v, estimates in fleet.advance().items():
            out[v] += estimates
        b = fleet.engines['/b'].estimator
        if not poisoned and b is not None and fleet.engines['/b'].stats.steps > 800:
            b.pool.est.identifier.statistics[b.pool.rows['/b']] = np.nan
            poisoned = True
    assert poisoned
    assert fleet.engines['/b'].stats.diverged == 1
    assert fleet.engines['/a'].stats.diverged == 0
    assert all(np.all(np.isfinite(e.zeta_hat)) for e in out['/b'])
    want = alone(vehicles[:1])['/a']
    assert_same(out['/a'], want[: len(out['/a'])])


def test_a_prediction_that_fails_in_a_round_fails_that_vehicles_step_alone(flight, monkeypatch):
    """A vehicle's deferred prediction raising a numerical failure (forced here, once): that
    step's estimate is not published and the vehicle restarts, as when its step fails; the other
    vehicle's predictions, run side by side with it, are those it gets alone."""
    vehicles = swarm(flight)[:2]
    fleet = Fleet()
    for name, config, _ in vehicles:
        fleet.add(VehicleEngine(config, name=name))
    b = fleet.engines['/b']
    steps = VehicleEngine.prediction_steps
    failed = []

    def failing(engine, e):
        if engine is b and not failed and engine.stats.predictions >= 10:
            failed.append(e.stamp_ns)
            yield from steps(engine, e)  # its requests are answered with the others' ...
            raise np.linalg.LinAlgError('forced')  # ... and then it fails
        return (yield from steps(engine, e))

    monkeypatch.setattr(VehicleEngine, 'prediction_steps', failing)
    out = {name: [] for name, _, _ in vehicles}
    for name, kind, m in merged(vehicles):
        feed(fleet.engines[name], kind, m)
        for v, estimates in fleet.advance().items():
            out[v] += estimates
    assert len(failed) == 1
    assert b.stats.diverged == 1 and fleet.engines['/a'].stats.diverged == 0
    assert failed[0] not in [e.stamp_ns for e in out['/b']]
    stamps = [e.stamp_ns for e in out['/b']]
    assert stamps == sorted(stamps) and len(out['/b']) > 100
    want = alone(vehicles[:1])['/a']
    assert_same(out['/a'], want[: len(out['/a'])])


def test_a_vehicle_with_other_settings_gets_a_pool_of_its_own(flight):
    """Changed gains of one vehicle move its estimator, state and all, out of the shared one."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)[:400]
    fleet = Fleet()
    for name in ('/a', '/b'):
        fleet.add(VehicleEngine(IV, name=name))
    for kind, m in seq:
        for engine in fleet.engines.values():
            feed(engine, kind, m)
        fleet.advance()
    a, b = fleet.engines['/a'], fleet.engines['/b']
    assert a.estimator.pool is b.estimator.pool
    before = b.estimator.zeta_hat[0].copy()
    b.update_estimator(replace(IV.estimator, l_max=IV.estimator.l_max / 2))
    assert a.estimator.pool is not b.estimator.pool and len(a.estimator.pool.keys) == 1
    np.testing.assert_array_equal(b.estimator.zeta_hat[0], before)
    assert b.estimator.config.l_max == IV.estimator.l_max / 2
    assert a.estimator.config.l_max == IV.estimator.l_max


def test_an_engine_alone_and_in_a_fleet_of_one_agree(flight):
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)[:1500]
    fleet = Fleet()
    engine = fleet.add(VehicleEngine(IV, name='/a'))
    got = []
    for kind, m in seq:
        feed(engine, kind, m)
        got += engine.advance()  # (a fleet's engine steps alone too)
    assert_same(got, alone([('/a', IV, seq)])['/a'][: len(got)])


def test_a_replaced_engine_leaves_its_pool_and_the_others_step_on(flight):
    """A node restarts a vehicle by adding a new engine of its name: the old engine's estimator
    leaves the pool, as its own, and the other vehicle's estimates are those it gets alone."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)[:1200]
    fleet = Fleet()
    for name in ('/a', '/b'):
        fleet.add(VehicleEngine(IV, name=name))
    out = []
    for k, (kind, m) in enumerate(seq):
        for engine in list(fleet.engines.values()):
            feed(engine, kind, m)
        if k == 600:
            old = fleet.engines['/b']
            kept = old.estimator.zeta_hat[0].copy()
            fleet.add(VehicleEngine(IV, name='/b'))
            assert old.fleet is None and not isinstance(old.estimator, PooledEstimator)
            np.testing.assert_array_equal(old.estimator.zeta_hat[0], kept)
            assert fleet.engines['/a'].estimator.pool.keys == ['/a']
        out += fleet.advance().get('/a', [])
    assert_same(out, alone([('/a', IV, seq)])['/a'][: len(out)])
    assert len(out) > 700
    b = fleet.engines['/b']
    assert b.started and b.estimator.pool is fleet.engines['/a'].estimator.pool


WAITS = replace(IV, reference_wait='stamps', reference_timeout=5.0)


def test_the_steps_left_at_a_time_jump_run_out_of_the_pool(flight, monkeypatch):
    """A hole in a vehicle's odometry that reads as a time jump (a node behind its inputs loses
    a run of them) ends its timeline: the steps its odometry covers, waiting for references,
    run then on the last reference. They run on the vehicle's estimator taken out of the pool
    (as it is about to stop), not on its row stepped alone in the pool, which copies the row out
    and back at every step; the estimates are those the vehicle gets alone."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    cut = seq[0][1].stamp_ns + 6 * NS
    # /b: no reference from 6 s on, its odometry on to 6.5 s (50 steps wait), a hole of 2 s
    holed = [(kind, m) for kind, m in seq if m.stamp_ns < cut
             or (kind == 'odom' and m.stamp_ns < cut + NS // 2) or m.stamp_ns >= cut + 5 * NS // 2]
    vehicles = [('/a', WAITS, seq), ('/b', WAITS, holed)]
    fleet, out, steps = in_fleet(vehicles, monkeypatch)
    pooled = [keys for keys, fed in steps if fed]  # the pool's steps while an input was fed
    want = alone(vehicles)
    for name, _, _ in vehicles:
        assert_same(out[name], want[name])
    b = fleet.engines['/b']
    assert b.stats.time_jumps == 1 and b.stats.resets == 0
    ended = [e for e in out['/b'] if cut <= e.stamp_ns <= cut + NS // 2]
    assert len(ended) >= 45  # (the steps that waited, run at the jump)
    assert pooled == []
    assert b.estimator.pool is fleet.engines['/a'].estimator.pool  # (back in it after the jump)


SPREAD = replace(IV, prediction=PredictionConfig(phase='spread'))


def test_spread_predictions_fall_on_each_vehicles_own_step_of_the_period(flight):
    """With prediction_phase 'spread', the vehicles of a swarm on one clock predict on different
    grid steps of each period (each on the step its namespace draws, every period), and each
    still gets, in a fleet, the estimates and predictions it gets alone."""
    odoms, refs = messages(flight)
    seq = in_time_order(odoms, refs)
    names = [f'/uav{i}' for i in range(4)]
    offsets = {n: prediction_offset_ns(SPREAD, n) for n in names}
    assert len(set(offsets.values())) > 1, offsets  # (else the flight shows nothing)
    vehicles = [(n, SPREAD, seq) for n in names]
    fleet = Fleet()
    for n in names:
        fleet.add(VehicleEngine(SPREAD, name=n))
    out = {n: [] for n in names}
    for k, (name, kind, m) in enumerate(merged(vehicles)):
        feed(fleet.engines[name], kind, m)
        if k % len(names) == len(names) - 1:
            for v, estimates in fleet.advance().items():
                out[v] += estimates
    for name, engine in fleet.engines.items():
        out[name] += fleet.advance([name]).get(name, []) + engine.finish()
    want = alone(vehicles)
    period, step = round(NS / SPREAD.prediction.rate), SPREAD.step_ns
    for n in names:
        assert_same(out[n], want[n])
        stamps = [e.stamp_ns for e in out[n] if e.prediction is not None]
        assert len(stamps) > 20
        # after the first (the first estimate's), one a period, on the first step of each
        # period shifted by the vehicle's offset
        assert set(np.diff(stamps[1:])) == {period}
        assert all((t - offsets[n]) % period < step for t in stamps[1:])


def test_prediction_offsets_spread_over_the_period_in_every_shard():
    """'aligned' shifts nothing; 'spread' draws each namespace's step of the period from a hash
    unrelated to the shards' (a CRC-32 of the same namespace): a hundred vehicles in four shards
    spread over most of the 20 steps of a period in each shard."""
    names = [f'/uav{i}' for i in range(100)]
    assert {prediction_offset_ns(IV, n) for n in names} == {0}
    step = SPREAD.step_ns
    steps = {n: prediction_offset_ns(SPREAD, n) // step for n in names}
    assert all(0 <= s < 20 and prediction_offset_ns(SPREAD, n) == s * step
               for n, s in steps.items())  # fmt: skip
    for shard in range(4):
        mine = {s for n, s in steps.items() if shard_of(n, 4) == shard}
        assert len(mine) >= 10, (shard, sorted(mine))
    assert VehicleEngine(SPREAD).namespace == '/'
    # the root and a trailing '/' as recordings and `--vehicles` may write them
    assert prediction_offset_ns(SPREAD, '') == prediction_offset_ns(SPREAD, '/')
    assert prediction_offset_ns(SPREAD, '/uav3/') == steps['/uav3'] * step
    # at a prediction rate at or above the engine's every step predicts: no shift
    every_step = replace(SPREAD, prediction=PredictionConfig(rate=200.0, phase='spread'))
    assert {prediction_offset_ns(every_step, n) for n in names} == {0}
    with pytest.raises(ConfigError, match='prediction_phase'):
        PredictionConfig(phase='staggered')
    assert VehicleEngine(SPREAD, name='/uav3')._prediction_offset_ns == steps['/uav3'] * step
    without = replace(SPREAD, prediction=PredictionConfig(horizon=0.0, phase='spread'))
    assert prediction_offset_ns(without, '/uav3') == 0


def test_run_engine_places_the_predictions_by_the_vehicles_namespace(flight):
    """run_engine (`cloe evaluate bag`) shifts the predictions by the namespace's offset, from
    its own time origin (it re-times a flight to start at T0_NS, so its instants are not those of
    `cloe infer`, aligned or spread; its scores are of the same kind)."""
    t, zeta, reference = flight
    short = slice(0, 600)  # (6 s: some thirty predictions)
    names = ('/', '/cf1', '/cf2', '/cf3')
    offsets = {n: prediction_offset_ns(SPREAD, n) for n in names}
    assert len(set(offsets.values())) > 1, offsets
    period, step = round(NS / SPREAD.prediction.rate), SPREAD.step_ns
    for n in names:
        run = run_engine(SPREAD, t[short], zeta[short], reference[short], namespace=n)
        assert run.engine.namespace == n
        stamps = [T0_NS + round(t0 * NS) for t0 in run.pred_t[1:]]  # (after the first estimate's)
        assert len(stamps) > 20
        assert all((s - offsets[n]) % period < step for s in stamps), n


def test_vehicles_that_start_together_join_their_pool_in_one_copy(flight, monkeypatch):
    """A swarm seen at once: its vehicles start on the same round and join the batched arrays
    together at the next step, one concatenation for all of them instead of one each (which
    grew as the square of their number). Until then each reads as its own estimator, the same
    values; and the estimates are those each gets alone."""
    from cloe_ros.core.cloe_iv import CloeIvEstimator

    seq = in_time_order(*messages(flight))[:300]
    vehicles = [(f'/v{k}', IV, moved(seq, offset=(2.0 * k, 0.0, 0.0))) for k in range(6)]
    joins = []
    concatenate = CloeIvEstimator.concatenate.__func__

    def counted(cls, parts):
        joins.append(len(parts))
        return concatenate(cls, parts)

    monkeypatch.setattr(CloeIvEstimator, 'concatenate', classmethod(counted))
    fleet = Fleet()
    for name, config, _ in vehicles:
        fleet.add(VehicleEngine(config, name=name))
    out = {name: [] for name, _, _ in vehicles}
    started = False
    for j in range(len(seq)):
        for name, _, inputs in vehicles:
            feed(fleet.engines[name], *inputs[j])
        for v, estimates in fleet.advance().items():
            out[v] += estimates
        if out['/v0'] and not started:  # the round they started in: none has joined yet
            started = True
            assert joins == []
            for name, _, _ in vehicles:
                est = fleet.engines[name].estimator
                np.testing.assert_array_equal(est.zeta_hat[0], out[name][-1].zeta_hat)
    assert joins == [6]  # (the first vehicle's estimator and the five others, at once)
    for name, engine in fleet.engines.items():
        out[name] += engine.finish()
    want = alone(vehicles)
    for name, _, _ in vehicles:
        assert_same(out[name], want[name])
