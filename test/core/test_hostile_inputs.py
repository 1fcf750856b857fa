"""Hostile inputs to the engine (issue: nothing lost unseen, nothing non-physical out): stamps at
the end of their range, a stray first frame, small glitches in time and in space, huge plans,
and predictions that must stay finite and within a quadrotor's reach of the estimate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine
from cloe_ros.core.estimator import EstimatorConfig
from cloe_ros.core.model import QUADROTOR_MAX_ACCELERATION, QUADROTOR_MAX_SPEED
from cloe_ros.core.samples import MAX_STAMP_NS, PathSample
from cloe_ros.core.timeline import MISSING_WINDOW
from cloe_ros.core.validation import MAX_PLAN_POSES
from cloe_ros.io.outputs import OutputConfig, OutputEncoder, parameter_vector
from test.core.test_engine import (
    _run_with_a_glitch,
    _stamped,
    in_time_order,
    messages,
    run,
    simulated_flight,
)

IV = EngineConfig(estimator=EstimatorConfig(algorithm='cloe_iv'))


@pytest.fixture(scope='module')
def flight():
    return simulated_flight()


def _restamped(odoms, refs, t0_ns):
    """The same messages with their first stamp moved to ``t0_ns``."""
    shift = t0_ns - odoms[0][0]
    return ([(s + shift, _stamped(m, s + shift)) for s, m in odoms],
            [(s + shift, _stamped(m, s + shift)) for s, m in refs])  # fmt: skip


def test_predictions_near_the_end_of_the_stamp_range_are_cut_and_encode(flight):
    """A flight whose last odometry is 2 s before the largest stamp a message carries
    (2038-01-19): predictions (10 s horizon) keep only the poses up to that stamp, and every
    estimate encodes; it used to end in ``struct.error`` in encode_prediction."""
    odoms, refs = messages(flight)
    odoms, refs = _restamped(odoms[:1000], refs[:500], MAX_STAMP_NS - 12 * NS)
    engine = VehicleEngine(IV)
    out = run(engine, in_time_order(odoms, refs)) + engine.finish()
    encoder = OutputEncoder(OutputConfig())
    cut = 0
    for e in out:
        for _, stamp, data in encoder.encode(e, 'world', 'base_link'):
            assert stamp <= MAX_STAMP_NS and data
        if e.prediction is not None:
            stamps, states = e.prediction
            assert stamps[-1] <= MAX_STAMP_NS
            assert len(states) == len(stamps) == len(e.prediction_radius)
            cut += len(stamps) < engine.config.prediction.n_poses
    assert cut > 0  # the last predictions were cut, not all dropped
    assert engine.stats.predictions > 0


def test_nothing_published_is_non_finite(flight):
    """cloe_iv's first parameters used to carry ``inf`` in ``uncertainty.*`` (and the paper's
    algorithms NaN in excitation and uncertainty): every published value is finite, -1 where
    nothing is measured yet."""
    odoms, refs = messages(flight)
    for algorithm in ('cloe_iv', 'cloe_sm'):
        config = EngineConfig(estimator=EstimatorConfig(algorithm=algorithm))
        engine = VehicleEngine(config)
        out = run(engine, in_time_order(odoms[:600], refs[:300])) + engine.finish()
        vectors = np.array([parameter_vector(e) for e in out])
        assert np.isfinite(vectors).all(), algorithm
        for e in out:
            assert np.isfinite(e.zeta_hat).all()
            if e.prediction is not None:
                assert np.isfinite(e.prediction[1]).all()
                assert np.isfinite(e.prediction_radius).all()


def test_a_glitched_stamp_below_max_gap_costs_one_sample(flight):
    """An odometry stamp 0.9 s ahead (below ``max_gap``) was accepted, and the next 89 real
    messages were rejected as out of order; it is held aside like a time jump and, since the next
    message does not continue from it, rejected alone. The estimates equal the clean run's."""
    engine, out, expected = _run_with_a_glitch(flight, 'odom', 500, 0.9)
    assert dict(engine.stats.rejected) == {'stamp outlier': 1}
    assert engine.stats.time_jumps == 0
    np.testing.assert_array_equal(
        np.array([e.zeta_hat for e in out]), np.array([e.zeta_hat for e in expected])
    )


