"""A vehicle's ``/diagnostics`` status (``diagnostic_msgs/DiagnosticStatus``), shared by the node
and ``cloe infer``: what its engine counted (inputs received, accepted and rejected, steps, time
jumps, restarts), its identifier's status, its reference's and its predictions', and, from the
node only, what DDS says of its inputs (:class:`Link`).

The node reports every ``diagnostics_period`` of its clock (all its vehicles in one
``DiagnosticArray``); ``cloe infer`` every ``diagnostics_period`` of message time, one array per
vehicle (:class:`OfflineReports`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from cloe_ros.core.anticipation import CHANNELS
from cloe_ros.core.engine import NS, Estimate, VehicleEngine
from cloe_ros.core.identifier import ROW_NAMES, STATUS_NAMES
from cloe_ros.io.messages import OK, WARN, Status, encode_diagnostics

#: The topic of the diagnostics, global as in ROS (``/diagnostics``).
DIAGNOSTICS_TOPIC = '/diagnostics'
#: Wall-clock seconds without odometry after which a started vehicle's status turns WARN.
STALE_AFTER = 2.0


@dataclass
class Link:
    """What the node's DDS side knows of a vehicle's inputs (``cloe infer`` has none of it).

    Attributes:
        lost: Messages DDS reports lost per input topic (``message_lost``).
        missing: The input topics without a publisher for ``publisher_timeout`` and more.
        missing_words: What the message says of them (which, and for how long).
        silent_s: Wall time since the last odometry message (None before the first).
        stale_after: A started vehicle's odometry silent for longer than this, s, is a WARN.
    """

    lost: dict[str, int] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    missing_words: str = ''
    silent_s: float | None = None
    stale_after: float = STALE_AFTER


def identification_values(
    last: Estimate | None, prediction_note: str
) -> list[tuple[str, str]]:
    """The identifier's status (per row: excitation, uncertainty, status) and the prediction's,
    from the vehicle's last estimate ``last`` (none before its first)."""
    if last is None:
        return []
    out = [('prediction', prediction_note or 'none yet')]
    if last.identification is None:
        out.append(('identifier', 'gradient (paper): identifiability not measured'))
        return out
    exc, unc, status = last.identification
    for name, e, u, st in zip(ROW_NAMES, exc, unc, status):
        out.append(
            (
                f'identifier: {name}',
                f'{STATUS_NAMES[int(st)]} (excitation {e:.3f}, uncertainty '
                f'{f"{u:.1%}" if math.isfinite(u) else "not measured yet"})',
            )
        )
    return out


