"""The timeline of one vehicle: its validated inputs in stamp order, the grid of steps over them,
samples held aside at a jump, and the samples its odometry lost. The second stage of a vehicle's
engine (:class:`~cloe_ros.core.engine.VehicleEngine`), after the validation
(:mod:`cloe_ros.core.validation`) and before the estimator.

Grid. Time is the header stamp, never the wall clock. The steps fall on ``t_k = t_0 + k h``
(``h`` the engine's step, integer nanoseconds), where ``t_0`` is the first odometry stamp at or
after the first reference stamp (so for a regular odometry stream at the engine's rate the grid
falls on the samples). :meth:`Timeline.next_inputs` gives the inputs of the step after the last
one (the measurement interpolated linearly between the two odometry samples around it, the latest
reference at or before it) once they are complete (:mod:`cloe_ros.core.engine` says when).

Order. Each input topic must arrive in stamp order: a duplicate stamp and a stamp older than the
previous one on the same topic are rejected.

Jumps. An odometry stamp more than ``max_gap`` from the previous one, forwards or backwards, is
held aside, and so is one after a gap of more than ``HELD_INTERVALS`` typical intervals, or one out
of a quadrotor's reach of the previous sample (``JUMP_DISTANCE``): the next odometry decides. If it
continues from the held sample, the jump is genuine: the timeline ends (its owner runs the steps
the old timeline's odometry covers and stops its estimator), and a new one starts at the held
sample; a jump backwards (a restarted simulation or bag) also drops the references of the old
timeline. If the next sample continues the old timeline instead, the held one is rejected as an
outlier. A reference is held aside the same way, with the references that continue it, when it is
not after the previous one and more than ``max_gap`` before the latest input, or more than
``max_gap`` after the previous one and ahead of the odometry: they are taken when the odometry
jumps back to their timeline (or catches up with them), and rejected as ``reference stamp
outlier`` when the next reference does not continue them.

Missing samples. :class:`GapCount` counts the odometry samples that never arrived, from the gaps
between accepted stamps.

One input without the other. Odometry that no reference pairs with yet (before the estimator
starts) and references ahead of the odometry (a vehicle whose odometry stopped) are kept for
``UNPAIRED_SPAN_NS`` (or twice ``max_gap``, if longer) back from the newest of them, with the last
one before that span; older ones are dropped unused, so a vehicle that streams one input for
hours holds a bounded memory.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from cloe_ros.core.kinematics import unwrap_near_one
from cloe_ros.core.samples import NS, OdometrySample
from cloe_ros.core.validation import MAX_SPEED, Rejection, seconds

if TYPE_CHECKING:
    from cloe_ros.core.engine import EngineConfig, VehicleStats


#: A sample farther from the previous one than this plus ``MAX_SPEED`` times the time between
#: them is held aside like a jump in time: the next sample decides (a glitch, or the frame moved).
JUMP_DISTANCE = 1.0  # m
#: An odometry gap longer than this many typical intervals (and ``MIN_HELD_GAP``), but shorter
#: than ``max_gap``, is held aside too, so a single glitched stamp ahead costs one sample.
HELD_INTERVALS = 10
MIN_HELD_GAP = 50_000_000  # ns
#: A gap of more than this many typical odometry intervals (a confirmed jump ahead included)
#: counts the samples that should have come in it as missing (``VehicleStats.odom_missing``).
MISSING_INTERVALS = 1.5
#: The typical interval: the median of the short ones of this many latest gaps, once this many
#: are short; gaps waiting for it, at most.
MISSING_WINDOW, MISSING_BASIS, MAX_GAPS_WAITING = 64, 8, 100_000
#: Rejected odometry stamps kept to tell a gap's rejected samples from its missing ones.
MAX_REJECTED_STAMPS = 1024
#: With ``reference_wait`` 'due': the share of the reference stream's interval after the last
#: reference from which the next one is due, and a step waits for it (a stream's jitter may
#: bring a reference up to a tenth of an interval early).
REFERENCE_DUE = 0.9
#: References held aside at most (100 s at 100 Hz), waiting for the odometry to follow them.
MAX_HELD_REFERENCES = 10_000
#: How far back from the newest one the inputs of one stream are kept while the other stream does
#: not pair with them (module docstring, "One input without the other"): 10 s.
UNPAIRED_SPAN_NS = 10 * NS

#: Why a held input turned out to be an outlier.
NOT_CONTINUED = 'the next one did not continue it'
#: Kinds of held odometry: a jump in time, a gap of many intervals, a jump in space.
TIME_JUMP, GAP, POSITION_JUMP = 'time jump', 'gap', 'position jump'


def near(position, previous, dt_ns: int) -> bool:
    """Whether a quadrotor can be at ``position`` (x, y, z) ``dt_ns`` after ``previous``
    (x, y, z). (Scalar math: it runs for every sample.)"""
    reach = JUMP_DISTANCE + MAX_SPEED * abs(dt_ns) / NS
    dx = float(position[0]) - float(previous[0])
    dy = float(position[1]) - float(previous[1])
    dz = float(position[2]) - float(previous[2])
    return dx * dx + dy * dy + dz * dz <= reach * reach


def drop_older(queue: deque, t_ns: int) -> None:
    """Drop the inputs of ``queue`` (stamp, value), in stamp order, that precede the last one
    stamped at or before ``t_ns`` (no step at or after ``t_ns`` needs them)."""
    while len(queue) > 1 and queue[1][0] <= t_ns:
        queue.popleft()


class GapCount:
    """The odometry samples missing between accepted stamps of a regular stream: those that
    never arrived, wherever they were lost (in DDS, in a subscription's queue while the node was
    busy or stopped, or never sent); a sample that arrived in the gap and was rejected is not
    missing.

    The stream's interval is the median of its short gaps: of the latest ``MISSING_WINDOW`` gaps,
    those at most twice the shortest (jitter stays in, holes of two intervals or more stay out).
    Until ``MISSING_BASIS`` such gaps agree, the gaps wait and are counted then: a node that falls
    behind from its first message sees only holes at first. A confirmed jump ahead counts too: DDS
    does not report what a full history overwrites, so a long run lost there reads only as a jump
    of the stamps (a clock set ahead reads the same way; ``time_jumps`` counts those). A jump
    back counts nothing, nor does the gap over which nothing published the odometry
    (:meth:`unpublished`)."""

    def __init__(self) -> None:
        self._gaps: deque[int] = deque(maxlen=MISSING_WINDOW)  # the latest gaps
        self._sorted: list[int] = []  # the same, in increasing order
        self._waiting: list[tuple[int, int]] = []  # (gap, rejected in it), not counted yet
        # stamps of odometry rejected, not yet passed by the accepted stream
        self._rejected: deque[int] = deque(maxlen=MAX_REJECTED_STAMPS)
        self._unpublished = False  # the next gap is a silence

    def rejected(self, stamp_ns: int) -> None:
        """An odometry sample stamped ``stamp_ns`` arrived and was rejected."""
        self._rejected.append(stamp_ns)

    def unpublished(self) -> None:
        """Nothing publishes the odometry now: the next gap is a silence, not samples lost."""
        self._unpublished = True

    def add(self, previous_ns: int, stamp_ns: int) -> int:
        """Take the gap between two accepted stamps; returns the samples found missing (in it,
        and in the gaps that waited for the interval, once it is known)."""
        dt = stamp_ns - previous_ns
        unpublished, self._unpublished = self._unpublished, False
        inside = 0
        if self._rejected:
            inside = sum(previous_ns < s < stamp_ns for s in self._rejected)
            self._rejected = deque(
                (s for s in self._rejected if s >= stamp_ns), maxlen=MAX_REJECTED_STAMPS
            )
        if dt <= 0 or unpublished:
            return 0
        gaps, ordered = self._gaps, self._sorted
        if len(gaps) == gaps.maxlen:
            del ordered[bisect.bisect_left(ordered, gaps[0])]  # (the gap about to drop out)
        gaps.append(dt)
        bisect.insort(ordered, dt)
        short = bisect.bisect_right(ordered, 2 * ordered[0])  # ordered[:short]: the short gaps
        waiting = self._waiting
        if short < MISSING_BASIS:
            if len(waiting) < MAX_GAPS_WAITING:
                waiting.append((dt, inside))
            return 0
        regular = ordered[short // 2]
        waiting.append((dt, inside))
        missing = 0
        for gap, arrived in waiting:
            if gap > MISSING_INTERVALS * regular:
                missing += max(0, round(gap / regular) - 1 - arrived)
        waiting.clear()
        return missing


class Timeline:
    """One vehicle's validated inputs in stamp order, and the grid of its steps (module
    docstring).

    ``stats`` gets the inputs accepted, the samples missing and the jumps; ``reject(rejection)``
    is called for every input refused here (out of order, a duplicate, an outlier); ``end(kind,
    backward)`` is called when a held odometry sample is confirmed as a jump (``TIME_JUMP`` or
    ``POSITION_JUMP``), before the old timeline's odometry is dropped: the owner runs the
    steps it covers and stops its estimator; ``running()`` says whether an estimator runs (then
    odometry no reference pairs with yet is kept whatever its age: the estimator drops what it
    has stepped past)."""

    def __init__(
        self, config: EngineConfig, stats: VehicleStats, reject: Callable[[Rejection], Rejection],
        end: Callable[[str, bool], None], running: Callable[[], bool],
    ) -> None:  # fmt: skip
        self.config = config  # (its owner's: the timing tolerances may change at run time)
        self.stats = stats
        self._reject, self._end, self._running = reject, end, running
        self.child_frame = ''  # body frame of the first accepted odometry
        #: Accepted odometry, (stamp, state zeta (12,), yaw unwrapped), and references,
        #: (stamp, r (4,)), in stamp order, from the last one at or before the grid on.
        self.odom: deque[tuple[int, np.ndarray]] = deque()
        self.refs: deque[tuple[int, np.ndarray]] = deque()
        #: The last grid time stepped (None while no estimator runs).
        self.t_ns: int | None = None
        self._anchor_ns: int | None = None  # (re)start no earlier than this
        self._anchor_exact = False  # (re)start exactly at _anchor_ns (after a reset)
        self._yaw: float | None = None  # the last accepted odometry's yaw, unwrapped
        self._held_odom: tuple[OdometrySample, np.ndarray] | None = None  # a jump, until the next
        self._held_kind = ''  # why it is held: TIME_JUMP, GAP or POSITION_JUMP
        self._interval_ns: float | None = None  # typical odometry interval
        self._ref_interval_ns: float | None = None  # typical reference interval
        self._held_refs: deque[tuple[int, np.ndarray]] = deque()  # references off the timeline
        self._held_refs_backward = False  # held for being behind it (else: ahead of it)
        self.gaps = GapCount()

    # ------------------------------------------------------------------------------ inputs

    def latest_ns(self) -> int | None:
        """The latest stamp accepted on odometry or reference (None before any)."""
        stamps = [q[-1][0] for q in (self.odom, self.refs) if q]
        return max(stamps) if stamps else None

    def add_odometry(self, sample: OdometrySample, zeta: np.ndarray) -> Rejection | None:
        """Take a validated odometry sample, whose state is ``zeta`` (12,); returns the reason if
        it was rejected (as passed to ``reject``). A sample that jumps in time or in space is
        held aside (None is returned) until the next one decides."""
        stamp, gap = sample.stamp_ns, self.config.max_gap * NS
        held = self._held_odom
        if held is not None:
            held_sample, held_zeta = held
            held_ns = held_sample.stamp_ns
            dt = stamp - held_ns
            if 0 < dt <= gap and near(sample.position, held_sample.position, dt):
                # the new timeline (or the new place) goes on from the held sample: genuine
                self._held_odom = None
                if self._held_kind in (TIME_JUMP, POSITION_JUMP):
                    # the old timeline's last sample is about to be dropped: count the hole now
                    self._count_missing(self.odom[-1][0], held_ns)
                if self._held_kind == TIME_JUMP:
                    self._time_jump(held_ns, backward=held_ns < self.odom[-1][0])
                elif self._held_kind == POSITION_JUMP:
                    self.stats.position_jumps += 1
                    self._close(POSITION_JUMP, False)
                    self._anchor_ns, self._anchor_exact = held_ns, False
                self._accept(held_sample, held_zeta)
                self._accept(sample, zeta)
                return None
            if stamp == held_ns:
                return self._reject(Rejection('duplicate stamp', seconds(stamp)))
            self._held_odom = None
            self.gaps.rejected(held_ns)
            self._reject_outlier(held_ns, self._held_outlier(), NOT_CONTINUED)
        if self.odom:
            last, previous = self.odom[-1][0], self.odom[-1][1]
            dt = stamp - last
            if abs(dt) > gap:
                return self._hold(sample, zeta, TIME_JUMP)  # or a glitch: the next one tells
            if dt == 0:
                return self._reject(Rejection('duplicate stamp', seconds(stamp)))
            if dt < 0:
                return self._reject(Rejection(
                    'out-of-order stamp', f'{seconds(stamp)}, {-dt / NS:.6g} s before the '
                    'previous one'))  # fmt: skip
            if dt > self._held_gap(self._interval_ns):
                return self._hold(sample, zeta, GAP)
            if not near(sample.position, (previous[0], previous[4], previous[10]), dt):
                return self._hold(sample, zeta, POSITION_JUMP)
            self._interval_ns = dt if self._interval_ns is None else (
                self._interval_ns + 0.05 * (dt - self._interval_ns))  # fmt: skip
        self._accept(sample, zeta)
        return None

    def add_reference(self, stamp: int, r: np.ndarray) -> Rejection | None:
        """Take a validated reference ``r`` (4,) stamped ``stamp``; returns the reason if it was
        rejected (as passed to ``reject``). One that jumps in time is held aside (None is
        returned) until the odometry or the next reference decides."""
        gap = self.config.max_gap * NS
        entry = (stamp, r)
        held = self._held_refs
        if held:
            if 0 < stamp - held[-1][0] <= gap:
                held.append(entry)  # continues the held ones
                if len(held) > MAX_HELD_REFERENCES:
                    why = f'more than {MAX_HELD_REFERENCES} held, the odometry did not follow'
                    self._reject_outlier(held.popleft()[0], 'reference stamp outlier', why)
                return None
            if stamp == held[-1][0]:
                return self._reject(Rejection('reference duplicate stamp', seconds(stamp)))
            self.drop_held_references()
        last = self.refs[-1][0] if self.refs else None
        if last is not None:
            latest = self.latest_ns()
            odom = self.odom[-1][0] if self.odom else None
            hold = self._held_gap(self._ref_interval_ns)
            behind = stamp <= last and stamp < latest - gap
            ahead = stamp > last + hold and odom is not None and stamp > odom + hold
            if behind or ahead:  # another timeline's, or a glitch: hold it aside
                self._held_refs.append(entry)
                self._held_refs_backward = behind
                return None
            if stamp == last:
                return self._reject(Rejection('reference duplicate stamp', seconds(stamp)))
            if stamp < last:
                return self._reject(Rejection(
                    'reference out-of-order stamp', f'{seconds(stamp)}, '
                    f'{(last - stamp) / NS:.6g} s before the previous one'))  # fmt: skip
            dt = stamp - last
            self._ref_interval_ns = dt if self._ref_interval_ns is None else (
                self._ref_interval_ns + 0.05 * (dt - self._ref_interval_ns))  # fmt: skip
        self.refs.append(entry)
        drop_older(self.refs, stamp - self._unpaired_span_ns)
        self.stats.reference_accepted += 1
        return None

    def _count_missing(self, previous_ns: int, stamp_ns: int) -> None:
        self.stats.odom_missing += self.gaps.add(previous_ns, stamp_ns)

    def _held_gap(self, interval_ns: float | None) -> float:
        """The forward gap (ns) beyond which a sample is held aside until the next one."""
        gap = self.config.max_gap * NS
        if interval_ns is None:
            return gap
        return min(gap, max(MIN_HELD_GAP, HELD_INTERVALS * interval_ns))

    @property
    def _unpaired_span_ns(self) -> int:
        """How far back from the newest one the inputs of one stream are kept unpaired."""
        return max(UNPAIRED_SPAN_NS, 2 * round(self.config.max_gap * NS))

    def _hold(self, sample: OdometrySample, zeta: np.ndarray, kind: str) -> None:
        self._held_odom, self._held_kind = (sample, zeta), kind

    def _held_outlier(self) -> str:
        """What the odometry sample held aside is, if the next one does not continue it."""
        return 'position outlier' if self._held_kind == POSITION_JUMP else 'stamp outlier'

    def _reject_outlier(self, stamp_ns: int, reason: str, why: str) -> None:
        latest = self.latest_ns()
        where = '' if latest is None else f', {(stamp_ns - latest) / NS:+.6g} s from the timeline'
        self._reject(Rejection(reason, f'{seconds(stamp_ns)}{where}; {why}', later=True))

    def _accept(self, sample: OdometrySample, zeta: np.ndarray) -> None:
        if self._yaw is not None:
            zeta[8] = unwrap_near_one(float(zeta[8]), self._yaw)
        self._yaw = float(zeta[8])
        if not self.child_frame:
            self.child_frame = sample.child_frame_id
        if self.odom:
            self._count_missing(self.odom[-1][0], sample.stamp_ns)
        self.odom.append((sample.stamp_ns, zeta))
        if not self._running():  # (a running estimator drops the odometry it stepped past)
            drop_older(self.odom, sample.stamp_ns - self._unpaired_span_ns)
        self.stats.odom_accepted += 1
        held = self._held_refs
        if held and not self._held_refs_backward:
            if held[0][0] <= sample.stamp_ns + self._held_gap(self._ref_interval_ns):
                self._take_held_references()  # the odometry caught up with them

    def _take_held_references(self) -> None:
        self.refs.extend(self._held_refs)
        self.stats.reference_accepted += len(self._held_refs)
        self._held_refs.clear()

    def drop_held_references(self, why: str = NOT_CONTINUED) -> None:
        """Reject the references held aside (``why``: why they are outliers)."""
        for stamp, _ in self._held_refs:
            self._reject_outlier(stamp, 'reference stamp outlier', why)
        self._held_refs.clear()

    def finish(self) -> None:
        """No more input will come: the inputs still held aside (an unconfirmed jump) are
        outliers."""
        if self._held_odom is not None:
            self._reject_outlier(self._held_odom[0].stamp_ns, self._held_outlier(),
                                 'nothing followed')  # fmt: skip
            self._held_odom = None
        self.drop_held_references('nothing confirmed it')

    def clear(self) -> None:
        """Forget the inputs not yet stepped (those of another frame)."""
        self.odom.clear()
        self.refs.clear()
        self._held_odom = None
        self._held_refs.clear()
        self._anchor_ns, self._anchor_exact = None, False

    # ------------------------------------------------------------------------------ jumps

    def _close(self, kind: str, backward: bool) -> None:
        """End the timeline at a jump of ``kind``: its owner runs the steps its odometry covers
        and stops its estimator (``end``), then the odometry goes."""
        self._end(kind, backward)
        self.odom.clear()

    def _time_jump(self, new_stamp_ns: int, backward: bool) -> None:
        """End the timeline and start a new one at ``new_stamp_ns``. Backwards, the references
        held aside become the new timeline's (else those stamped after ``new_stamp_ns`` are
        dropped: they are the old timeline's)."""
        self.stats.time_jumps += 1
        self._close(TIME_JUMP, backward)
        if backward:
            if self._held_refs and self._held_refs_backward:
                self.refs.clear()
                self._take_held_references()
            else:
                while self.refs and self.refs[-1][0] > new_stamp_ns:
                    self.refs.pop()
        self._anchor_ns, self._anchor_exact = new_stamp_ns, False

    # ------------------------------------------------------------------------------ the grid

    def stop(self) -> None:
        """No estimator runs: the grid starts over where :meth:`start_time` says."""
        self.t_ns = None

    def restart_next(self) -> None:
        """The grid starts over at its next step (a reset, a divergence, a new algorithm)."""
        if self.t_ns is not None:
            self._anchor_ns = self.t_ns + self.config.step_ns
            self._anchor_exact = True
        self.t_ns = None

    def started(self, t_ns: int) -> None:
        """An estimator started at ``t_ns``: the grid's origin."""
        self.t_ns, self._anchor_exact = t_ns, False

    def start_time(self) -> int | None:
        """Where a (re)started estimator begins: after a reset, the next grid time; otherwise
        the first odometry stamp at or after both the first reference and the restart point, so
        the grid follows the odometry's own clock."""
        if self._anchor_exact:
            return self._anchor_ns
        earliest = max(self.refs[0][0], self._anchor_ns or self.refs[0][0])
        for stamp, _ in self.odom:
            if stamp >= earliest:
                return stamp
        return None

    def first_inputs(self, force_reference: bool) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The time, measurement and reference an estimator starts with, once complete; else
        None."""
        if not self.odom or not self.refs:
            return None
        t0 = self.start_time()
        if t0 is None:
            return None
        zeta = self.measurement(t0)
        if zeta is None:
            return None
        r = self.reference_at(t0, zeta[8])
        if r is None:
            return None
        if not force_reference and not self.reference_complete(t0):
            return None
        return t0, zeta, r

    def next_inputs(self, force_reference: bool) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The time, measurement and reference of the grid step after :attr:`t_ns`, once
        complete (``force_reference``: holding the last reference); else None."""
        t_next = self.t_ns + self.config.step_ns
        if not self.odom or self.odom[-1][0] < t_next:
            return None  # (the odometry does not cover it yet: the common case, checked first)
        if not force_reference and not self.reference_complete(t_next):
            return None
        zeta = self.measurement(t_next)
        if zeta is None:
            return None
        return t_next, zeta, self.reference_at(t_next, zeta[8])

    def measurement(self, t_ns: int) -> np.ndarray | None:
        """The odometry state at ``t_ns`` interpolated linearly; None if not yet covered."""
        odom = self.odom
        if not odom or odom[-1][0] < t_ns or odom[0][0] > t_ns:
            return None
        drop_older(odom, t_ns)  # (samples no longer needed)
        t0, z0 = odom[0]
        if t0 == t_ns or len(odom) == 1:
            return z0.copy()
        t1, z1 = odom[1]
        w = (t_ns - t0) / (t1 - t0)
        return z0 + w * (z1 - z0)

    def reference_at(self, t_ns: int, yaw_now: float) -> np.ndarray | None:
        """The latest reference stamped at or before ``t_ns`` (yaw taken near ``yaw_now``)."""
        refs = self.refs
        drop_older(refs, t_ns)
        if not refs or refs[0][0] > t_ns:
            return None
        r = refs[0][1].copy()
        r[2] = unwrap_near_one(float(r[2]), float(yaw_now))
        return r

    def reference_complete(self, t_ns: int) -> bool:
        """Every reference stamped up to ``t_ns`` has arrived (with ``reference_wait`` 'due':
        or the next one is not due by ``t_ns``), or the odometry is ``reference_timeout`` ahead
        of it (the last reference is then held)."""
        if self.refs and self.refs[-1][0] >= t_ns:
            return True
        interval = self._ref_interval_ns
        if (self.config.reference_wait == 'due' and interval is not None and self.refs
                and t_ns < self.refs[-1][0] + REFERENCE_DUE * interval):
            return True  # (the next reference is not due yet)
        timeout = round(self.config.reference_timeout * NS)
        return bool(self.odom) and self.odom[-1][0] >= t_ns + timeout