def test_a_real_pause_below_max_gap_goes_on(flight):
    """A 0.5 s pause in the odometry (a stalled link) is held for one sample, which confirms it:
    nothing is rejected and every sample is used."""
    odoms, refs = messages(flight)
    odoms = odoms[:400] + odoms[450:800]
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(odoms, refs[:400]))
    engine.finish()
    assert not engine.stats.rejected
    assert engine.stats.odom_accepted == len(odoms)


def test_a_position_99_km_away_is_a_position_outlier(flight):
    """A position 99 km away (inside the 100 km plausibility bound) yielded predictions 737 km
    from the estimate; no quadrotor gets there in 10 ms, so it is held aside, and rejected when
    the next sample continues from the old position. The estimates equal the clean run's."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:800], refs[:400]
    seq = in_time_order(odoms, refs)
    clean = VehicleEngine(IV)
    expected = run(clean, seq) + clean.finish()
    _, sample = odoms[500]
    at = seq.index(('odom', sample))
    jumped = replace(sample, position=sample.position + np.array([99e3, 0.0, 0.0]))
    engine = VehicleEngine(IV)
    out = run(engine, [*seq[:at], ('odom', jumped), *seq[at + 1:]]) + engine.finish()
    assert dict(engine.stats.rejected) == {'position outlier': 1}
    assert engine.stats.position_jumps == 0
    assert len(out) == len(expected) and out[-1].stamp_ns == expected[-1].stamp_ns


def test_a_confirmed_position_jump_restarts_on_the_same_timeline(flight):
    """From sample 500 on, every position is 5 m off (a motion-capture frame moved): the second
    shifted sample confirms the first, the estimator restarts there and follows the new place."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:1000], refs[:500]
    shift = np.array([5.0, 0.0, 0.0])
    moved = [(s, m if i < 500 else replace(m, position=m.position + shift))
             for i, (s, m) in enumerate(odoms)]  # fmt: skip
    engine = VehicleEngine(IV)
    out = run(engine, in_time_order(moved, refs)) + engine.finish()
    assert engine.stats.position_jumps == 1
    assert not engine.stats.rejected
    last = out[-1]
    np.testing.assert_allclose(last.zeta_hat[[0, 4, 10]], moved[-1][1].position, atol=0.05)