def vehicle_status(
    name: str, namespace: str, engine: VehicleEngine, output_ns: str, *,
    last: Estimate | None, prediction_note: str, malformed: int, last_rejected: str,
    steps_per_s: float, link: Link | None = None,
) -> Status:  # fmt: skip
    """The status of the vehicle whose engine is ``engine``, named ``name``, with hardware id
    its ``namespace``: OK while it runs with nothing to say, WARN before it starts, after
    rejected inputs (``malformed`` undecodable ones among them, ``last_rejected`` the last's
    description), a divergence, a reference it does not track, and (``link``) inputs lost in
    DDS, without publishers or silent for ``link.stale_after``. ``last`` is its last estimate,
    ``prediction_note`` what its last prediction said, ``steps_per_s`` its recent step rate."""
    s = engine.stats
    rejected = sum(s.rejected.values()) + malformed
    if not engine.started:
        level, message = WARN, 'waiting for odom and reference'
        if rejected:
            message += f'; {rejected} input(s) rejected, the last: {last_rejected}'
    elif s.diverged:
        level, message = WARN, f'running; the estimator diverged {s.diverged} time(s)'
    elif rejected:
        level = WARN
        message = f'running; {rejected} input(s) rejected, the last: {last_rejected}'
    else:
        level, message = OK, 'running'
    silent_values: list[tuple[str, str]] = []  # (what only DDS knows: the node's alone)
    dds_values: list[tuple[str, str]] = []
    if link is not None:
        silent_values = [
            ('odom_silent_s', '' if link.silent_s is None else f'{link.silent_s:.1f}')]
        dds_values = [*[(f'{k}_lost', str(n)) for k, n in link.lost.items()],
                      ('publishers_missing', ', '.join(link.missing))]  # fmt: skip
        if any(link.lost.values()):
            level = max(level, WARN)
            message += '; lost in DDS: ' + ', '.join(
                f'{n} {k}' for k, n in link.lost.items() if n)
        if link.missing:
            level = max(level, WARN)
            message += f'; {link.missing_words}'
        if engine.started and link.silent_s is not None and link.silent_s > link.stale_after:
            level = WARN
            message = f'{message}; no odometry for {link.silent_s:.1f} s'
    if engine.started and prediction_note and not prediction_note.startswith('identified'):
        message += f'; prediction {prediction_note}'
    trust = None if last is None else last.trust
    untracked = [] if trust is None else [
        (c, why) for c, ok, why in zip(CHANNELS, trust.tracked, trust.reasons) if not ok]
    if engine.started and untracked:
        level = max(level, WARN)
        message += '; reference not tracked: ' + ', '.join(c for c, _ in untracked)
    values = [
        ('algorithm', engine.config.estimator.algorithm),
        ('output_ns', output_ns),
        *identification_values(last, prediction_note),
        ('reference', 'not decided yet' if trust is None else
         'tracked' if not untracked else
         'not tracked: ' + '; '.join(f'{c} ({why})' for c, why in untracked)),
        ('untracked_steps', str(s.untracked_steps)),
        ('rate_hz', f'{engine.config.rate:g}'),
        ('prediction_phase', engine.config.prediction.phase),
        *silent_values,
        ('steps_per_s', f'{steps_per_s:.1f}'),
        ('steps', str(s.steps)),
        ('odom_received', str(s.odom_received)),
        ('odom_accepted', str(s.odom_accepted)),
        ('reference_received', str(s.reference_received)),
        ('reference_accepted', str(s.reference_accepted)),
        ('rejected', str(rejected)),
        ('malformed', str(malformed)),
        *dds_values,
        *[(f'rejected: {k}', str(n)) for k, n in sorted(s.rejected.items())],
        ('time_jumps', str(s.time_jumps)),
        ('odom_missing', str(s.odom_missing)),
        ('position_jumps', str(s.position_jumps)),
        ('frames_relearnt', str(s.frames_relearnt)),
        ('resets', str(s.resets)),
        ('diverged', str(s.diverged)),
        ('error_norm', f'{s.last_error_norm:.6g}' if math.isfinite(s.last_error_norm)
         else 'no step yet'),
        ('last_stamp', '' if s.last_stamp_ns is None else f'{s.last_stamp_ns / NS:.3f}'),
        ('predictions', str(s.predictions)),
        ('predictions_withheld', str(s.predictions_withheld)),
        ('plans_accepted', str(s.plans_accepted)),
    ]
    return Status(level, name, message, namespace, tuple(values))


