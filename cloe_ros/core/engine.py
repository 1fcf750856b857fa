"""The inference engine of one vehicle: validated inputs in, estimates out, in fixed steps of
message time.

One :class:`VehicleEngine` per vehicle; the ROS node and ``cloe infer`` both feed it samples in
arrival order and publish / write what it returns, so the same input messages give the same
estimates online and offline. It wires four stages, each with one job and its own module:

* validation (:mod:`cloe_ros.core.validation`): whether an input's values are usable and in the
  vehicle's world frame;
* the timeline (:mod:`cloe_ros.core.timeline`): the inputs in stamp order, the grid of steps,
  samples held aside at a jump, samples lost;
* the estimator (:mod:`cloe_ros.core.algorithms`): a row of a pool the vehicles of a
  :class:`~cloe_ros.core.fleet.Fleet` share, stepped with theirs;
* anticipation (:mod:`cloe_ros.core.anticipation`, :mod:`cloe_ros.core.prediction`): the
  anticipated paths and their radii.

Timing. The step ``t_k -> t_k+1`` of the grid (:mod:`cloe_ros.core.timeline`) runs as soon as

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

Restarts. At a jump in time or in space that the next odometry confirms (the timeline's module
docstring), the steps of the old timeline are finished and the estimator is re-initialised on the
new data (the identified model is kept); a jump backwards (a restarted simulation or bag) also
drops the plan; the references the timeline held aside for being behind it (a latched reference
of a restarted source, published before its odometry) become the new timeline's. When the world
frame learnt from the first input is learnt again (that input was an outlier), everything
accepted in the old frame is dropped and the estimator restarts without its model. A numerical
failure restarts the estimator at the next step, without its model.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from cloe_ros.core.algorithms import load_estimator, make_estimator
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
from cloe_ros.core.kinematics import unwrap_near
from cloe_ros.core.model import unstable_blocks
from cloe_ros.core.prediction import PredictionConfig, Predictor, plan_references
from cloe_ros.core.samples import MAX_STAMP_NS, NS, OdometrySample, PathSample, PoseSample
from cloe_ros.core.timeline import TIME_JUMP, Timeline
from cloe_ros.core.validation import (
    FRAME_MOVED,
    FRAME_OTHER,
    FRAME_RELEARNT,
    MAX_PLAN_POSES,
    Rejection,
    WorldFrame,
    check_odometry,
    check_plan,
    check_reference,
    long_plan,
    seconds,
)
from cloe_ros.settings import check_fields, default


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
        quaternion_tolerance: Largest accepted ``| ||q|| - 1 |``, below 1 (a zero quaternion
            has no orientation).
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
        if not (math.isfinite(tolerance) and 0.0 <= tolerance < 1.0):
            msg = f'quaternion_tolerance must be within [0, 1), got {tolerance!r}'
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
    last_stamp_ns: int | None = None
    #: The last estimate (its error's norm is worked out when asked: diagnostics ask once a
    #: report, the engine makes one a step).
    last_estimate: Estimate | None = field(default=None, repr=False)

    @property
    def last_error_norm(self) -> float:
        """``|zeta - zeta_hat|`` of the last estimate, in mixed units (nan before any)."""
        e = self.last_estimate
        return float('nan') if e is None else math.hypot(*e.error.tolist())


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
        stats: VehicleStats | None = None,
    ) -> None:
        self.name = name
        #: The vehicle's namespace as a recording shows it ('/' for the root; default: ``name``,
        #: which ``cloe infer`` takes from the bag's topics): with ``prediction_phase`` 'spread',
        #: where in each period its predictions fall.
        self.namespace = namespace if namespace is not None else (name or '/')
        # (the prediction settings are read-only in the node, and a new rate makes new engines:
        # the shift holds for the engine's life)
        self._prediction_offset_ns = prediction_offset_ns(config, self.namespace)
        # (the engine's counters and its timeline's: one object for the engine's life)
        self._stats = VehicleStats() if stats is None else stats
        self._factory = estimator_factory
        load_estimator(config.estimator.algorithm)  # (not at the first message)
        self._frame = WorldFrame(config.world_frame)
        self._timeline = Timeline(config, self._stats, self._rejected, self._end_timeline,
                                  lambda: self._est is not None)  # fmt: skip
        self._config = config
        self.fleet: Fleet | None = None  # (set by Fleet.add)
        self._est = None
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
        self._rejections: deque[Rejection] = deque(maxlen=100)  # for take_rejections
        prediction = config.prediction
        self._anticipator = Anticipator(
            config.anticipation, prediction.step, max(prediction.n_poses, 1), config.rate,
            prediction.rate, config.estimator.ground_altitude,
        ) if prediction.enabled else None  # fmt: skip
        self._t0_ns: int | None = None  # origin of the anticipator's seconds
        self._covariance = ErrorCovariance(self.step_s)  # the estimate's error statistics
        self._trust: TrustStatus | None = None

    @property
    def config(self) -> EngineConfig:
        """The engine's settings (:meth:`update_config` changes them at run time)."""
        return self._config

    @property
    def stats(self) -> VehicleStats:
        """The vehicle's counters (``stats`` of the constructor: a node that makes a new engine
        for a vehicle, at a change of algorithm or rate, goes on counting in the old one's)."""
        return self._stats

    def update_config(self, config: EngineConfig) -> None:
        """New settings at run time: the timing tolerances (``max_gap``, ``reference_timeout``,
        ``reference_wait``, ``quaternion_tolerance``) apply at once, the estimator's as
        :meth:`update_estimator` says. (A new rate, prediction or anticipation setting makes a
        new engine: those are read-only in the node, or restart it.)"""
        self._set_config(replace(config, estimator=self._config.estimator))
        self.update_estimator(config.estimator)

    def _set_config(self, config: EngineConfig) -> None:
        self._config = self._timeline.config = config

    # ----------------------------------------------------------------------------- inputs

    @property
    def world_frame(self) -> str | None:
        return self._frame.name

    @property
    def child_frame(self) -> str:
        """The body frame of the first accepted odometry ('' before it)."""
        return self._timeline.child_frame

    def _check_frame(self, frame_id: str) -> str | None:
        """What is wrong with ``frame_id`` (:class:`~cloe_ros.core.validation.WorldFrame`); None
        if the input is in the vehicle's frame. An input that sets a reopened frame anew drops
        the inputs kept; one that has the frame learnt again also restarts the estimator."""
        verdict = self._frame.check(frame_id)
        if verdict == FRAME_OTHER:
            return self._frame.mismatch(frame_id)
        if verdict == FRAME_MOVED:
            self._drop_inputs()
        elif verdict == FRAME_RELEARNT:
            self._stats.frames_relearnt += 1
            self._stop_estimator()
            self._drop_inputs()
            self._model = None
            why = f'{self._frame.previous!r} was an outlier: the inputs are in {frame_id!r}'
            self._rejections.append(Rejection('world frame learnt again', why))
        return None

    def _drop_inputs(self) -> None:
        """Forget the inputs not yet stepped (those of another frame)."""
        self._timeline.clear()
        self._plan = None

    def _rejected(self, rejection: Rejection) -> Rejection:
        """Count and keep ``rejection`` (of an input, now or later: a held one), for the logs."""
        self._stats.rejected[str(rejection)] += 1
        self._rejections.append(rejection)
        return rejection

    def _reject(self, reason: str, detail: str = '') -> Rejection:
        return self._rejected(Rejection(reason, detail))

    def take_rejections(self) -> list[Rejection]:
        """The rejections since the last call, including those decided later than their input's
        arrival (a held sample found to be an outlier), for the logs."""
        out = list(self._rejections)
        self._rejections.clear()
        return out

    def add_odometry(self, sample: OdometrySample) -> Rejection | None:
        """Accept an odometry sample; returns the reason if it was rejected. A sample that jumps
        in time or in space is held aside (None is returned) until the next one decides
        (:mod:`cloe_ros.core.timeline`)."""
        self._stats.odom_received += 1
        zeta, rejection = check_odometry(sample, self._config.quaternion_tolerance)
        if rejection is None:
            wrong = self._check_frame(sample.frame_id)
            if wrong:
                rejection = Rejection('wrong frame', wrong)
        if rejection is not None:
            self._timeline.gaps.rejected(sample.stamp_ns)
            return self._rejected(rejection)
        return self._timeline.add_odometry(sample, zeta)

    def odometry_unpublished(self) -> None:
        """Nothing publishes the vehicle's odometry now (the node sees it in the ROS graph): the
        gap before the next odometry is a silence, not samples lost."""
        if self._timeline.odom:
            self._timeline.gaps.unpublished()

    def add_reference(self, sample: PoseSample) -> Rejection | None:
        """Accept a reference sample (position and yaw); returns the reason if rejected. One that
        jumps in time is held aside (None is returned) until the odometry or the next reference
        decides (:mod:`cloe_ros.core.timeline`)."""
        self._stats.reference_received += 1
        r, rejection = check_reference(sample, self._config.quaternion_tolerance)
        if rejection is not None:
            return self._rejected(rejection)
        wrong = self._check_frame(sample.frame_id)
        if wrong:
            return self._reject('wrong reference frame', wrong)
        return self._timeline.add_reference(sample.stamp_ns, r)

    def refuse_long_plan(self, poses: int) -> Rejection | None:
        """Refuse a plan of more than ``MAX_PLAN_POSES`` poses from its pose count alone, before
        it is decoded (counted as :meth:`add_plan` counts it); None if it is not too long."""
        if poses <= MAX_PLAN_POSES:
            return None
        self._stats.plans_received += 1
        return self._rejected(long_plan(poses))

    def add_plan(self, sample: PathSample) -> Rejection | None:
        """Accept planned future references (poses stamped at future times); returns the reason
        if rejected. The latest plan is used for predictions until its last pose has passed."""
        self._stats.plans_received += 1
        refs, rejection = check_plan(sample, self._config.quaternion_tolerance)
        if rejection is not None:
            return self._rejected(rejection)
        frame = self._frame.name
        if frame is None:
            return self._reject(
                'plan before the world frame', f'plan in {sample.frame_id!r}; the first odometry '
                'or reference sets the frame')  # fmt: skip
        if sample.frame_id != frame:
            return self._reject('wrong plan frame', self._frame.mismatch(sample.frame_id))
        stamps = sample.stamps_ns
        latest = self._timeline.latest_ns()
        if latest is not None and stamps[-1] <= latest:
            return self._reject('stale plan', f'last pose at {seconds(stamps[-1])}, latest '
                                f'input at {seconds(latest)}')  # fmt: skip
        self._plan = (np.asarray(stamps, dtype=np.int64), refs)
        self._stats.plans_accepted += 1
        return None

    def _end_timeline(self, kind: str, backward: bool) -> None:
        """A jump the next odometry confirmed (:class:`~cloe_ros.core.timeline.Timeline`): run
        the steps the old timeline's odometry covers, holding the last reference (their estimates
        wait in :meth:`take_pending`), then stop the estimator; a jump back in time drops the
        plan. The estimator leaves the fleet's pool first, as its stop would have it do: those
        steps are this vehicle's alone, and a row of a pool stepped alone is copied out of the
        pool and back at every step (a node behind its inputs can have hundreds of steps waiting
        for references when a hole in its odometry reads as a time jump)."""
        self._est = self._set_estimator(None)  # (its own now, out of any pool)
        self._pending.extend(self._run(force_reference=True))
        self._stop_estimator()
        if kind == TIME_JUMP and backward:
            self._plan = None

    def _stop_estimator(self) -> None:
        self._history.clear()
        self._clear_anticipation()
        if self._est is not None:
            self._model = (self._est.theta_hat[0].copy(), self._est.gain_l[0].copy())
        self._set_estimator(None)
        self._timeline.stop()

    def reset(self) -> None:
        """Forget the identified model and re-initialise at the next step (inputs are kept). A
        world frame learnt from the inputs is open again: the estimates of the inputs kept are
        in it, and the next input sets it; one in another frame drops the inputs kept (they were
        in the old frame)."""
        self._stats.resets += 1
        self._frame.reopen()
        self._forget_model()

    def _forget_model(self) -> None:
        self._timeline.restart_next()
        self._set_estimator(None)
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
        old = self._config.estimator
        if config == old:
            return
        self._set_config(replace(self._config, estimator=config))
        if self._anticipator is not None and config.ground_altitude != old.ground_altitude:
            self._anticipator.set_ground_altitude(config.ground_altitude)
        iv = config.algorithm == 'cloe_iv'
        if config.algorithm != old.algorithm or (iv and config.identifier != old.identifier):
            load_estimator(config.algorithm)
            self._stats.resets += 1  # (a restart the user asked for; the frame is kept)
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
        """Run every step whose inputs are complete, up to the first that fails numerically (the
        estimator restarts on the next step's data, at the next call); returns their estimates in
        time order."""
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
        self._timeline.finish()
        return out

    def _start(self, force_reference: bool) -> Estimate | None:
        first = self._timeline.first_inputs(force_reference)
        if first is None:
            return None
        t0, zeta, r = first
        config = self._config.estimator
        iv = config.algorithm == 'cloe_iv'
        if iv and self._model is not None and not unstable_blocks(self._model[0]):
            # after a time jump the IV identifier starts over from its last (stable) estimate
            config = replace(config, theta_initial=tuple(self._model[0]))
        est = self._factory(config, zeta, r, self.step_s)
        if self._model is not None and not iv:
            est.theta_hat[0], est.gain_l[0] = self._model
        self._set_estimator(est)
        self._timeline.started(t0)
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
                self._diverged(self._timeline.start_time())
                return None
            if first is None:
                return None
            out.append(first)
        inputs = self._timeline.next_inputs(force_reference)
        if inputs is None:
            return None
        t_next, zeta, r = inputs
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
            self._timeline.t_ns = step.t_ns
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
        self._stats.diverged += 1
        self._timeline.t_ns = t_ns
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
        self._stats.steps += 1
        self._stats.last_stamp_ns = t_ns
        self._stats.last_estimate = e
        if self._trust is not None and not self._trust.all_tracked:
            self._stats.untracked_steps += 1
        if self._window:
            self._history.append((e.zeta_hat, used))
        if self._anticipator is not None:
            if self._t0_ns is None:
                self._t0_ns = t_ns
            self._anticipator.observe((t_ns - self._t0_ns) / NS, zeta, e.zeta_hat, used, r)
        if self._config.prediction.enabled:
            slot = (t_ns - self._prediction_offset_ns) // round(NS / self._config.prediction.rate)
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
        h = self._config.step_ns / NS
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
            self._stats.predictions_withheld += 1
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
        step_ns = round(self._config.prediction.step * NS)
        stamps = e.stamp_ns + step_ns * np.arange(1, len(states) + 1, dtype=np.int64)
        n = int(np.searchsorted(stamps, MAX_STAMP_NS, side='right'))
        if n == 0:  # the first pose is later than any stamp a message can carry
            e.prediction_status = PREDICTION_WITHHELD
            e.prediction_note = 'withheld: its stamps are beyond the largest a message carries'
            self._stats.predictions_withheld += 1
            return
        e.prediction_radius = anticipation.radius[:n]
        e.prediction_weights = anticipation.weights[:n]
        e.prediction = (stamps[:n], states[:n])
        self._stats.predictions += 1
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
            theta, coupling, states, refs, self._every / self._config.rate
        )
        config = self._config.prediction
        fade = np.exp(-config.step * np.arange(config.n_poses) / config.disturbance_time)
        return fade[:, None] * b[None, :]

    @property
    def started(self) -> bool:
        return self._est is not None

    @property
    def step_s(self) -> float:
        """The grid step, s."""
        return self._config.step_ns / NS
