"""The engine's first two stages on their own: input validation (one message's values, the world
frame) and the timeline (stamp order, the grid, held samples and jumps, samples lost). The
engine's tests (test_engine, test_hostile_inputs) check them wired together."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloe_ros.core.engine import EngineConfig, VehicleStats
from cloe_ros.core.kinematics import odometry_to_state_one, yaw_quaternion
from cloe_ros.core.samples import NS, OdometrySample, PathSample, PoseSample
from cloe_ros.core.timeline import MISSING_BASIS, TIME_JUMP, GapCount, Timeline
from cloe_ros.core.validation import (
    FRAME_MOVED,
    FRAME_OTHER,
    FRAME_RELEARN,
    FRAME_RELEARNT,
    FRAME_SAME,
    MAX_TILT,
    WorldFrame,
    check_odometry,
    check_plan,
    check_reference,
)

T0 = 1_700_000_000 * NS
STEP = NS // 100  # 100 Hz


def odometry(k: int, x: float = 0.0, yaw: float = 0.3, frame: str = 'map') -> OdometrySample:
    """Odometry at ``T0 + k`` steps, at ``x`` m, hovering at 1 m with ``yaw`` rad."""
    return OdometrySample(T0 + k * STEP, frame, 'base_link', np.array([x, 0.0, 1.0]),
                          yaw_quaternion(yaw), np.array([0.1, 0.0, 0.0]), np.zeros(3))  # fmt: skip


def test_check_odometry_gives_the_state_or_why_not():
    sample = odometry(0, x=2.0)
    zeta, why = check_odometry(sample, 0.1)
    assert why is None
    expected = odometry_to_state_one(sample.position, sample.orientation, sample.linear,
                                     sample.angular)  # fmt: skip
    np.testing.assert_array_equal(zeta, expected)
    tilted = OdometrySample(T0, 'map', 'b', np.zeros(3),
                            np.array([math.sin(0.5 * (MAX_TILT + 0.1)), 0, 0,
                                      math.cos(0.5 * (MAX_TILT + 0.1))]),
                            np.zeros(3), np.zeros(3))  # fmt: skip
    zeta, why = check_odometry(tilted, 0.1)
    assert zeta is None and why.startswith('tilt beyond 80 deg') and 'roll 85.7 deg' in why.detail
    nan = OdometrySample(T0, 'map', 'b', np.zeros(3), np.array([0, 0, 0, 1.0]),
                         np.array([np.nan, 0, 0]), np.zeros(3))  # fmt: skip
    assert check_odometry(nan, 0.1)[1].describe() == 'non-finite odometry: in linear'


def test_check_reference_and_plan_give_x_y_yaw_z():
    r, why = check_reference(PoseSample(T0, 'map', np.array([1.0, 2.0, 3.0]),
                                        yaw_quaternion(0.5)), 0.1)  # fmt: skip
    assert why is None
    np.testing.assert_allclose(r, [1.0, 2.0, 0.5, 3.0], atol=1e-15)
    _, why = check_reference(PoseSample(T0, 'map', np.zeros(3), np.array([0, 0, 0, 2.0])), 0.1)
    assert why == 'invalid reference quaternion' and why.detail == 'norm 2'
    yaws = np.array([3.0, -3.0])  # across +-pi: unwrapped along the plan
    plan = PathSample(T0, 'map', np.array([T0, T0 + NS]), np.zeros((2, 3)),
                      np.array([yaw_quaternion(y) for y in yaws]))  # fmt: skip
    refs, why = check_plan(plan, 0.1)
    assert why is None and refs[1, 2] == pytest.approx(2 * math.pi - 3.0)
    backwards = PathSample(T0, 'map', np.array([T0, T0]), np.zeros((2, 3)),
                           np.array([yaw_quaternion(0.0)] * 2))  # fmt: skip
    assert check_plan(backwards, 0.1)[1] == 'plan stamps not increasing'


def test_a_world_frame_learnt_from_an_outlier_is_learnt_again():
    frame = WorldFrame()
    assert frame.check('odom') == FRAME_SAME and frame.name == 'odom'  # the first input sets it
    verdicts = [frame.check('map') for _ in range(FRAME_RELEARN)]
    assert verdicts == [FRAME_OTHER] * (FRAME_RELEARN - 1) + [FRAME_RELEARNT]
    assert (frame.name, frame.previous) == ('map', 'odom')
    frame.reopen()  # (a reset): the next input sets it, and says whether it moved
    assert frame.check('world') == FRAME_MOVED and frame.check('map') == FRAME_OTHER
    configured = WorldFrame('map')
    assert [configured.check('odom') for _ in range(2 * FRAME_RELEARN)] == [FRAME_OTHER] * 40
    configured.reopen()
    assert configured.check('odom') == FRAME_OTHER and configured.mismatch('odom') == (
        "received 'odom', expected 'map'")  # fmt: skip


class Owner:
    """What a timeline's owner does, recorded: rejections and ends of the timeline."""

    def __init__(self) -> None:
        self.rejected, self.ended, self.running = [], [], False
        self.stats = VehicleStats()
        self.timeline = Timeline(EngineConfig(max_gap=0.5), self.stats, self.reject,
                                 self.end, lambda: self.running)  # fmt: skip

    def reject(self, rejection):
        self.rejected.append(rejection)
        return rejection

    def end(self, kind: str, backward: bool) -> None:
        # the old timeline is still there when its owner runs its last steps
        self.ended.append((kind, backward, self.timeline.odom[-1][0]))

    def odometry(self, k: int, x: float = 0.0):
        sample = odometry(k, x)
        return self.timeline.add_odometry(sample, check_odometry(sample, 0.1)[0])