class OfflineReports:
    """``/diagnostics`` of ``cloe infer``: per vehicle, its status after the batch of its steps
    in which an estimate enters a new ``period_s`` of message time, and once more after its last
    input, each a ``DiagnosticArray`` of that vehicle alone, stamped (and logged) with the
    batch's last estimate: the statuses are the node's (:func:`vehicle_status`, named ``<node>:
    <namespace>``), without what only DDS knows, with the engine's counters as they are then
    (its inputs fed so far; its steps to that estimate), and ``steps_per_s`` the steps per second
    of message time since its first estimate or its last report. Also keeps, per vehicle, the
    first input rejected for each reason (what was wrong, and the log time of its message),
    which ``cloe infer`` prints as the node logs them.

    The caller steps a vehicle when the recording's time has passed a grid step
    (:class:`~cloe_ros.core.fleet.RecordingBatches`), whose start the first input of any vehicle
    of the process sets: with ``--jobs``, or beside other vehicles, a report can count the
    inputs of a grid step more or fewer than alone."""

    def __init__(self, node: str, period_s: float, output_ns: str) -> None:
        self.node, self.output_ns = node, output_ns
        self.period_ns = max(1, round(period_s * NS))
        #: per vehicle and reason, the first description, the log time of its message (None
        #: where the rejection was decided by a later message) and how many there were
        self.first_rejected: dict[str, dict[str, tuple[str, int | None, int]]] = {}
        self._last_rejected: dict[str, str] = {}
        self._note: dict[str, str] = {}
        self._last: dict[str, Estimate] = {}
        self._slot: dict[str, int] = {}  # the period of the last report
        self._steps: dict[str, int] = {}  # estimates so far
        self._since: dict[str, tuple[int, int, float]] = {}  # stamp, steps and rate of the last

    def rejected(self, vehicle: str, text: str, log_ns: int | None = None) -> None:
        """An input of ``vehicle`` rejected (or, 'world frame learnt again', accepted in a new
        frame), as :meth:`~cloe_ros.core.validation.Rejection.describe` gives it; ``log_ns`` the
        log time of its message, if known."""
        self._last_rejected[vehicle] = text
        first = self.first_rejected.setdefault(vehicle, {})
        reason = text.split(':')[0]
        text, at, count = first.get(reason, (text, log_ns, 0))
        first[reason] = (text, at, count + 1)

    def reports(
        self, vehicle: str, namespace: str, engine: VehicleEngine, estimates: list[Estimate],
        malformed: int,
    ) -> list[tuple[str, int, bytes]]:  # fmt: skip
        """After a batch of ``estimates`` of ``vehicle`` was emitted: its report if one of
        them entered a new period, as ``[(topic, stamp, cdr)]`` (or none)."""
        if not estimates:
            return []
        if vehicle not in self._since:  # (the rate counts from the first estimate)
            self._since[vehicle] = (estimates[0].stamp_ns, 1, 0.0)
        for est in estimates:
            if est.prediction_note:
                self._note[vehicle] = est.prediction_note
        self._steps[vehicle] = self._steps.get(vehicle, 0) + len(estimates)
        last = self._last[vehicle] = estimates[-1]
        slots = {est.stamp_ns // self.period_ns for est in estimates}
        if slots == {self._slot.get(vehicle)}:
            return []
        self._slot[vehicle] = last.stamp_ns // self.period_ns
        return [self._report(vehicle, namespace, engine, last.stamp_ns, malformed)]

    def final(
        self, vehicle: str, namespace: str, engine: VehicleEngine, last_input_ns: int,
        malformed: int,
    ) -> tuple[str, int, bytes]:  # fmt: skip
        """The vehicle's last report, after its last input: at its last estimate (at its last
        input's log time ``last_input_ns`` if it gave none)."""
        last = self._last.get(vehicle)
        stamp = last_input_ns if last is None else last.stamp_ns
        return self._report(vehicle, namespace, engine, stamp, malformed)

    def _report(
        self, vehicle: str, namespace: str, engine: VehicleEngine, stamp_ns: int, malformed: int
    ) -> tuple[str, int, bytes]:
        steps = self._steps.get(vehicle, 0)
        since_ns, since_steps, rate = self._since.get(vehicle, (stamp_ns, steps, 0.0))
        if stamp_ns > since_ns:
            rate = (steps - since_steps) / ((stamp_ns - since_ns) / NS)
        self._since[vehicle] = (stamp_ns, steps, rate)
        status = vehicle_status(
            f'{self.node}: {namespace}', namespace, engine, self.output_ns,
            last=self._last.get(vehicle), prediction_note=self._note.get(vehicle, ''),
            malformed=malformed, last_rejected=self._last_rejected.get(vehicle, ''),
            steps_per_s=rate,
        )  # fmt: skip
        return DIAGNOSTICS_TOPIC, stamp_ns, encode_diagnostics(stamp_ns, [status])
