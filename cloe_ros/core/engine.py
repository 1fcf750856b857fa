"""The inference engine: validated inputs in, estimates out, in fixed steps of message time.

One :class:`VehicleEngine` per vehicle; the ROS node and ``cloe infer`` both feed it samples in
arrival order and publish / write what it returns, so the same input messages give the same
estimates online and offline.

Timing. Time is the header stamp, never the wall clock. The engine steps on the grid
``t_k = t_0 + k h`` (``h = 1/rate``, integer nanoseconds), where ``t_0`` is the first odometry
stamp at or after the first reference stamp (so for a regular odometry stream at the engine's
rate the grid falls on the samples). The step ``t_k -> t_k+1`` runs as soon as

* an odometry sample stamped at or after ``t_k+1`` has arrived (the measurement at ``t_k+1`` is
  interpolated linearly between the two odometry samples around it), and
* a reference stamped at or after ``t_k+1`` has arrived (so every reference up to ``t_k+1`` is
  known; the step uses the latest one at or before ``t_k+1``, the reference of the measurement's
  time), or the odometry is ``reference_timeout`` ahead of ``t_k+1`` (a stopped or slow reference
  stream is held). With ``reference_wait`` 'due' (the default) a step also runs when no newer
  reference is due by ``t_k+1``: the next one is due ``REFERENCE_DUE`` (0.9) of the stream's
  interval after the last. So between the samples of a 10 Hz reference stream the steps follow
  the 100 Hz odometry at once, instead of waiting up to 100 ms for the next reference.

Each input topic must arrive in stamp order (DDS keeps per-publisher order; bags are read in
order). With ``reference_wait`` 'stamps' the estimates then depend on the stamps alone, not on how
the two topics interleave; with 'due' too, but for a reference that comes more than a tenth of an
interval early and after the odometry of its stamp: it applies from the next step instead.

Rejected inputs, never fed to the estimator, counted per reason: non-finite values, a quaternion
far from unit norm, values no quadrotor in a local world frame reaches (beyond ``MAX_POSITION``,
``MAX_SPEED``, ``MAX_RATE``), a roll or pitch beyond ``MAX_TILT`` (outside the near-hover model,
whose Euler rates are singular at 90 deg), a frame other than the vehicle's world frame (set by the
first odometry or reference, never by a plan), a duplicate stamp, a stamp older than the previous
one on the same topic.

Time jumps. An odometry stamp more than ``max_gap`` from the previous one, forwards or backwards,
is held aside: the next odometry decides. If it continues from the held sample (later, by at most
``max_gap``), the jump is genuine: the steps of the old timeline are finished and the estimator is
re-initialised on the new data (the identified model is kept); a jump backwards (a restarted
simulation or bag) also drops the references and plan of the old timeline. If the next sample
continues the old timeline instead, the held one is rejected as a ``stamp outlier``. So a single
glitched stamp never reaches the estimator, and published stamps only go backwards on a genuine
backward jump. A reference is held aside the same way, with the references that continue it,
when it is not after the previous one and more than ``max_gap`` before the latest input, or more
than ``max_gap`` after the previous one and ahead of the odometry: they are taken when the odometry
jumps back to their timeline (or catches up with them), and rejected as ``reference stamp
outlier`` when the next reference does not continue them. A latched reference of a restarted
source, published before its odometry, is so kept for the new timeline.

One input without the other. Odometry that no reference pairs with yet (before the estimator
starts) and references ahead of the odometry (a vehicle whose odometry stopped) are kept for
``UNPAIRED_SPAN_NS`` (or twice ``max_gap``, if longer) back from the newest of them, with the last
one before that span; older ones are dropped unused, so a vehicle that streams one input for
hours holds a bounded memory. An estimator that starts then starts on the inputs kept.
"""

from __future__ import annotations

import bisect
import functools
import hashlib
import math
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from cloe_ros.core import kernels
from cloe_ros.core.algorithms import make_estimator
from cloe_ros.core.anticipation import (
    POSITION,
    AnticipationConfig,
    Anticipator,
    TrustStatus,
    run,
)
from cloe_ros.core.covariance import ErrorCovariance
from cloe_ros.core.estimator import ConfigError, EstimatorConfig
from cloe_ros.core.fleet import Fleet, PooledEstimator, StepOutputs, row_of
from cloe_ros.core.identifier import IDENTIFIED, NOT_IDENTIFIABLE, ROW_NAMES
from cloe_ros.core.kinematics import (
    odometry_to_state_one,
    quaternion_yaw,
    quaternion_yaw_one,
    unwrap_near,
    unwrap_near_one,
)
from cloe_ros.core.model import QUADROTOR_MAX_RATE, QUADROTOR_MAX_SPEED, unstable_blocks
from cloe_ros.core.prediction import PredictionConfig, Predictor, plan_references
from cloe_ros.core.samples import MAX_STAMP_NS, OdometrySample, PathSample, PoseSample
from cloe_ros.settings import check_fields, default

NS = 1_000_000_000

#: Bounds of plausible inputs, generous for any quadrotor in a local world frame; beyond them an
#: input is rejected (such values overflow the estimator's statistics, or leave its model).
MAX_POSITION = 1e5  # m, each coordinate (odometry, reference, plan)
MAX_SPEED = QUADROTOR_MAX_SPEED  # m/s, each body velocity component
MAX_RATE = QUADROTOR_MAX_RATE  # rad/s, each body rate
#: A sample farther from the previous one than this plus ``MAX_SPEED`` times the time between
#: them is held aside like a jump in time: the next sample decides (a glitch, or the frame moved).
POSITION_JUMP = 1.0  # m
#: An odometry gap longer than this many typical intervals (and ``MIN_HELD_GAP``), but shorter
#: than ``max_gap``, is held aside too, so a single glitched stamp ahead costs one sample.
HELD_INTERVALS = 10
#: A gap of more than this many typical odometry intervals (a confirmed jump ahead included)
#: counts the samples that should have come in it as missing (``VehicleStats.odom_missing``).
MISSING_INTERVALS = 1.5
#: The typical interval: the median of the short ones of this many latest gaps, once this many
#: are short; gaps waiting for it, at most.
MISSING_WINDOW, MISSING_BASIS, MAX_GAPS_WAITING = 64, 8, 100_000
#: Rejected odometry stamps kept to tell a gap's rejected samples from its missing ones.
MAX_REJECTED_STAMPS = 1024
MIN_HELD_GAP = 50_000_000  # ns
#: Longest accepted plan, poses (a minute at 100 Hz, and more).
MAX_PLAN_POSES = 10_000
#: Inputs in one other frame, in a row, after which a frame learnt from the first input is taken
#: to have been an outlier and is learnt again.
FRAME_RELEARN = 20
MAX_TILT = math.radians(80.0)  # roll and pitch: the model linearises about hover in Euler angles
#: Reference and plan quaternions are normalised before their yaw is taken, but for those of unit
#: norm to round-off: dividing by 1 - 1e-16 would only add round-off to the yaw.
ROUNDOFF = 1e-12
#: With ``reference_wait`` 'due': the share of the reference stream's interval after the last
#: reference from which the next one is due, and a step waits for it (a stream's jitter may
#: bring a reference up to a tenth of an interval early).
REFERENCE_DUE = 0.9
#: References held aside at most (100 s at 100 Hz), waiting for the odometry to follow them.
MAX_HELD_REFERENCES = 10_000
#: How far back from the newest one the inputs of one stream are kept while the other stream does
#: not pair with them (module docstring, "One input without the other"): 10 s.
UNPAIRED_SPAN_NS = 10 * NS