def test_the_grid_steps_on_interpolated_measurements_and_the_reference_of_their_time():
    owner = Owner()
    line = owner.timeline
    line.add_reference(T0, np.array([1.0, 0.0, 0.0, 1.0]))
    line.add_reference(T0 + 10 * STEP, np.array([2.0, 0.0, 0.0, 1.0]))  # all known up to it
    for k in range(0, 6, 2):  # odometry at 50 Hz, at 0, 0.02, 0.04 m
        assert owner.odometry(k, x=0.01 * k) is None
    t0, zeta, r = line.first_inputs(force_reference=False)
    assert t0 == T0 and zeta[0] == 0.0
    np.testing.assert_allclose(r, [1.0, 0.0, 0.0, 1.0], atol=1e-15)
    line.started(t0)
    t1, zeta, r = line.next_inputs(force_reference=False)  # between two odometry samples
    assert t1 == T0 + STEP and zeta[0] == pytest.approx(0.01) and r[0] == 1.0
    line.t_ns = t1
    line.t_ns = line.next_inputs(False)[0]
    line.t_ns = line.next_inputs(False)[0]
    line.t_ns = line.next_inputs(False)[0]
    assert line.t_ns == T0 + 4 * STEP and line.next_inputs(False) is None  # not covered yet
    assert owner.rejected == [] and owner.stats.odom_accepted == 3


def test_a_confirmed_time_jump_ends_the_timeline_once_and_an_unconfirmed_one_is_an_outlier():
    owner = Owner()
    for k in range(10):
        owner.odometry(k)
    assert owner.odometry(100) is None and owner.ended == []  # held aside: the next one tells
    assert owner.odometry(10) is None  # continues the old timeline: the held one was a glitch
    assert owner.rejected == ['stamp outlier'] and owner.ended == []
    assert owner.odometry(200) is None and owner.odometry(201) is None  # confirmed
    assert owner.ended == [(TIME_JUMP, False, T0 + 10 * STEP)]
    assert [s for s, _ in owner.timeline.odom] == [T0 + 200 * STEP, T0 + 201 * STEP]
    assert owner.stats.time_jumps == 1 and owner.stats.odom_accepted == 13
    assert owner.odometry(201) == 'duplicate stamp' and owner.odometry(195) == 'out-of-order stamp'


def test_the_gap_count_waits_for_the_interval_then_counts_what_never_arrived():
    gaps = GapCount()
    assert gaps.add(0, 5 * STEP) == 0  # a hole first: the interval is not known yet
    stamp = 5 * STEP
    for _ in range(MISSING_BASIS - 1):
        assert gaps.add(stamp, stamp + STEP) == 0
        stamp += STEP
    assert gaps.add(stamp, stamp + STEP) == 4  # now it is: the first hole lost four samples
    gaps.rejected(stamp + 3 * STEP)  # one arrived in the next hole, and was refused
    assert gaps.add(stamp + STEP, stamp + 5 * STEP) == 2
    gaps.unpublished()  # nothing published the odometry over the next gap: a silence
    assert gaps.add(stamp + 5 * STEP, stamp + 50 * STEP) == 0