def test_a_stray_first_frame_is_learnt_again_and_reset_forgets_the_frame(flight):
    """A first odometry message in 'map', then good ones in 'world', gave 0 states (all 'wrong
    frame'): after 20 in a row in 'world', 'map' is taken for the outlier. ``reset`` forgets a
    learnt frame: inputs in another frame are then accepted at once."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:600], refs[:300]
    stray = replace(odoms[0][1], frame_id='map', stamp_ns=odoms[0][0] - NS // 100)
    engine = VehicleEngine(EngineConfig())
    assert engine.add_odometry(stray) is None
    out = []
    for kind, sample in in_time_order(odoms, refs):
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(sample)
        out.extend(engine.advance())
    out.extend(engine.finish())
    assert engine.world_frame == 'world'
    assert engine.stats.frames_relearnt == 1
    assert engine.stats.rejected['wrong frame'] + engine.stats.rejected.get(
        'wrong reference frame', 0) < 25
    assert len(out) > 500
    # a frame set by the inputs is forgotten by reset
    engine.reset()
    later = odoms[-1][0] + NS // 100
    assert engine.add_odometry(replace(odoms[-1][1], frame_id='odom', stamp_ns=later)) is None
    assert engine.world_frame == 'odom'


def test_a_configured_frame_is_never_learnt_again(flight):
    """With ``world_frame`` configured, inputs in another frame stay rejected however many."""
    odoms, _ = messages(flight)
    engine = VehicleEngine(EngineConfig(world_frame='world'))
    for _, m in odoms[:50]:
        assert engine.add_odometry(replace(m, frame_id='map')) == 'wrong frame'
    engine.reset()
    assert engine.world_frame == 'world' and engine.stats.frames_relearnt == 0


def test_a_plan_longer_than_the_bound_is_rejected(flight):
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(odoms[:10], refs[:5]))
    n = MAX_PLAN_POSES + 1
    stamps = odoms[10][0] + NS // 100 * np.arange(n, dtype=np.int64)
    plan = PathSample(odoms[10][0], 'world', stamps, np.zeros((n, 3)),
                      np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))  # fmt: skip
    assert engine.add_plan(plan) == f'plan longer than {MAX_PLAN_POSES} poses'


@pytest.mark.parametrize('algorithm', ['cloe_iv'])
def test_predictions_stay_within_reach_of_the_estimate(flight, algorithm):
    """Every predicted pose is within ``|v0| h + a h^2 / 2`` and ``v_max h`` of the estimated
    position (v0 the estimated velocity), whatever the candidates say."""
    odoms, refs = messages(flight)
    engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig(algorithm=algorithm)))
    out = run(engine, in_time_order(odoms, refs)) + engine.finish()
    checked = 0
    for e in out:
        if e.prediction is None:
            continue
        stamps, states = e.prediction
        h = (stamps - e.stamp_ns) / NS
        p0, v0 = e.zeta_hat[[0, 4, 10]], e.zeta_hat[[1, 5, 11]]
        speed = min(float(np.linalg.norm(v0)), QUADROTOR_MAX_SPEED)
        reach = np.minimum(speed * h + 0.5 * QUADROTOR_MAX_ACCELERATION * h**2,
                           QUADROTOR_MAX_SPEED * h)  # fmt: skip
        d = np.linalg.norm(states[:, [0, 4, 10]] - p0, axis=1)
        assert np.all(d <= reach + 1e-9)
        checked += 1
    assert checked > 10


def test_samples_missing_from_a_regular_stream_are_counted(flight):
    """Odometry lost on its way (in DDS, or in a queue the node did not empty in time) leaves
    gaps in the stamps: 19 of 600 samples dropped in 8 runs of 1, 2 and 5 are counted as
    missing, and nothing is rejected."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:600], refs[:300]
    dropped = set()
    for start, run_length in [(100 + 50 * k, (1, 2, 5)[k % 3]) for k in range(8)]:
        dropped.update(range(start, start + run_length))
    kept = [m for i, m in enumerate(odoms) if i not in dropped]
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(kept, refs))
    engine.finish()
    assert engine.stats.odom_missing == len(dropped) == 19
    assert not engine.stats.rejected