@dataclass(frozen=True)
class EngineConfig:
    """Settings of one vehicle's engine.

    Attributes:
        rate: Estimator steps per second of message time, Hz.
        estimator: Algorithm and gains.
        reference_timeout: How far (s) the odometry may run ahead of a step before the last
            reference is held without waiting for a newer one.
        reference_wait: ``'due'``: a step waits for a newer reference only once one is due,
            ``REFERENCE_DUE`` of the reference stream's interval after the last one;
            ``'stamps'``: until a reference at or after the step has arrived.
        max_gap: Odometry gap (s) treated as a time jump, forwards or backwards.
        world_frame: Required ``header.frame_id``; empty: the first frame seen, then that one.
        quaternion_tolerance: Largest accepted ``| ||q|| - 1 |``.
        prediction: Horizon, pose spacing and rate of the anticipated paths.
        anticipation: Intent, reference trust, guard and radius of the predictions
            (:mod:`cloe_ros.core.anticipation`).

    """

    rate: float = default('rate')
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    reference_timeout: float = default('reference_timeout')
    reference_wait: str = default('reference_wait')
    max_gap: float = default('max_gap')
    world_frame: str = default('world_frame')
    quaternion_tolerance: float = 0.1
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    anticipation: AnticipationConfig = field(default_factory=AnticipationConfig)

    def __post_init__(self) -> None:
        check_fields(self, 'engine')  # defaults and ranges: cloe_ros.settings
        tolerance = self.quaternion_tolerance
        if not (math.isfinite(tolerance) and 0.0 <= tolerance <= 1.0):
            msg = f'quaternion_tolerance must be within [0, 1], got {tolerance!r}'
            raise ConfigError(msg)

    @functools.cached_property
    def step_ns(self) -> int:
        """The grid step, ns (asked for at every step: computed once, the config is frozen)."""
        return round(NS / self.rate)


@dataclass
class Estimate:
    """The engine's output at one step.

    Attributes:
        stamp_ns: Estimate time (a grid time), ns.
        zeta_hat: Estimated state (12,); yaw unwrapped (continuous).
        theta_hat: Identified parameters (16,).
        gain_l: Observer gains L (12,).
        measured: Measured state at ``stamp_ns`` (12,), interpolated; yaw unwrapped.
        reference: Reference at ``stamp_ns`` (4,), yaw unwrapped.
        coupling: Tilt couplings of the model (2,) (``+-g`` unless identified).
        identification: Per identified row (``ROW_NAMES``): excitation, relative uncertainty and
            status (``cloe_iv``); None for the paper's algorithms, which do not measure them.
        prediction: Anticipated path, when one is due: stamps (n,) ns and states (n, 12).
        prediction_status: ``PREDICTION_*`` code of the last prediction decision.
        prediction_note: Why, in words.
        model: The model the observer runs on and the predictions integrate, ``(theta (16,),
            coupling (2,))``: for ``cloe_iv`` the identifier's usable model (stable, from rows
            at least converging, else the prior), which differs from ``theta_hat`` while that is
            not usable; for the paper's algorithms ``theta_hat`` and ``coupling`` themselves.
        trust: Whether the vehicle tracks each reference channel (x, y, psi, z) (None before the
            first prediction decision, or without predictions).
        prediction_radius: With ``prediction``: the 95 % radius of each pose (n,), m.
        prediction_weights: With ``prediction``: the guard's weight of each candidate per pose
            (n, M), :data:`~cloe_ros.core.anticipation.CANDIDATES` order.
        error_variance: Estimated variance of ``zeta_hat - zeta`` per state (12,), in ``zeta``'s
            units (:class:`~cloe_ros.core.covariance.ErrorCovariance`; ``cloe/state``'s
            covariances are made from it).

    """

    stamp_ns: int
    zeta_hat: np.ndarray
    theta_hat: np.ndarray
    gain_l: np.ndarray
    measured: np.ndarray
    reference: np.ndarray
    coupling: np.ndarray | None = None
    identification: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    prediction: tuple[np.ndarray, np.ndarray] | None = None
    prediction_status: int = 0
    prediction_note: str = ''
    model: tuple[np.ndarray, np.ndarray] | None = None
    trust: TrustStatus | None = None
    prediction_radius: np.ndarray | None = None
    prediction_weights: np.ndarray | None = None
    error_variance: np.ndarray | None = None

    @property
    def error(self) -> np.ndarray:
        """``zeta - zeta_hat`` at ``stamp_ns``."""
        return self.measured - self.zeta_hat


#: Prediction decisions: withheld (no usable model), from a model not (yet) identified, identified.
PREDICTION_WITHHELD, PREDICTION_PROVISIONAL, PREDICTION_IDENTIFIED = 0, 1, 2


@dataclass
class VehicleStats:
    """Counters for diagnostics."""

    odom_received: int = 0
    odom_accepted: int = 0
    reference_received: int = 0
    reference_accepted: int = 0
    rejected: Counter = field(default_factory=Counter)
    steps: int = 0
    time_jumps: int = 0
    odom_missing: int = 0
    position_jumps: int = 0
    frames_relearnt: int = 0
    resets: int = 0
    diverged: int = 0
    plans_received: int = 0
    plans_accepted: int = 0
    predictions: int = 0
    predictions_withheld: int = 0
    untracked_steps: int = 0  # steps with a reference channel not tracked
    last_error_norm: float = float('nan')
    last_stamp_ns: int | None = None


#: Why a held input turned out to be an outlier.
NOT_CONTINUED = 'the next one did not continue it'


class Rejection(str):
    """Why an input was rejected: the reason (the counter's key, categorical) as the string, and
    ``detail``, the offending value, for the logs."""

    detail: str

    def __new__(cls, reason: str, detail: str = '') -> Rejection:
        obj = super().__new__(cls, reason)
        obj.detail = detail
        return obj

    def describe(self) -> str:
        """``reason: detail``."""
        return f'{self}: {self.detail}' if self.detail else str(self)


def seconds(stamp_ns: int) -> str:
    """A stamp in seconds, every nanosecond shown (``1700000001.230000000 s``)."""
    sec, nsec = divmod(int(stamp_ns), NS)
    return f'{sec}.{nsec:09d} s'


def _near(position, previous, dt_ns: int) -> bool:
    """Whether a quadrotor can be at ``position`` (x, y, z) ``dt_ns`` after ``previous``
    (x, y, z). (Scalar math: it runs for every sample.)"""
    reach = POSITION_JUMP + MAX_SPEED * abs(dt_ns) / NS
    dx = float(position[0]) - float(previous[0])
    dy = float(position[1]) - float(previous[1])
    dz = float(position[2]) - float(previous[2])
    return dx * dx + dy * dy + dz * dz <= reach * reach


def _drop_older(queue: deque, t_ns: int) -> None:
    """Drop the inputs of ``queue`` (stamp, value), in stamp order, that precede the last one
    stamped at or before ``t_ns`` (no step at or after ``t_ns`` needs them)."""
    while len(queue) > 1 and queue[1][0] <= t_ns:
        queue.popleft()


#: Numerical failures of a step (the estimator restarts, counted as ``diverged``).
NUMERICAL_FAILURES = (ArithmeticError, np.linalg.LinAlgError)

EstimatorFactory = Callable[[EstimatorConfig, np.ndarray, np.ndarray, float], object]


@dataclass(frozen=True)
class Step:
    """The inputs of one grid step: its time, the measurement interpolated there, the reference
    as received and as the estimator takes it, the channels tracked (None: all)."""

    t_ns: int
    zeta: np.ndarray
    r: np.ndarray
    used: np.ndarray
    tracked: np.ndarray | None