@pytest.mark.parametrize('silence', [0.5, 3.0])  # s: a gap, and a time jump
def test_a_silence_the_graph_showed_is_not_missing_samples(flight, silence):
    """A gap over which nothing published the odometry (the node saw it in the ROS graph and
    said so, odometry_unpublished) counts no missing sample; the same gap unannounced does."""
    odoms, refs = messages(flight)
    cut = round(100 * silence)
    counted = {}
    for announced in (False, True):
        engine = VehicleEngine(EngineConfig())
        run(engine, in_time_order(odoms[:300], refs[:150]))
        if announced:
            engine.odometry_unpublished()
        run(engine, in_time_order(odoms[300 + cut:700], refs[150 + cut // 2:350]))
        engine.finish()
        counted[announced] = engine.stats.odom_missing
    assert counted == {False: cut, True: 0}


def test_a_sample_that_arrived_and_was_rejected_is_not_missing(flight):
    """Received and missing add up to what was sent: a sample rejected (NaN) between two
    accepted ones, or held aside alone between two long holes and rejected as a stamp outlier
    for want of a sample continuing it, arrived; its slot is not counted missing."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:900], refs[:450]
    lost = set(range(300, 450)) | set(range(451, 600))  # 450 alone between two 1.5 s holes
    stamp, sample = odoms[200]
    odoms[200] = (stamp, replace(sample, position=np.array([np.nan, 0.0, 1.0])))
    kept = [m for i, m in enumerate(odoms) if i not in lost]
    engine = VehicleEngine(EngineConfig())
    for kind, m in in_time_order(kept, refs):
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(m)
        engine.advance()
    engine.finish()
    assert dict(engine.stats.rejected) == {'non-finite odometry': 1, 'stamp outlier': 1}
    assert engine.stats.odom_received == 900 - len(lost)
    assert engine.stats.odom_missing == len(lost) == 299


def test_a_long_run_lost_is_counted_across_the_time_jump_it_makes(flight):
    """A run longer than ``max_gap`` lost from a regular stream (a full subscription history
    overwrites it, and DDS reports nothing) reads as a jump ahead: once the next sample confirms
    it, its samples are counted as missing, and the jump as a time jump. A jump back (a restarted
    source) counts nothing."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:900], refs[:450]
    assert len(odoms) == 900
    lost = range(300, 550)  # 2.5 s at 100 Hz, beyond max_gap (1 s)
    kept = [m for i, m in enumerate(odoms) if i not in lost]
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(kept, refs))
    assert engine.stats.time_jumps == 1
    assert engine.stats.odom_missing == len(lost) == 250
    run(engine, in_time_order(odoms[:200], refs[:100]))  # the source restarts: a jump back
    engine.finish()
    assert engine.stats.time_jumps == 2
    assert engine.stats.odom_missing == 250
    assert not engine.stats.rejected


def test_missing_samples_are_counted_when_the_first_gap_was_a_hole(flight):
    """The stream's interval comes from its recent gaps, not from the first one: a node that
    took its first sample and then fell behind at once (its first gap is a hole of 49 samples)
    still counts every hole, that one included."""
    odoms, refs = messages(flight)
    odoms, refs = odoms[:900], refs[:450]
    lost = set(range(1, 50)) | set(range(400, 700))
    kept = [m for i, m in enumerate(odoms) if i not in lost]
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(kept, refs))
    engine.finish()
    assert engine.stats.odom_missing == len(lost) == 349


def test_the_interval_follows_a_stream_whose_rate_changes(flight):
    """The interval is the median of the latest ``MISSING_WINDOW`` gaps: odometry at 100 Hz,
    then at 50 Hz (the same samples stamped 20 ms apart), then 6 samples dropped alone, each
    leaving a gap of two 50 Hz intervals. Until the 20 ms gaps are the window's median, each
    reads as one 100 Hz sample missing (31 of them); after, each drop is one sample missing (not
    three, as at 100 Hz), and the 100 Hz gaps that left the window count no more."""
    odoms, refs = messages(flight)
    t0 = odoms[0][0]
    stamps = [t0 + 10_000_000 * i for i in range(300)]
    stamps += [stamps[-1] + 20_000_000 * (i + 1) for i in range(400)]
    dropped = {400 + 40 * k for k in range(6)}  # (the first 100 gaps after the change: kept)
    kept = [(s, replace(m, stamp_ns=s)) for i, (s, (_, m)) in enumerate(zip(stamps, odoms))
            if i not in dropped]  # fmt: skip
    refs = [(s, replace(m, stamp_ns=s)) for s, (_, m) in zip(stamps[::2], refs)]
    engine = VehicleEngine(EngineConfig())
    run(engine, in_time_order(kept, refs))
    engine.finish()
    assert engine.stats.odom_missing == MISSING_WINDOW // 2 - 1 + len(dropped) == 31 + 6
    assert not engine.stats.rejected


def test_a_plan_is_refused_by_its_pose_count_alone(flight):
    engine = VehicleEngine(EngineConfig())
    assert engine.refuse_long_plan(MAX_PLAN_POSES) is None
    reason = f'plan longer than {MAX_PLAN_POSES} poses'
    assert engine.refuse_long_plan(MAX_PLAN_POSES + 1) == reason
    assert engine.stats.rejected[reason] == 1
    assert engine.stats.plans_received == 1