def prediction_offset_ns(config: EngineConfig, namespace: str) -> int:
    """How far the prediction periods of the vehicle of ``namespace`` (as a recording shows it,
    '/' for the root; '' and a trailing '/' are taken as that) are shifted, ns: 0 with
    ``prediction_phase`` 'aligned'; with 'spread', a whole number of grid steps below the period,
    drawn from the namespace by BLAKE2 (the same in every process and on every host, and
    unrelated to the shards' CRC-32 of it, so that the vehicles of one shard still spread over
    the whole period). At a prediction rate at or above the engine's, every step predicts and
    the shift is 0."""
    prediction = config.prediction
    if prediction.phase != 'spread' or not prediction.enabled:
        return 0
    steps = max(1, round(NS / prediction.rate) // config.step_ns)
    namespace = '/' + namespace.strip('/')
    digest = hashlib.blake2b(namespace.encode('utf-8'), digest_size=8).digest()
    return int.from_bytes(digest, 'little') % steps * config.step_ns


class VehicleEngine:
    """Validates one vehicle's inputs and runs its estimator in fixed steps of message time.

    Alone, it steps its own estimator (:meth:`advance`); added to a
    :class:`~cloe_ros.core.fleet.Fleet`, its estimator is a row of one shared with the other
    vehicles and :meth:`Fleet.advance <cloe_ros.core.fleet.Fleet.advance>` steps the vehicles that
    are due together, with the same estimates.
    """

    def __init__(
        self,
        config: EngineConfig,
        name: str = '',
        estimator_factory: EstimatorFactory = make_estimator,
        namespace: str | None = None,
    ) -> None:
        self.name = name
        #: The vehicle's namespace as a recording shows it ('/' for the root; default: ``name``,
        #: which ``cloe infer`` takes from the bag's topics): with ``prediction_phase`` 'spread',
        #: where in each period its predictions fall.
        self.namespace = namespace if namespace is not None else (name or '/')
        # (the prediction settings are read-only in the node, and a new rate makes new engines:
        # the shift holds for the engine's life)
        self._prediction_offset_ns = prediction_offset_ns(config, self.namespace)
        self.config = config
        self.stats = VehicleStats()
        self._factory = estimator_factory
        self._odom: deque[tuple[int, np.ndarray]] = deque()
        self._refs: deque[tuple[int, np.ndarray]] = deque()
        self._frame = config.world_frame or None
        self.child_frame = ''  # body frame of the first accepted odometry
        self._yaw: float | None = None
        self.fleet: Fleet | None = None  # (set by Fleet.add)
        self._est = None
        self._t_ns: int | None = None  # last grid time processed
        self._anchor_ns: int | None = None  # (re)start no earlier than this
        self._anchor_exact = False  # (re)start exactly at _anchor_ns (after a reset)
        self._model: tuple[np.ndarray, np.ndarray] | None = None  # theta_hat, L to restart with
        self._pending: list[Estimate] = []  # estimates produced while handling a time jump
        self._deferred: Estimate | None = None  # whose prediction the caller runs (a fleet)
        self._plan: tuple[np.ndarray, np.ndarray] | None = None  # stamps (K,), refs (K, 4)
        self._predictor = Predictor(config.prediction)
        self._prediction_slot: int | None = None
        self._last_r: np.ndarray | None = None
        # steady-state offsets per reference channel, for the predictions (_track_offsets: four
        # numbers each, kept as floats, a step's arithmetic in Python being cheaper than numpy's)
        self._offset = [0.0] * 4
        self._offset_prev_r: list[float] | None = None
        self._ref_rate = [1.0] * 4  # (m/s, rad/s: "moving" until measured still)
        self._gains = [1.0] * 4
        # recent estimates and references, every prediction step, for the recent-offset fit
        self._every = max(1, round(config.prediction.step * config.rate))
        self._window = math.ceil(config.prediction.disturbance_time * config.rate / self._every)
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(
            maxlen=self._window * self._every + 1
        )
        self._held_odom: OdometrySample | None = None  # a jump in time, until the next one
        self._held_kind = ''  # why it is held: 'time jump', 'gap' or 'position jump'
        self._checked: tuple = (None, None)  # the latest sample found usable, and its state
        self._interval_ns: float | None = None  # typical odometry interval
        # the latest odometry gaps, for the stream's interval (_count_missing)
        self._gaps: deque[int] = deque(maxlen=MISSING_WINDOW)
        self._gaps_sorted: list[int] = []  # the same, in increasing order
        self._gaps_waiting: list[tuple[int, int]] = []  # (gap, rejected in it), not counted yet
        # stamps of odometry rejected, not yet passed by the accepted stream
        self._rejected_stamps: deque[int] = deque(maxlen=MAX_REJECTED_STAMPS)
        self._ref_interval_ns: float | None = None  # typical reference interval
        self._frame_learnt = False  # the frame was learnt from an input (not configured)
        self._frame_open = False  # a learnt frame the next input may set anew (after a reset)
        self._unpublished_gap = False  # the next odometry gap is a silence (odometry_unpublished)
        self._other_frames: list[str] = []  # frames of the inputs refused in a row since
        self._held_refs: deque[tuple[int, np.ndarray]] = deque()  # references off the timeline
        self._held_refs_backward = False  # held for being behind it (else: ahead of it)
        self._rejections: deque[Rejection] = deque(maxlen=100)  # for take_rejections
        prediction = config.prediction
        self._anticipator = Anticipator(
            config.anticipation, prediction.step, max(prediction.n_poses, 1), config.rate,
            prediction.rate, config.estimator.ground_altitude,
        ) if prediction.enabled else None  # fmt: skip
        self._t0_ns: int | None = None  # origin of the anticipator's seconds
        self._covariance = ErrorCovariance(self.step_s)  # the estimate's error statistics
        self._trust: TrustStatus | None = None

    # ----------------------------------------------------------------------------- inputs

    @property
    def world_frame(self) -> str | None:
        return self._frame

    def _check_frame(self, frame_id: str) -> str | None:
        """What is wrong with ``frame_id`` (odometry and reference set the frame if unknown).

        A frame learnt from the first input (none configured) is learnt again when the next
        ``FRAME_RELEARN`` inputs all come in one other frame: the first input was the outlier.
        Everything accepted in the old frame is then dropped and the estimator restarts."""
        if self._frame is None:
            self._frame, self._frame_learnt = frame_id, True
            self._other_frames.clear()
            return None
        if self._frame_open:  # (after a reset: this input sets the frame)
            self._frame_open = False
            if frame_id != self._frame:
                self._drop_inputs()
                self._frame = frame_id
            return None
        if frame_id == self._frame:
            self._other_frames.clear()
            return None
        if self._frame_learnt:
            others = self._other_frames
            if others and others[-1] != frame_id:
                others.clear()
            others.append(frame_id)
            if len(others) >= FRAME_RELEARN:
                self._relearn_frame(frame_id)
                return None
        return f'received {frame_id!r}, expected {self._frame!r}'

    def _relearn_frame(self, frame_id: str) -> None:
        old = self._frame
        self._frame = frame_id
        self._other_frames.clear()
        self.stats.frames_relearnt += 1
        self._stop_estimator()
        self._drop_inputs()
        self._model = None
        self._rejections.append(Rejection(
            'world frame learnt again', f'{old!r} was an outlier: the inputs are in {frame_id!r}'))

    def _drop_inputs(self) -> None:
        """Forget the inputs not yet stepped (those of another frame)."""
        self._odom.clear()
        self._refs.clear()
        self._plan = None
        self._held_odom = None
        self._held_refs.clear()
        self._anchor_ns, self._anchor_exact = None, False

    def _reject(self, reason: str, detail: str = '') -> Rejection:
        rejection = Rejection(reason, detail)
        self.stats.rejected[reason] += 1
        self._rejections.append(rejection)
        return rejection

    def take_rejections(self) -> list[Rejection]:
        """The rejections since the last call, including those decided later than their input's
        arrival (a held sample found to be an outlier), for the logs."""
        out = list(self._rejections)
        self._rejections.clear()
        return out

    def _latest_ns(self) -> int | None:
        """The latest stamp accepted on odometry or reference (None before any)."""
        stamps = [q[-1][0] for q in (self._odom, self._refs) if q]
        return max(stamps) if stamps else None

    def _odometry_problem(self, sample: OdometrySample) -> tuple[str, str] | None:
        """(reason, detail) if the sample's values or frame are unusable; else None, its state
        computed (:meth:`_accept_odometry` takes it), in one compiled call
        (:func:`~cloe_ros.core.kernels.odometry_state`)."""
        fields = (sample.position, sample.orientation, sample.linear, sample.angular)
        arrays = [np.asarray(a, dtype=float) for a in fields]
        zeta, detail = np.empty(12), np.empty(2)
        verdict = kernels.odometry_state(*arrays, self.config.quaternion_tolerance, MAX_POSITION,
                                         MAX_SPEED, MAX_RATE, MAX_TILT, zeta, detail)  # fmt: skip
        if verdict == kernels.NON_FINITE:
            fields = zip(('position', 'orientation', 'linear', 'angular'), arrays)
            bad = ', '.join(n for n, a in fields if not np.isfinite(a).all())
            return 'non-finite odometry', f'in {bad}'
        if verdict == kernels.BAD_QUATERNION:
            return 'invalid quaternion', f'norm {detail[0]:.6g}'
        bounds = {kernels.BAD_POSITION: ('position', MAX_POSITION, 'm'),
                  kernels.BAD_VELOCITY: ('velocity', MAX_SPEED, 'm/s'),
                  kernels.BAD_RATE: ('angular rate', MAX_RATE, 'rad/s')}  # fmt: skip
        if verdict in bounds:
            name, bound, unit = bounds[verdict]
            return f'{name} beyond {bound:g} {unit}', f'{detail[0]:.6g} {unit}'
        if verdict == kernels.BAD_TILT:
            roll, pitch = detail.tolist()
            return (
                f'tilt beyond {math.degrees(MAX_TILT):g} deg, outside the model',
                f'roll {math.degrees(roll):.1f} deg, pitch {math.degrees(pitch):.1f} deg',
            )
        wrong = self._check_frame(sample.frame_id)
        if wrong:
            return 'wrong frame', wrong
        self._checked = (sample, zeta)
        return None

    def add_odometry(self, sample: OdometrySample) -> Rejection | None:
        """Accept an odometry sample; returns the reason if it was rejected. A sample that jumps
        in time or in space is held aside (None is returned) until the next one decides (module
        docstring)."""
        self.stats.odom_received += 1
        problem = self._odometry_problem(sample)
        if problem:
            self._rejected_stamps.append(sample.stamp_ns)
            return self._reject(*problem)
        stamp, gap = sample.stamp_ns, self.config.max_gap * NS
        held = self._held_odom
        if held is not None:
            dt = stamp - held.stamp_ns
            if 0 < dt <= gap and _near(sample.position, held.position, dt):
                # the new timeline (or the new place) goes on from the held sample: genuine
                self._held_odom = None
                if self._held_kind in ('time jump', 'position jump'):
                    # the old timeline's last sample is about to be dropped: count the hole now
                    self._count_missing(self._odom[-1][0], held.stamp_ns)
                if self._held_kind == 'time jump':
                    self._time_jump(held.stamp_ns, backward=held.stamp_ns < self._odom[-1][0])
                elif self._held_kind == 'position jump':
                    self._discontinuity(held.stamp_ns)
                self._accept_odometry(held)
                self._accept_odometry(sample)
                return None
            if stamp == held.stamp_ns:
                return self._reject('duplicate stamp', seconds(stamp))
            self._held_odom = None
            reason = 'position outlier' if self._held_kind == 'position jump' else 'stamp outlier'
            self._rejected_stamps.append(held.stamp_ns)
            self._reject_outlier(held.stamp_ns, reason, NOT_CONTINUED)
        if self._odom:
            last, previous = self._odom[-1][0], self._odom[-1][1]
            dt = stamp - last
            if abs(dt) > gap:
                return self._hold(sample, 'time jump')  # or a glitch: the next sample tells
            if dt == 0:
                return self._reject('duplicate stamp', seconds(stamp))
            if dt < 0:
                return self._reject(
                    'out-of-order stamp', f'{seconds(stamp)}, {-dt / NS:.6g} s before the '
                    'previous one')  # fmt: skip
            if dt > self._held_gap(self._interval_ns):
                return self._hold(sample, 'gap')
            if not _near(sample.position, (previous[0], previous[4], previous[10]), dt):
                return self._hold(sample, 'position jump')
            self._interval_ns = dt if self._interval_ns is None else (
                self._interval_ns + 0.05 * (dt - self._interval_ns))  # fmt: skip
        self._accept_odometry(sample)
        return None

    def odometry_unpublished(self) -> None:
        """Nothing publishes the vehicle's odometry now (the node sees it in the ROS graph): the
        gap before the next odometry is a silence, not samples lost."""
        if self._odom:
            self._unpublished_gap = True

    def _count_missing(self, previous_ns: int, stamp_ns: int) -> None:
        """Count the samples missing between two accepted stamps of a regular stream: those that
        never arrived, wherever they were lost (in DDS, in a subscription's queue while the node
        was busy or stopped, or never sent); a sample that arrived in the gap and was rejected is
        not missing.

        The stream's interval is the median of its short gaps: of the latest ``MISSING_WINDOW``
        gaps, those at most twice the shortest (jitter stays in, holes of two intervals or more
        stay out). Until ``MISSING_BASIS`` such gaps agree, the gaps wait and are counted then:
        a node that falls behind from its first message sees only holes at first. A confirmed
        jump ahead counts too: DDS does not report what a full history overwrites, so a long run
        lost there reads only as a jump of the stamps (a clock set ahead reads the same way;
        ``time_jumps`` counts those). A jump back counts nothing, nor does the gap over which
        nothing published the odometry (:meth:`odometry_unpublished`)."""
        dt = stamp_ns - previous_ns
        unpublished, self._unpublished_gap = self._unpublished_gap, False
        inside = 0
        if self._rejected_stamps:
            inside = sum(previous_ns < s < stamp_ns for s in self._rejected_stamps)
            self._rejected_stamps = deque(
                (s for s in self._rejected_stamps if s >= stamp_ns), maxlen=MAX_REJECTED_STAMPS
            )
        if dt <= 0 or unpublished:
            return
        gaps, ordered = self._gaps, self._gaps_sorted
        if len(gaps) == gaps.maxlen:
            del ordered[bisect.bisect_left(ordered, gaps[0])]  # (the gap about to drop out)
        gaps.append(dt)
        bisect.insort(ordered, dt)
        short = bisect.bisect_right(ordered, 2 * ordered[0])  # ordered[:short]: the short gaps
        waiting = self._gaps_waiting
        if short < MISSING_BASIS:
            if len(waiting) < MAX_GAPS_WAITING:
                waiting.append((dt, inside))
            return
        regular = ordered[short // 2]
        waiting.append((dt, inside))
        for gap, arrived in waiting:
            if gap > MISSING_INTERVALS * regular:
                self.stats.odom_missing += max(0, round(gap / regular) - 1 - arrived)
        waiting.clear()

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

    def _hold(self, sample: OdometrySample, kind: str) -> None:
        self._held_odom, self._held_kind = sample, kind
        return None

    def _reject_outlier(self, stamp_ns: int, reason: str, why: str) -> None:
        latest = self._latest_ns()
        where = '' if latest is None else f', {(stamp_ns - latest) / NS:+.6g} s from the timeline'
        self._reject(reason, f'{seconds(stamp_ns)}{where}; {why}')

    def _accept_odometry(self, sample: OdometrySample) -> None:
        checked, zeta = self._checked
        if checked is not sample:  # (a sample held aside, checked before the latest)
            zeta = odometry_to_state_one(
                sample.position, sample.orientation, sample.linear, sample.angular
            )
        if self._yaw is not None:
            zeta[8] = unwrap_near_one(float(zeta[8]), self._yaw)
        self._yaw = float(zeta[8])
        if not self.child_frame:
            self.child_frame = sample.child_frame_id
        if self._odom:
            self._count_missing(self._odom[-1][0], sample.stamp_ns)
        self._odom.append((sample.stamp_ns, zeta))
        if self._est is None:  # (a running estimator drops the odometry it has stepped past)
            _drop_older(self._odom, sample.stamp_ns - self._unpaired_span_ns)
        self.stats.odom_accepted += 1
        held = self._held_refs
        if held and not self._held_refs_backward:
            if held[0][0] <= sample.stamp_ns + self._held_gap(self._ref_interval_ns):
                self._take_held_references()  # the odometry caught up with them

    def _take_held_references(self) -> None:
        self._refs.extend(self._held_refs)
        self.stats.reference_accepted += len(self._held_refs)
        self._held_refs.clear()

    def add_reference(self, sample: PoseSample) -> Rejection | None:
        """Accept a reference sample (position and yaw); returns the reason if rejected. One that
        jumps in time is held aside (None is returned) until the odometry or the next reference
        decides (module docstring)."""
        self.stats.reference_received += 1
        q = sample.orientation
        p, qs = sample.position.tolist(), q.tolist()
        if not all(map(math.isfinite, (*p, *qs))):
            bad = 'position' if not all(map(math.isfinite, p)) else 'orientation'
            return self._reject('non-finite reference', f'in {bad}')
        norm = math.sqrt(float(q @ q))
        if abs(norm - 1.0) > self.config.quaternion_tolerance:
            return self._reject('invalid reference quaternion', f'norm {norm:.6g}')
        largest = max(map(abs, p))
        if largest > MAX_POSITION:
            return self._reject(
                f'reference position beyond {MAX_POSITION:g} m', f'{largest:.6g} m'
            )
        wrong = self._check_frame(sample.frame_id)
        if wrong:
            return self._reject('wrong reference frame', wrong)
        stamp, gap = sample.stamp_ns, self.config.max_gap * NS
        x, y, z, w = (c / (norm if abs(norm - 1.0) > ROUNDOFF else 1.0) for c in qs)
        yaw = quaternion_yaw_one((x, y, z, w))
        entry = (stamp, np.array([p[0], p[1], yaw, p[2]]))
        held = self._held_refs
        if held:
            if 0 < stamp - held[-1][0] <= gap:
                held.append(entry)  # continues the held ones
                if len(held) > MAX_HELD_REFERENCES:
                    why = f'more than {MAX_HELD_REFERENCES} held, the odometry did not follow'
                    self._reject_outlier(held.popleft()[0], 'reference stamp outlier', why)
                return None
            if stamp == held[-1][0]:
                return self._reject('reference duplicate stamp', seconds(stamp))
            self._drop_held_references()
        last = self._refs[-1][0] if self._refs else None
        if last is not None:
            latest = self._latest_ns()
            odom = self._odom[-1][0] if self._odom else None
            hold = self._held_gap(self._ref_interval_ns)
            behind = stamp <= last and stamp < latest - gap
            ahead = stamp > last + hold and odom is not None and stamp > odom + hold
            if behind or ahead:  # another timeline's, or a glitch: hold it aside
                self._held_refs.append(entry)
                self._held_refs_backward = behind
                return None
            if stamp == last:
                return self._reject('reference duplicate stamp', seconds(stamp))
            if stamp < last:
                return self._reject(
                    'reference out-of-order stamp', f'{seconds(stamp)}, '
                    f'{(last - stamp) / NS:.6g} s before the previous one')  # fmt: skip
        if last is not None:
            dt = stamp - last
            self._ref_interval_ns = dt if self._ref_interval_ns is None else (
                self._ref_interval_ns + 0.05 * (dt - self._ref_interval_ns))  # fmt: skip
        self._refs.append(entry)
        _drop_older(self._refs, stamp - self._unpaired_span_ns)
        self.stats.reference_accepted += 1
        return None

    def _drop_held_references(self, why: str = NOT_CONTINUED) -> None:
        for stamp, _ in self._held_refs:
            self._reject_outlier(stamp, 'reference stamp outlier', why)
        self._held_refs.clear()

    def refuse_long_plan(self, poses: int) -> Rejection | None:
        """Refuse a plan of more than ``MAX_PLAN_POSES`` poses from its pose count alone, before
        it is decoded (counted as :meth:`add_plan` counts it); None if it is not too long."""
        if poses <= MAX_PLAN_POSES:
            return None
        self.stats.plans_received += 1
        return self._reject_long_plan(poses)

    def _reject_long_plan(self, poses: int) -> Rejection:
        return self._reject(f'plan longer than {MAX_PLAN_POSES} poses', f'{poses} poses')

    def add_plan(self, sample: PathSample) -> Rejection | None:
        """Accept planned future references (poses stamped at future times); returns the reason
        if rejected. The latest plan is used for predictions until its last pose has passed."""
        self.stats.plans_received += 1
        stamps, p, q = sample.stamps_ns, sample.positions, sample.orientations
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            return self._reject('non-finite plan')
        if len(stamps) == 0:
            return self._reject('empty plan')
        if len(stamps) > MAX_PLAN_POSES:
            return self._reject_long_plan(len(stamps))
        largest = float(np.max(np.abs(p)))
        if largest > MAX_POSITION:
            return self._reject(f'plan position beyond {MAX_POSITION:g} m', f'{largest:.6g} m')
        norms = np.sqrt(np.sum(q * q, axis=1))
        worst = int(np.argmax(np.abs(norms - 1.0)))
        if abs(norms[worst] - 1.0) > self.config.quaternion_tolerance:
            return self._reject(
                'invalid plan quaternion', f'pose {worst}: norm {norms[worst]:.6g}'
            )
        steps = np.diff(stamps)
        if np.any(steps <= 0):
            k = int(np.argmax(steps <= 0)) + 1
            return self._reject(
                'plan stamps not increasing',
                f'pose {k} at {seconds(stamps[k])} after {seconds(stamps[k - 1])}',
            )
        if self._frame is None:
            return self._reject(
                'plan before the world frame', f'plan in {sample.frame_id!r}; the first odometry '
                'or reference sets the frame')  # fmt: skip
        if sample.frame_id != self._frame:
            return self._reject(
                'wrong plan frame', f'received {sample.frame_id!r}, expected {self._frame!r}'
            )
        latest = self._latest_ns()
        if latest is not None and stamps[-1] <= latest:
            return self._reject('stale plan', f'last pose at {seconds(stamps[-1])}, latest '
                                f'input at {seconds(latest)}')  # fmt: skip
        yaw = quaternion_yaw(q / np.where(np.abs(norms - 1.0) > ROUNDOFF, norms, 1.0)[:, None])
        refs = np.column_stack([p[:, 0], p[:, 1], np.unwrap(yaw), p[:, 2]])
        self._plan = (np.asarray(stamps, dtype=np.int64), refs)
        self.stats.plans_accepted += 1
        return None

    def _discontinuity(self, new_stamp_ns: int) -> None:
        """The vehicle's position jumped and the next sample confirmed it (a motion-capture frame
        reset, a vehicle carried to another place): finish what can be finished and restart the
        estimator at ``new_stamp_ns`` on the same timeline (the identified model is kept)."""
        self.stats.position_jumps += 1
        self._end_timeline()
        self._anchor_ns, self._anchor_exact = new_stamp_ns, False

    def _end_timeline(self) -> None:
        """Before a restart: run the steps the odometry covers, holding the last reference
        (their estimates wait in :meth:`take_pending`), then stop the estimator and drop the
        odometry. The estimator leaves the fleet's pool first, as its stop would have it do:
        those steps are this vehicle's alone, and a row of a pool stepped alone is copied out
        of the pool and back at every step (a node behind its inputs can have hundreds of steps
        waiting for references when a hole in its odometry reads as a time jump)."""
        self._est = self._set_estimator(None)  # (its own now, out of any pool)
        self._pending.extend(self._run(force_reference=True))
        self._stop_estimator()
        self._odom.clear()

    def _time_jump(self, new_stamp_ns: int, backward: bool) -> None:
        """Finish what can be finished, then restart the estimator at ``new_stamp_ns``. Backwards,
        the references held aside become the new timeline's (else those stamped after
        ``new_stamp_ns`` are dropped: they are the old timeline's), and the plan is dropped."""
        self.stats.time_jumps += 1
        self._end_timeline()
        if backward:
            if self._held_refs and self._held_refs_backward:
                self._refs.clear()
                self._take_held_references()
            else:
                while self._refs and self._refs[-1][0] > new_stamp_ns:
                    self._refs.pop()
            self._plan = None
        self._anchor_ns, self._anchor_exact = new_stamp_ns, False

    def _stop_estimator(self) -> None:
        self._history.clear()
        self._clear_anticipation()
        if self._est is not None:
            self._model = (self._est.theta_hat[0].copy(), self._est.gain_l[0].copy())
        self._set_estimator(None)
        self._t_ns = None

    def reset(self) -> None:
        """Forget the identified model and re-initialise at the next step (inputs are kept). A
        world frame learnt from the inputs is open again: the estimates of the inputs kept are
        in it, and the next input sets it; one in another frame drops the inputs kept (they were
        in the old frame)."""
        self.stats.resets += 1
        if self._frame_learnt:
            self._frame_open = True
            self._other_frames.clear()
        self._forget_model()

    def _forget_model(self) -> None:
        if self._t_ns is not None:
            self._anchor_ns = self._t_ns + self.config.step_ns
            self._anchor_exact = True
        self._set_estimator(None)
        self._t_ns = None
        self._model = None
        self._prediction_slot = None
        self._covariance.reset()
        self._history.clear()
        self._clear_anticipation()

    def _clear_anticipation(self) -> None:
        if self._anticipator is not None:
            self._anticipator.clear()
        self._t0_ns = None
        self._trust = None

    def update_estimator(self, config: EstimatorConfig) -> None:
        """Use new gains from the next step on, keeping the state and the identified model.

        A change of algorithm, or of the ``cloe_iv`` identifier's settings (its filters and
        statistics are built for them), restarts the estimator and forgets the model. ``l_initial``
        applies from the next (re)start."""
        old = self.config.estimator
        if config == old:
            return
        self.config = replace(self.config, estimator=config)
        if self._anticipator is not None and config.ground_altitude != old.ground_altitude:
            self._anticipator.set_ground_altitude(config.ground_altitude)
        iv = config.algorithm == 'cloe_iv'
        if config.algorithm != old.algorithm or (iv and config.identifier != old.identifier):
            self.stats.resets += 1  # (a restart the user asked for; the frame is kept)
            self._forget_model()
            return
        est = self._est
        if est is None:
            return  # (the next start uses the new config)
        if iv:
            # the observer reads its gains from the config at every step, but for the
            # sliding-mode terms, which it holds per vehicle; the identifier is left as it is
            est = self._set_estimator(None)
            est.config = config
            est.lambda_[:] = config.sm_gains
            est.exponents[:] = config.sm_exponents
            self._set_estimator(est)
        else:
            new = self._factory(config, est.zeta_hat[0], self._last_r, self.step_s)
            new.theta_hat[:] = est.theta_hat
            new.gain_l[:] = est.gain_l
            self._set_estimator(new)

    def _set_estimator(self, est):
        """Make ``est`` (of one vehicle; None: none) this vehicle's estimator, a row of the fleet's
        when in one; returns the previous one as an estimator of its own."""
        old = self._est
        if isinstance(old, PooledEstimator):
            old = old.detach()
        self._est = est if est is None or self.fleet is None else self.fleet.adopt(self, est)
        return old

    @property
    def estimator(self):
        """The running estimator (None before the start): of one vehicle, or a row of the
        fleet's."""
        return self._est

    # ------------------------------------------------------------------------------ steps

    def advance(self) -> list[Estimate]:
        """Run every step whose inputs are complete; returns their estimates in time order."""
        out = self.take_pending()
        out.extend(self._run(force_reference=False))
        return out

    def take_pending(self) -> list[Estimate]:
        """The estimates of steps already run (while handling a time jump), not yet returned."""
        out, self._pending = self._pending, []
        return out

    def finish(self) -> list[Estimate]:
        """No more input will come: run the remaining steps the odometry covers, holding the last
        reference. Inputs still held aside (an unconfirmed jump) are outliers."""
        out = self.advance()
        out.extend(self._run(force_reference=True))
        if self._held_odom is not None:
            reason = 'position outlier' if self._held_kind == 'position jump' else 'stamp outlier'
            self._reject_outlier(self._held_odom.stamp_ns, reason, 'nothing followed')
            self._held_odom = None
        self._drop_held_references('nothing confirmed it')
        return out

    def _measurement(self, t_ns: int) -> np.ndarray | None:
        """The odometry state at ``t_ns`` interpolated linearly; None if not yet covered."""
        odom = self._odom
        if not odom or odom[-1][0] < t_ns or odom[0][0] > t_ns:
            return None
        _drop_older(odom, t_ns)  # (samples no longer needed)
        t0, z0 = odom[0]
        if t0 == t_ns or len(odom) == 1:
            return z0.copy()
        t1, z1 = odom[1]
        w = (t_ns - t0) / (t1 - t0)
        return z0 + w * (z1 - z0)

    def _reference_at(self, t_ns: int, yaw_now: float) -> np.ndarray | None:
        """The latest reference stamped at or before ``t_ns`` (yaw taken near ``yaw_now``)."""
        refs = self._refs
        _drop_older(refs, t_ns)
        if not refs or refs[0][0] > t_ns:
            return None
        r = refs[0][1].copy()
        r[2] = unwrap_near_one(float(r[2]), float(yaw_now))
        return r

    def _reference_complete(self, t_ns: int) -> bool:
        """Every reference stamped up to ``t_ns`` has arrived (with ``reference_wait`` 'due':
        or the next one is not due by ``t_ns``), or the odometry is ``reference_timeout`` ahead
        of it (the last reference is then held)."""
        if self._refs and self._refs[-1][0] >= t_ns:
            return True
        interval = self._ref_interval_ns
        if (self.config.reference_wait == 'due' and interval is not None and self._refs
                and t_ns < self._refs[-1][0] + REFERENCE_DUE * interval):
            return True  # (the next reference is not due yet)
        timeout = round(self.config.reference_timeout * NS)
        return bool(self._odom) and self._odom[-1][0] >= t_ns + timeout

    def _start_time(self) -> int | None:
        """Where the (re)started estimator begins: after a reset, the next grid time; otherwise
        the first odometry stamp at or after both the first reference and the restart point, so
        the grid follows the odometry's own clock."""
        if self._anchor_exact:
            return self._anchor_ns
        earliest = max(self._refs[0][0], self._anchor_ns or self._refs[0][0])
        for stamp, _ in self._odom:
            if stamp >= earliest:
                return stamp
        return None

    def _start(self, force_reference: bool) -> Estimate | None:
        if not self._odom or not self._refs:
            return None
        t0 = self._start_time()
        if t0 is None:
            return None
        zeta = self._measurement(t0)
        if zeta is None:
            return None
        r = self._reference_at(t0, zeta[8])
        if r is None:
            return None
        if not force_reference and not self._reference_complete(t0):
            return None
        config = self.config.estimator
        iv = config.algorithm == 'cloe_iv'
        if iv and self._model is not None and not unstable_blocks(self._model[0]):
            # after a time jump the IV identifier starts over from its last (stable) estimate
            config = replace(config, theta_initial=tuple(self._model[0]))
        est = self._factory(config, zeta, r, self.step_s)
        if self._model is not None and not iv:
            est.theta_hat[0], est.gain_l[0] = self._model
        self._set_estimator(est)
        self._t_ns, self._anchor_exact = t0, False
        self._last_r = r
        self._covariance.restart()
        return self._estimate(t0, zeta, r)

    def _run(self, force_reference: bool) -> list[Estimate]:
        out: list[Estimate] = []
        while (step := self.next_step(force_reference, out)) is not None:
            if not self.complete_step(step, self.step_alone(step), out):
                break
        return out

    def next_step(self, force_reference: bool, out: list[Estimate]) -> Step | None:
        """The inputs of the next grid step if they are complete, else None. Starts the
        estimator first if it can (its first estimate goes to ``out``)."""
        if self._est is None:
            try:
                first = self._start(force_reference)
            except NUMERICAL_FAILURES:
                self._diverged(self._start_time())
                return None
            if first is None:
                return None
            out.append(first)
        t_next = self._t_ns + self.config.step_ns
        if not self._odom or self._odom[-1][0] < t_next:
            return None  # (the odometry does not cover it yet: the common case, checked first)
        if not force_reference and not self._reference_complete(t_next):
            return None
        zeta = self._measurement(t_next)
        if zeta is None:
            return None
        r = self._reference_at(t_next, zeta[8])
        used, tracked = self._reference_for_step(zeta, r)
        return Step(t_next, zeta, r, used, tracked)

    def step_alone(self, step: Step) -> bool:
        """Step this vehicle's estimator alone; False if it failed numerically."""
        tracked = None if step.tracked is None else step.tracked[None]
        try:
            self._est.step(step.zeta[None], step.used[None], self.step_s, tracked)
        except NUMERICAL_FAILURES:
            return False
        return True

    def complete_step(
        self, step: Step, ok: bool, out: list[Estimate], variance: np.ndarray | None = None,
        defer: bool = False, outputs: tuple[StepOutputs, int] | None = None,
    ) -> bool:  # fmt: skip
        """After the estimator stepped (``ok``: without failing), the estimate of ``step`` into
        ``out``; False if the estimator diverged (it restarts on the next step's data).
        ``variance``: the error statistics' update for this step if already made (a fleet
        updates those of a batch at once, :meth:`ErrorCovariance.update_many`). ``defer``: a
        prediction due is left to the caller (:meth:`take_deferred`), to run before this
        vehicle's next step. ``outputs``: the estimator's outputs of the batch this step was in
        and this vehicle's index in it, when gathered already (:class:`StepOutputs`)."""
        try:
            if not ok:
                raise FloatingPointError('the step failed')
            self._t_ns = step.t_ns
            self._last_r = step.used
            self._track_offsets(step.zeta, step.used)
            batch, k = self._own_outputs() if outputs is None else outputs
            if not batch.finite[k]:
                raise FloatingPointError('non-finite estimate')
            out.append(self._estimate(step.t_ns, step.zeta, step.r, step.used, variance, defer,
                                      batch.row(k)))  # fmt: skip
        except NUMERICAL_FAILURES:
            # a diverged estimator never publishes: start over on the next step's data
            self._diverged(step.t_ns)
            return False
        return True

    def _reference_for_step(
        self, zeta: np.ndarray, r: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The reference the estimator steps with and which channels are tracked (None: all):
        a channel whose reference the vehicle does not track takes the virtual reference of its
        motion, and is not identified (:class:`~cloe_ros.core.anticipation.Anticipator`)."""
        if self._anticipator is None or self._trust is None:
            return r, None
        used, tracked = self._anticipator.reference_for_estimator(zeta, r)
        return used, None if self._anticipator.trust.all_followed else tracked

    def _diverged(self, t_ns: int | None) -> None:
        """The estimator failed numerically at ``t_ns``: count it, restart at the next step."""
        self.stats.diverged += 1
        self._t_ns = t_ns
        self._forget_model()

    def _estimate(
        self, t_ns: int, zeta: np.ndarray, r: np.ndarray, used: np.ndarray | None = None,
        variance: np.ndarray | None = None, defer: bool = False, row: tuple | None = None,
    ) -> Estimate:  # fmt: skip
        """The estimate at ``t_ns``: ``r`` is the reference as received, ``used`` the one the
        estimator stepped with (the same unless a channel is not tracked); ``variance`` the
        error statistics' update if made already (see :meth:`complete_step`); ``row`` the
        estimator's outputs for this vehicle if gathered already (:meth:`StepOutputs.row`),
        else they are taken from the estimator."""
        used = r if used is None else used
        if row is None:
            batch, k = self._own_outputs()
            row = batch.row(k)
        zeta_hat, theta_hat, gain_l, coupling, identification, model = row
        e = Estimate(t_ns, zeta_hat, theta_hat, gain_l, zeta, r, coupling=coupling,
                     identification=identification, model=model, trust=self._trust)
        if variance is None:
            variance = self._covariance.update(zeta, e.zeta_hat, e.gain_l)
        e.error_variance = variance.copy()
        self.stats.steps += 1
        self.stats.last_stamp_ns = t_ns
        self.stats.last_error_norm = math.hypot(*e.error.tolist())
        if self._trust is not None and not self._trust.all_tracked:
            self.stats.untracked_steps += 1
        if self._window:
            self._history.append((e.zeta_hat, used))
        if self._anticipator is not None:
            if self._t0_ns is None:
                self._t0_ns = t_ns
            self._anticipator.observe((t_ns - self._t0_ns) / NS, zeta, e.zeta_hat, used, r)
        if self.config.prediction.enabled:
            slot = (t_ns - self._prediction_offset_ns) // round(NS / self.config.prediction.rate)
            # a new period: a later one, or any other after a jump back in time
            if slot != self._prediction_slot:
                self._prediction_slot = slot
                if defer:
                    self._deferred = e
                else:
                    self._predict(e)
        return e

    def _own_outputs(self) -> tuple[StepOutputs, int]:
        """This vehicle's estimator outputs, gathered alone (:class:`StepOutputs`), and its
        index among them."""
        est, i = row_of(self._est)
        return StepOutputs(est, np.array([i])), 0

    def take_deferred(self) -> Estimate | None:
        """The estimate whose prediction :meth:`complete_step` left to the caller (None if
        none): the caller runs :meth:`prediction_steps` of it, or calls
        :meth:`prediction_failed` if that raised a numerical failure."""
        e, self._deferred = self._deferred, None
        return e

    def prediction_failed(self, e: Estimate) -> None:
        """The deferred prediction of ``e`` failed numerically: as a failure of its step (the
        estimate is not published; the estimator restarts on the next step's data)."""
        self._diverged(e.stamp_ns)

    def _track_offsets(self, zeta: np.ndarray, r: np.ndarray) -> None:
        """Steady-state offsets between where the vehicle settles and where the model says it
        settles for the same reference (per reference channel), for the predictions.

        A real vehicle may hold its altitude a few centimetres off the setpoint; the identifier's
        band-pass filters cannot see constants. The offset ``pos - g r`` (``g`` the model's static
        gain) is low-passed (2 s) while that channel's reference is still (below 5 cm/s or
        0.05 rad/s), and held while it moves, when ``pos - g r`` is tracking lag, not offset.
        """
        h = self.config.step_ns / NS
        r = r.tolist()
        previous, self._offset_prev_r = self._offset_prev_r, r
        if previous is None:
            return
        a_rate, a_offset = min(1.0, h / 0.5), min(1.0, h / 2.0)
        rates, offset, gains = self._ref_rate, self._offset, self._gains
        z = zeta.tolist()
        for c, pos in enumerate((z[0], z[4], z[8], z[10])):
            rates[c] += a_rate * (abs(r[c] - previous[c]) / h - rates[c])
            if rates[c] < 0.05:
                offset[c] += a_offset * (pos - gains[c] * r[c] - offset[c])

    def _predict(self, e: Estimate) -> None:
        """Attach the anticipated path to ``e`` (or say why there is none)."""
        run(self.prediction_steps(e))

    def prediction_steps(self, e: Estimate):
        """:meth:`_predict` as steps: a generator of the requests of its costliest solves
        (:func:`~cloe_ros.core.anticipation.run_together` batches those of many vehicles)."""
        theta, coupling = e.model
        unstable = self._predictor.unstable_blocks(theta, coupling)
        if unstable:
            e.prediction_status = PREDICTION_WITHHELD
            e.prediction_note = (
                f'withheld: the identified model is unstable ({", ".join(unstable)})'
            )
            self.stats.predictions_withheld += 1
            return
        ant = self._anticipator
        t = (e.stamp_ns - self._t0_ns) / NS
        yield from ant.update_steps(t, theta, coupling)
        self._trust = e.trust = ant.trust.status()
        tracked = ant.trust.followed
        # the reference, shifted by the steady-state offsets (see _track_offsets) where tracked
        gains = self._predictor.static_gains(theta, coupling)
        self._gains = gains.tolist()
        shift = np.divide(np.array(self._offset), gains, out=np.zeros(4),
                          where=np.abs(gains) > 0.1)  # fmt: skip
        shift[~tracked] = 0.0
        offsets = yield from self._recent_offsets_steps(theta, coupling, shift)
        plan = None
        if self._plan is not None and self._plan[0][-1] > e.stamp_ns:
            stamps, refs = self._plan
            refs = refs.copy()
            refs[:, 2] = refs[:, 2] + (unwrap_near(refs[0, 2], e.zeta_hat[8]) - refs[0, 2])
            plan = plan_references(e.reference, ((stamps - e.stamp_ns) / NS, refs),
                                   ant.starts)  # fmt: skip
        # the future reference: the plan, else the intent; untracked channels: the virtual one
        path, _ = yield from ant.reference_path_steps(t, e.measured, plan)
        path += shift
        states = yield from self._predictor.predict_steps(
            e.zeta_hat, theta, coupling, path[0], (ant.starts, path), offsets
        )
        center = e.zeta_hat[[0, 4, 10]], e.zeta_hat[[1, 5, 11]]
        anticipation = yield from ant.combine_steps(t, states[:, POSITION], e.measured, coupling,
                                                    center)  # fmt: skip
        states[:, POSITION] = anticipation.positions
        step_ns = round(self.config.prediction.step * NS)
        stamps = e.stamp_ns + step_ns * np.arange(1, len(states) + 1, dtype=np.int64)
        n = int(np.searchsorted(stamps, MAX_STAMP_NS, side='right'))
        if n == 0:  # the first pose is later than any stamp a message can carry
            e.prediction_status = PREDICTION_WITHHELD
            e.prediction_note = 'withheld: its stamps are beyond the largest a message carries'
            self.stats.predictions_withheld += 1
            return
        e.prediction_radius = anticipation.radius[:n]
        e.prediction_weights = anticipation.weights[:n]
        e.prediction = (stamps[:n], states[:n])
        self.stats.predictions += 1
        if e.identification is None:
            e.prediction_status = PREDICTION_PROVISIONAL
            e.prediction_note = 'provisional: this algorithm does not check identifiability'
            return
        status = e.identification[2]
        pending = [name for name, s in zip(ROW_NAMES, status) if s != IDENTIFIED]
        if pending:
            weak = [n for n, s in zip(ROW_NAMES, status) if s == NOT_IDENTIFIABLE]
            e.prediction_status = PREDICTION_PROVISIONAL
            e.prediction_note = 'provisional: ' + (
                f'not identifiable: {", ".join(weak)}' if weak
                else f'converging: {", ".join(pending)}')  # fmt: skip
        else:
            e.prediction_status = PREDICTION_IDENTIFIED
            e.prediction_note = 'identified model'

    def _recent_offsets_steps(self, theta: np.ndarray, coupling: np.ndarray, shift: np.ndarray):
        """Model error over the last ``disturbance_time``, as reference offsets over the horizon
        (n, 4) on top of the steady-state ``shift``; None until the window is full. As steps
        (the fit is a request, see :meth:`prediction_steps`).

        The offset ``b`` with which the model best reproduces the recent estimates
        (:func:`~cloe_ros.core.prediction.fit_reference_offset`) replaces the steady-state shift
        at the start of the horizon and fades back to it with time constant
        ``disturbance_time``: a model error seen over the last half second says much about the
        next half second and little about the next five. (On the recorded flights the vehicle
        leaves its altitude ahead of the logged landing setpoint, and holds its altitude some
        centimetres off the setpoint after take-off; see docs/identifier.md.)
        """
        if len(self._history) < (self._history.maxlen or 0) or not self._window:
            return None
        pick = list(self._history)[:: self._every]
        states = np.array([p[0] for p in pick])
        refs = np.array([p[1] for p in pick]) + shift
        b = yield from self._predictor.recent_offset_steps(
            theta, coupling, states, refs, self._every / self.config.rate
        )
        config = self.config.prediction
        fade = np.exp(-config.step * np.arange(config.n_poses) / config.disturbance_time)
        return fade[:, None] * b[None, :]

    @property
    def started(self) -> bool:
        return self._est is not None

    @property
    def step_s(self) -> float:
        """The grid step, s."""
        return self.config.step_ns / NS
