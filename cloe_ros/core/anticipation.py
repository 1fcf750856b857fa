"""Anticipation that holds on real flights: intent, reference trust, a guard, a 95 % radius.

(docs/anticipation.md has the math and the measurements.)

The identified closed loop (:mod:`cloe_ros.core.prediction`) says how a vehicle responds to its
reference. Three things decide whether its prediction can be trusted on a flight it has never
seen, and this module does them, per vehicle, causally, in message time:

* **Intent** (:class:`Intent`). With no plan, where the reference itself goes is predicted from
  its own recent past by several models (held, constant velocity, a single-frequency harmonic
  per axis, and one shared by x and y, which fits circles and ellipses), combined per horizon
  by how well each predicted the reference that followed.
* **Reference trust** (:class:`ReferenceTrust`). Per reference channel (x, y, yaw, z): does the
  vehicle track the reference it is given? The identified model is run over the last second
  from the estimate of a second ago with the references that came since, and compared with where
  the vehicle went; a reference the model-driven replay misses by far more than constant
  velocity does, and by more than a floor, is *not tracked* (a reference that runs away, freezes
  while the vehicle moves, jumps or is offset without the vehicle following, or carries
  velocities). A reference commanding the vehicle to the ground is not tracked either: a landed
  vehicle follows no closed loop. While a channel is not tracked nothing published relies on
  it: the engine drives the observer, the identifier (paused for that channel's rows) and the
  closed-loop prediction with a *virtual reference* inferred from the vehicle's own motion
  (:meth:`VirtualReference.of`).
* **A guard** (:class:`Ensemble`). The closed-loop prediction is one candidate beside predictors
  that need no model and no reference (constant turn rate and velocity from the measured state,
  constant velocity, hold, the centroid of the recent path). Every candidate's past
  predictions are scored once their poses' times have passed, and the published path is, per
  horizon, the convex combination of candidates with the least recent squared error (minimum
  variance on the simplex). A candidate that has recently done worse than the baselines at a
  horizon so loses its weight there, whatever the identifier believes.
* **A 95 % radius** per predicted pose (:class:`CoverageRadius`): the 95 % quantile of the
  published predictor's own recent errors at that horizon, corrected online (each miss raises
  it, each hit lowers it by a twentieth as much) so that the long-run coverage is 95 %.

Every array here is for one vehicle; stamps are float seconds relative to the vehicle's first
estimate (so that float64 keeps sub-microsecond resolution).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from cloe_ros.core import kernels, kernels_combine, kernels_ensemble, kernels_models
from cloe_ros.core.model import (
    BLOCK_SLICES,
    BLOCKS,
    QUADROTOR_MAX_ACCELERATION,
    QUADROTOR_MAX_SPEED,
    discretise,
    propagate,
    system_matrices,
)
from cloe_ros.errors import ConfigError
from cloe_ros.settings import check_fields, default

#: Reference channels, in the order of ``r = [x_d, y_d, psi_d, z_d]``, and the state index of the
#: position (or yaw) each commands.
CHANNELS = ('x', 'y', 'psi', 'z')
CHANNEL_STATE = np.array([0, 4, 8, 10])
CHANNEL_RATE = np.array([1, 5, 9, 11])
#: Scored coordinates: positions x, y, z (indices into zeta, and into the reference channels).
POSITION = np.array([0, 4, 10])
VELOCITY = np.array([1, 5, 11])
POSITION_CHANNELS = np.array([0, 1, 3])
#: The horizontal reference channels, fitted with one frequency by the ellipse intent.
XY = np.array([0, 1])

#: Candidates of the vehicle's path, in this order (see :class:`Anticipator`).
CANDIDATES = ('model', 'turn', 'velocity', 'hold', 'centroid')
#: The least growth exponent of each candidate's mean squared error with the horizon (and of the
#: published path's), used where a horizon has no score yet: what extrapolates a velocity or an
#: acceleration it cannot know to change misses by ~h^2 (MSE ~h^4); what holds a position or
#: follows a reference misses by ~h (MSE ~h^2); the centroid by a constant.
GROWTH = np.array([2.0, 4.0, 4.0, 2.0, 0.0, 0.0])
#: The scale the radius's scores are normalised by: the candidates' spread about the published
#: path plus this floor, m, and this growth with the horizon, m/s.
SCALE_FLOOR = 0.02
SCALE_GROWTH = 0.05
#: Candidates that rely on the reference (excluded for a channel whose reference is not tracked).
USES_REFERENCE = ('model',)
#: Intent models of the reference, in this order (see :class:`Intent`).
INTENT_MODELS = ('hold', 'velocity', 'harmonic', 'harmonic_xy')

#: The predictions run compiled (:mod:`~cloe_ros.core.kernels_models`,
#: :mod:`~cloe_ros.core.kernels_ensemble`, :mod:`~cloe_ros.core.kernels_combine`): each kernel
#: gives bitwise the numpy code's values (it calls numpy's own BLAS and LAPACK,
#: :mod:`~cloe_ros.core.blas`), without the requests that batch that code's solves over the
#: vehicles. Where numpy's OpenBLAS is not found, the numpy code runs.
COMPILED = kernels_ensemble.AVAILABLE and kernels_combine.AVAILABLE and kernels_models.AVAILABLE


def raise_for(status: int) -> None:
    """Raise what the numpy code raises where a kernel returned ``status`` (0: nothing)."""
    if status == kernels_ensemble.LINALG_ERROR:
        raise np.linalg.LinAlgError('a solve of the prediction failed (singular matrix)')
    if status == kernels_ensemble.INDEX_ERROR:
        raise IndexError('the prediction has no candidate to weigh')
    if status:
        raise ValueError(f'the prediction failed (kernel status {status})')


@dataclass(frozen=True)
class AnticipationConfig:
    """Settings of intent, trust, guard and radius (docs/anticipation.md).

    Attributes:
        intent: Predict the reference from its own past when there is no plan (else: held).
        guard: Publish the per-horizon combination of candidates (else: the model alone).
        trust: Check whether the vehicle tracks its reference (else: it always does).
        score_time: Time constant of the recent scores of candidates and intents, s (of issue
            time).
        intent_window: Recent past the harmonic intent models are fitted on, s.
        centroid_window: Recent past whose mean position is the centroid candidate, s.
        coverage: Probability the published radius is meant to hold.
        trust_horizon: Span of the hindsight replay of the reference trust, s.
        trust_time: Time constant of the trust statistics, s.
        trust_memory: The reference is judged with the model in use this long ago, s: an
            identifier fed a reference the vehicle ignores fits itself to it within seconds.
        trust_hold: A channel found not tracked is judged with the model that found it for at
            most this long, s (then with the model in use ``trust_memory`` ago again).
        trust_ratio: A channel is not tracked when the replay with its reference misses by more
            than this many times constant velocity's miss ...
        trust_floor: ... and by more than this (m, rad for yaw); tracked again below half of it
            or below the ratio.
        ground_altitude: A commanded altitude at or below this (m) commands the vehicle to the
            ground: no channel is tracked (negative: never).
        max_speed: Physical envelope of the predictions: no quadrotor flies faster, m/s ...
        max_acceleration: ... or accelerates harder, m/s^2 (see :func:`clip_to_envelope`).

    """

    intent: bool = default('prediction_intent')
    guard: bool = default('prediction_guard')
    trust: bool = default('reference_trust')
    score_time: float = 5.0
    intent_window: float = 3.0
    centroid_window: float = 6.0
    coverage: float = default('prediction_coverage')
    trust_horizon: float = 1.0
    trust_time: float = 1.0
    trust_memory: float = 5.0
    trust_hold: float = 60.0
    trust_ratio: float = default('reference_trust_ratio')
    trust_floor: float = default('reference_trust_floor')
    ground_altitude: float = 0.05
    max_speed: float = QUADROTOR_MAX_SPEED
    max_acceleration: float = QUADROTOR_MAX_ACCELERATION

    def __post_init__(self) -> None:
        check_fields(self, 'anticipation')  # the settings' defaults and ranges: cloe_ros.settings
        for name, low, high in (
            ('score_time', 0.1, 1e4), ('intent_window', 0.5, 60.0),
            ('centroid_window', 0.5, 600.0),
            ('trust_horizon', 0.2, 10.0), ('trust_time', 0.05, 60.0),
            ('trust_memory', 0.0, 600.0), ('trust_hold', 0.0, 1e6),
            ('max_speed', 1.0, 1e4), ('max_acceleration', 1.0, 1e4),
        ):  # fmt: skip
            value = getattr(self, name)
            if not (math.isfinite(value) and low <= value <= high):
                raise ConfigError(f'must be within [{low:g}, {high:g}], got {value!r}', name)
        if not math.isfinite(self.ground_altitude):
            raise ConfigError(f'must be finite, got {self.ground_altitude!r}', 'ground_altitude')


# ----------------------------------------------------------------------------- history


class History:
    """The recent past of one vehicle at the engine's rate: the last ``capacity`` steps.

    Per step: time (s), the measured state (12,), the estimate (12,) and the reference the
    estimator used (4,). The rows are kept in a linear buffer half as long again as the
    capacity, in order, so the held steps are always one slice of it (read without a copy);
    when the buffer's end is reached, the newest steps move to its front.
    """

    COLUMNS = ('t', 'measured', 'estimate', 'reference', 'logged')

    def __init__(self, span: float, rate: float) -> None:
        self.capacity = max(8, math.ceil(span * rate) + 2)
        size = self.capacity + max(8, self.capacity // 2)
        self.t = np.zeros(size)
        self.measured = np.zeros((size, 12))
        self.estimate = np.zeros((size, 12))
        self.reference = np.zeros((size, 4))
        self.logged = np.zeros((size, 4))  # the reference as received
        self._end = 0  # one past the newest row
        self.count = 0

    def clear(self) -> None:
        self._end = 0
        self.count = 0

    def append(self, t: float, measured, estimate, reference, logged) -> None:
        k = self._end
        if k == len(self.t):  # the buffer is full: the newest capacity - 1 rows go to the front
            keep = self.capacity - 1
            for name in self.COLUMNS:
                column = getattr(self, name)
                column[:keep] = column[k - keep : k]
            k = keep
        self.t[k] = t
        self.measured[k] = measured
        self.estimate[k] = estimate
        self.reference[k] = reference
        self.logged[k] = logged
        self._end = k + 1
        self.count += 1

    @property
    def held(self) -> slice:
        """The rows of the held steps, oldest first."""
        return slice(self._end - min(self.count, self.capacity), self._end)

    def ordered(self, column: str) -> np.ndarray:
        """``column`` (a field name) of the held steps, oldest first: a view, valid until the
        next append."""
        return getattr(self, column)[self.held]

    def last(self, span: float | None = None) -> slice:
        """The rows of the steps of the last ``span`` s (all held if None), oldest first, as a
        slice (reads are views; the times are increasing, a time jump clears the history)."""
        held = self.held
        if span is None or held.stop == held.start:
            return held
        t = self.t[held]
        first = int(np.searchsorted(t, t[-1] - span - 1e-9, side='left'))
        return slice(held.start + first, held.stop)

    def at(self, times: np.ndarray, column: str, channels) -> np.ndarray:
        """``column`` (a field name) interpolated at ``times`` (...,) for ``channels``:
        (..., len(channels)), with the arithmetic of ``np.interp`` (the same values); NaN
        outside the held span."""
        times = np.asarray(times, float)
        channels = np.asarray(channels, dtype=np.intp)
        out = np.empty((times.size, len(channels)))
        kernels.interpolate(self.ordered('t'), self.ordered(column),
                            np.ascontiguousarray(times.reshape(-1)), channels, out)  # fmt: skip
        return out.reshape(*times.shape, len(channels))


# ------------------------------------------------------------------------------ intent


def last_jump(r: np.ndarray, factor: float = 10.0, floor: float = 0.1) -> int:
    """Index just after the last jump of the reference positions ``r`` (T, 3): a one-sample move
    more than ``factor`` times the typical one and more than ``floor`` m (0 if none). The fits
    of :class:`Intent` start there, so one step of the setpoint does not read as a velocity."""
    if len(r) < 3:
        return 0
    d = np.sqrt(np.sum(np.diff(r, axis=0) ** 2, axis=1))
    big = np.flatnonzero(d > max(floor, factor * median(d)))
    return int(big[-1] + 1) if len(big) else 0


def median(x: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D ``x``, the same value (the middle entries of one
    partition, averaged as numpy does; NaN if any is), without its generic reduction's cost."""
    n = len(x)
    k = n // 2
    p = np.partition(x, (k, -1) if n % 2 else (k - 1, k, -1))
    if np.isnan(p[-1]):
        return math.nan
    return float(p[k]) if n % 2 else (float(p[k - 1]) + float(p[k])) / 2.0


def harmonic_fit(
    t: np.ndarray, y: np.ndarray, ahead: np.ndarray, omegas: np.ndarray, joint: bool = False
) -> np.ndarray:
    """Extrapolate ``y`` (T, C), sampled at ``t`` (T,) s (<= 0, now at 0), to ``ahead`` (K,) s with
    the single-frequency fit ``c + a cos(w t) + b sin(w t)`` of least squared error, the
    frequency searched over ``omegas`` (W,) rad/s per column, or shared by every column when
    ``joint`` (a circle or an ellipse in x and y). Returns (K, C)."""
    columns = np.arange(y.shape[1])
    separate, shared = harmonic_fits(t, y, ahead, omegas, columns if joint else columns[:0])
    return shared if joint else separate


def harmonic_fits(
    t: np.ndarray, y: np.ndarray, ahead: np.ndarray, omegas: np.ndarray, joint: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`harmonic_fit` of every column of ``y`` (K, C), and of the columns ``joint`` with
    one frequency (K, len(joint)), from one least-squares solve per frequency."""
    separate, shared = harmonic_fits_batch(t[None], y[None], ahead, omegas, joint)
    return separate[0], shared[0]


def harmonic_fits_batch(
    t: np.ndarray, y: np.ndarray, ahead: np.ndarray, omegas: np.ndarray, joint: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`harmonic_fits` of V series at once: ``t`` (V, T), ``y`` (V, T, C); returns
    (V, K, C) and (V, K, len(joint)), each series' as it gets alone (every product is per
    series and frequency)."""
    t, y = np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(y, dtype=float)
    omegas = np.ascontiguousarray(omegas, dtype=float)
    basis = np.empty((len(t), len(omegas), t.shape[1], 3))  # (V, W, T, 3): 1, cos, sin
    kernels.harmonic_basis(t, omegas, basis)
    basis_t = np.swapaxes(basis, -1, -2)  # (V, W, 3, T); matmul (BLAS), 3x einsum's speed here
    gram = basis_t @ basis
    gram += 1e-9 * np.eye(3)
    coef = np.linalg.solve(gram, basis_t @ y[:, None])  # (V, W, 3, C)
    resid = np.empty((len(t), len(omegas), y.shape[2]))  # (V, W, C)
    kernels.harmonic_residuals(basis, coef, y, resid)
    series = np.arange(len(t))[:, None]

    def extrapolate(best: np.ndarray, columns: np.ndarray) -> np.ndarray:  # best (V, C')
        wa = ahead[None, :, None] * omegas[best][:, None, :]  # (V, K, C')
        c = coef[series, best, :, columns[None, :]]  # (V, C', 3)
        return (c[:, None, :, 0] + c[:, None, :, 1] * np.cos(wa)
                + c[:, None, :, 2] * np.sin(wa))  # fmt: skip

    columns = np.arange(y.shape[2])
    separate = extrapolate(np.argmin(resid, axis=1), columns)
    if not len(joint):
        return separate, np.zeros((len(t), len(ahead), 0))
    best = np.argmin(resid[:, :, joint].sum(axis=2), axis=1)  # (V,)
    return separate, extrapolate(np.repeat(best[:, None], len(joint), axis=1), joint)


def linear_fit(t: np.ndarray, y: np.ndarray, ahead: np.ndarray) -> np.ndarray:
    """Least-squares line through ``y`` (T, C) at ``t`` (T,), evaluated at ``ahead`` (K,)."""
    basis = np.column_stack([np.ones_like(t), t])
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return coef[0] + np.outer(ahead, coef[1])


class Intent:
    """Candidate futures of the reference (``INTENT_MODELS``) from its recent past.

    Args:
        window: Span of the harmonic fits, s (the constant-velocity fit uses the last second).
        ahead: Times after now of the predicted references, s (K,): the starts of the
            prediction steps.

    """

    #: Frequencies searched by the harmonic models: periods from 1.5 s to 30 s.
    OMEGAS = 2.0 * np.pi / np.geomspace(1.5, 30.0, 60)
    #: The fits use every this-many-th sample (at 100 Hz: 20 Hz), enough for periods >= 1.5 s.
    SUBSAMPLE_HZ = 20.0

    def __init__(self, window: float, ahead: np.ndarray) -> None:
        self.window = window
        self.ahead = np.asarray(ahead, float)

    def candidates_steps(self, t: np.ndarray, r: np.ndarray):
        """(len(INTENT_MODELS), K, 4) futures of the references ``r`` (T, 4) sampled at ``t``
        (T,) s, the last sample being now; as steps (see :func:`run`): the harmonic fit is a
        request."""
        k = len(self.ahead)
        if COMPILED:
            out = np.empty((len(INTENT_MODELS), k, 4))
            raise_for(kernels_ensemble.intent_candidates(
                np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(r, dtype=float),
                self.ahead, self.OMEGAS, float(self.window), self.SUBSAMPLE_HZ, out))  # fmt: skip
            return out
        out = np.broadcast_to(r[-1], (len(INTENT_MODELS), k, 4)).copy()
        now = t[-1]
        start = last_jump(r[:, POSITION_CHANNELS])
        t, r = t[start:] - now, r[start:]
        recent = t >= -1.0
        if np.count_nonzero(recent) >= 5 and t[recent][0] <= -0.5:
            out[1] = linear_fit(t[recent], r[recent], self.ahead)
        if len(t) >= 2 and t[0] <= -0.5 * self.window:
            step = max(1, round(1.0 / (self.SUBSAMPLE_HZ * max(median(np.diff(t)), 1e-6))))
            ts, rs = t[::-1][::step][::-1], r[::-1][::step][::-1]  # (keeps the last sample)
            if len(ts) >= 10:
                out[2], joint = yield HarmonicFits(ts, rs, self.ahead, self.OMEGAS, XY)
                out[3] = out[2]
                out[3][:, :2] = joint
        return out


# ---------------------------------------------------------------------------- ensemble


def simplex_weights(s: np.ndarray, allowed: np.ndarray, shrink: float = 0.1) -> np.ndarray:
    """Weights ``w >= 0``, ``sum(w) = 1``, on the ``allowed`` (M,) candidates, minimising
    ``w' S w`` for each horizon's error cross-product matrix ``S`` (K, M, M) shrunk by
    ``shrink`` towards its diagonal (a minimum-variance combination). (K, M)."""
    k, m, _ = s.shape
    diag = np.einsum('kii->ki', s)
    s = (1.0 - shrink) * s + shrink * diag[:, :, None] * np.eye(m)
    s = s + 1e-12 * (1.0 + diag.max(axis=1))[:, None, None] * np.eye(m)
    active = np.broadcast_to(allowed, (k, m)).copy()
    w = np.zeros((k, m))
    todo = np.arange(k)  # the horizons whose active set changed (the others are solved)
    for _ in range(m):
        # solve on the active set (inactive rows and columns become the identity)
        on = active[todo]
        sa = np.where(on[:, :, None] & on[:, None, :], s[todo], 0.0)
        sa += np.where(on, 0.0, 1.0)[:, :, None] * np.eye(m)
        x = np.linalg.solve(sa, on.astype(float)[..., None])[..., 0]
        w[todo] = x = x / x.sum(axis=1, keepdims=True)
        negative = on & (x < 0)
        again = negative.any(axis=1)
        if not again.any():
            break
        worst = np.argmin(np.where(negative, x, np.inf), axis=1)
        todo = todo[again]
        active[todo, worst[again]] = False
    return np.where(active, np.clip(w, 0.0, None), 0.0)


# ------------------------------------------------------------------------ requests
#
# The solves and model runs of a prediction that cost the most for their size (a least-squares
# fit per frequency, the simplex weights, the closed loop's run, the recent-offset fit) are
# written as steps: a generator yields a request and is sent its answer. :func:`run` answers at
# once; :func:`run_together` drives the predictions of many vehicles side by side and answers
# the requests of one kind and shape in one batched call, each the answer it would get alone.
# A request is a frozen dataclass with ``key()`` (requests of one key are batched) and the
# class method ``answer_all(requests)`` (their answers, in order).


@dataclass(frozen=True)
class HarmonicFits:
    """A request for :func:`harmonic_fits` with these arguments."""

    t: np.ndarray
    y: np.ndarray
    ahead: np.ndarray
    omegas: np.ndarray
    joint: np.ndarray

    def key(self) -> tuple:
        return ('harmonic', self.y.shape, self.ahead.tobytes(), self.omegas.tobytes(),
                self.joint.tobytes())  # fmt: skip

    @classmethod
    def answer_all(cls, requests: list) -> list:
        first = requests[0]
        separate, joint = harmonic_fits_batch(*stack_fields(requests, ('t', 'y')), first.ahead,
                                              first.omegas, first.joint)  # fmt: skip
        return list(zip(separate, joint))


@dataclass(frozen=True)
class SimplexWeights:
    """A request for :func:`simplex_weights` of ``s`` (K, M, M) over ``allowed`` (M,)."""

    s: np.ndarray
    allowed: np.ndarray

    def key(self) -> tuple:
        return ('simplex', self.s.shape[1])

    @classmethod
    def answer_all(cls, requests: list) -> list:
        sizes = [len(r.s) for r in requests]
        allowed = np.concatenate([np.broadcast_to(r.allowed, r.s.shape[:2]) for r in requests])
        w = simplex_weights(np.concatenate([r.s for r in requests]), allowed)
        return np.split(w, np.cumsum(sizes)[:-1])


@dataclass(frozen=True)
class Propagation:
    """A request for the states (n, 12) of the discrete model ``(ad, bd)`` run from ``x0`` (12,)
    over the references ``refs`` (n, 4) (:func:`~cloe_ros.core.model.propagate`)."""

    ad: np.ndarray
    bd: np.ndarray
    x0: np.ndarray
    refs: np.ndarray

    def key(self) -> tuple:
        return ('propagate', self.refs.shape)

    @classmethod
    def answer_all(cls, requests: list) -> list:
        return list(propagate(*stack_fields(requests, ('ad', 'bd', 'x0', 'refs'))))


def stack_fields(requests: list, names: tuple[str, ...]) -> list[np.ndarray]:
    """Each field ``names`` of ``requests`` (all of one shape), stacked: (len(requests), ...)."""
    return [np.array([getattr(r, name) for r in requests]) for name in names]


def answer(requests: list) -> list:
    """The answers of ``requests`` (all of one :meth:`key`), in one batched call."""
    return type(requests[0]).answer_all(requests)


def run(steps):
    """The value of the generator ``steps``, its requests answered one at a time."""
    try:
        request = next(steps)
        while True:
            request = steps.send(answer([request])[0])
    except StopIteration as done:
        return done.value


def run_together(all_steps: list, failures: tuple = (ArithmeticError, np.linalg.LinAlgError)
                 ) -> list:  # fmt: skip
    """The values of several generators driven side by side (requests of one kind and shape
    answered together); a generator that raises one of ``failures`` gets it as its value (a
    batched call that raises is answered again one request at a time, so that only the
    generator whose request failed fails)."""
    values: list = [None] * len(all_steps)
    live: dict[int, object] = {}

    def resume(i: int, send) -> None:
        steps = all_steps[i]
        try:
            if isinstance(send, BaseException):
                live[i] = steps.throw(send)
            else:
                live[i] = steps.send(send)
        except StopIteration as done:
            values[i] = done.value
        except failures as err:
            values[i] = err

    for i in range(len(all_steps)):
        resume(i, None)
    while live:
        groups: dict[tuple, list[int]] = {}
        for i, request in live.items():
            groups.setdefault(request.key(), []).append(i)
        asked, live = live, {}
        for members in groups.values():
            try:
                answers = answer([asked[i] for i in members])
            except failures:
                answers = []
                for i in members:
                    try:
                        answers.append(answer([asked[i]])[0])
                    except failures as err:
                        answers.append(err)
            for i, reply in zip(members, answers):
                resume(i, reply)
    return values


@dataclass(frozen=True)
class Scores:
    """Poses scored by :meth:`Ensemble.score`, by prediction (in slot order), then horizon: the
    slot of their prediction (n,), its issue time (n,), their horizon (n,) and each candidate's
    squared error (n, M)."""

    slots: np.ndarray
    issued: np.ndarray
    horizons: np.ndarray
    squared: np.ndarray


class Ensemble:
    """Per-horizon weights of M candidate predictors from their scored past predictions.

    :meth:`weights` gives, per horizon, the convex combination of the allowed candidates with
    the least recent squared error (:func:`simplex_weights` on exponentially weighted error
    cross-products, time constant ``score_time`` s of issue time). Horizons not scored yet (the
    longest ones, early on) take each candidate's error extrapolated from its growth over the
    scored horizons (MSE ~ h^alpha, 0 <= alpha <= 4), with the correlations of the longest
    scored horizon; before any score, the first allowed candidate alone.

    Args:
        names: Candidate names (M).
        offsets: Times of the predicted poses after their issue time, s (K,).
        dims: Scored coordinates per pose (D).
        score_time: Time constant of the scores, s of issue time.
        period: Time between two predictions, s.
        max_pending: Most predictions awaiting their scores (older ones are dropped).

    """

    def __init__(
        self, names, offsets: np.ndarray, dims: int, score_time: float, period: float,
        max_pending: int, min_growth: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        self.names = tuple(names)
        m = len(self.names)
        self.min_growth = np.zeros(m) if min_growth is None else np.asarray(min_growth, float)
        self.offsets = np.asarray(offsets, float)
        m, k = len(self.names), len(self.offsets)
        self._alpha = 1.0 - math.exp(-period / score_time)
        self.cross = np.zeros((k, m, m))  # exponentially weighted error cross-products
        self.scored = np.zeros(k, dtype=bool)
        self._pending_t = np.full(max_pending, np.nan)  # issue times
        self._pending = np.zeros((max_pending, m, k, dims))
        self._next = 0

    def clear(self) -> None:
        self.cross[:] = 0.0
        self.scored[:] = False
        self._pending_t[:] = np.nan

    def add(self, t: float, paths: np.ndarray) -> int:
        """Remember the candidates' predictions ``paths`` (M, K, D) issued at ``t``; returns the
        slot it is kept in (until it is scored, or ``max_pending`` more are added)."""
        slot = self._next
        self._pending_t[slot] = t
        self._pending[slot] = paths
        self._next = (slot + 1) % len(self._pending_t)
        return slot

    def score(
        self, since: float, now: float, t: np.ndarray, truth: np.ndarray, channels: np.ndarray
    ) -> Scores:
        """Score the poses whose times fall in ``(since, now]`` against the true values
        ``truth[:, channels]`` (T, D) sampled at the increasing ``t`` (T,) s, interpolated
        (poses outside their span are not scored); forget the predictions all of whose poses
        are due. Each horizon's scores are weighed in in the predictions' order (the first
        score of a horizon is its estimate, see :class:`Ensemble`). Returns the scored poses,
        by prediction (in slot order), then horizon."""
        size = self._pending.shape[0] * len(self.offsets)
        slots, horizons = np.empty(size, np.intp), np.empty(size, np.intp)
        issued, squared = np.empty(size), np.empty((size, len(self.names)))
        n = kernels.score_ensemble(
            self._pending_t, self._pending, self.offsets, since, now,
            np.ascontiguousarray(t, dtype=float), np.asarray(truth, dtype=float),
            np.asarray(channels, dtype=np.intp), self.cross, self.scored, self._alpha, slots,
            issued, horizons, squared,
        )  # fmt: skip
        return Scores(slots[:n], issued[:n], horizons[:n], squared[:n])

    def expected_cross(self) -> np.ndarray:
        """The error cross-products per horizon (K, M, M), unscored horizons extrapolated."""
        cross = self.cross.copy()
        scored = np.flatnonzero(self.scored)
        if not len(scored):
            return cross
        last = scored[-1]
        k = len(self.offsets)
        if last + 1 < k:
            mse = np.einsum('kmm->km', cross)
            half = scored[np.searchsorted(scored, (last + 1) // 2 - 1)] if last > 0 else last
            h_last, h_half = self.offsets[last], self.offsets[half]
            if last > half:
                ratio = (mse[last] + 1e-12) / (mse[half] + 1e-12)
                alpha = np.clip(np.log(ratio) / np.log(h_last / h_half), 0.0, 4.0)
            else:
                alpha = np.full(len(self.names), 2.0)
            alpha = np.maximum(alpha, self.min_growth)
            ks = np.arange(last + 1, k)
            sd_last = np.sqrt(mse[last] + 1e-24)
            rho = cross[last] / np.outer(sd_last, sd_last)
            sd = sd_last[None, :] * (self.offsets[ks, None] / h_last) ** (alpha[None, :] / 2.0)
            cross[ks] = rho[None] * sd[:, :, None] * sd[:, None, :]
        # horizons below the longest scored one that have no score yet: the nearest shorter one
        for j in range(last):
            if not self.scored[j]:
                cross[j] = cross[scored[np.searchsorted(scored, j)]]
        return cross

    def weights(self, allowed: np.ndarray | None = None) -> np.ndarray:
        """(K, M) weights (rows sum to 1) over the ``allowed`` (M,) candidates (default all)."""
        return run(self.weights_steps(allowed))

    def weights_steps(self, allowed: np.ndarray | None = None):
        """:meth:`weights` as steps (see :func:`run`): the simplex solve is a request."""
        m = len(self.names)
        allowed = np.ones(m, dtype=bool) if allowed is None else np.asarray(allowed, bool)
        if not self.scored.any():
            w = np.zeros((len(self.offsets), m))
            w[:, int(np.flatnonzero(allowed)[0])] = 1.0
            return w
        if COMPILED:
            return compiled_weights(self, m, allowed)
        return (yield SimplexWeights(self.expected_cross(), allowed))


def compiled_weights(ensemble: Ensemble, m: int, allowed: np.ndarray) -> np.ndarray:
    """The weights (K, m) over the first ``m`` candidates of ``ensemble``, the ``allowed`` ones
    (:func:`~cloe_ros.core.kernels_ensemble.ensemble_weights`)."""
    out = np.empty((len(ensemble.offsets), m))
    raise_for(kernels_ensemble.ensemble_weights(
        ensemble.cross, ensemble.scored, ensemble.offsets, ensemble.min_growth, m,
        np.ascontiguousarray(allowed, dtype=bool), out))  # fmt: skip
    return out


# ------------------------------------------------------------------------------ radius


class CoverageRadius:
    """The radius per horizon within which the vehicle is meant to be with probability
    ``coverage``, from the published predictor's own recent errors at that horizon.

    The radius of a horizon is the quantile, at level ``q``, of the last ``window`` errors scored
    there, and ``q`` is corrected online after each scored pose (adaptive conformal inference,
    Gibbs & Candes 2021): ``q += gain * (miss - (1 - coverage))``, so a miss raises the level by
    ``gain * coverage`` and a hit lowers it by ``gain * (1 - coverage)``. Over a flight the misses
    then approach ``1 - coverage`` of the scored poses whatever the shape of the error
    distribution, and the radius never leaves the range of the recent errors (at ``q >= 1`` it is
    the largest one). Horizons with fewer than ``min_errors`` scores take the radius of the
    longest scored horizon grown like the errors grow with the horizon; before any score, the
    prior ``prior_floor + prior_speed * h`` (m).
    """

    def __init__(
        self,
        offsets: np.ndarray,
        coverage: float,
        window: int = 50,
        gain: float = 0.05,
        min_errors: int = 5,
        prior_floor: float = 0.1,
        prior_speed: float = 1.0,
    ) -> None:
        self.offsets = np.asarray(offsets, float)
        k = len(self.offsets)
        self.coverage, self.window, self.gain, self.min_errors = coverage, window, gain, min_errors
        self.prior = prior_floor + prior_speed * self.offsets
        self._errors = np.full((k, window), np.nan)
        self._count = np.zeros(k, dtype=int)
        self.level = np.full(k, coverage)

    def clear(self) -> None:
        self._errors[:] = np.nan
        self._count[:] = 0
        self.level[:] = self.coverage

    def update(
        self, ks: np.ndarray, errors: np.ndarray, radii_then: np.ndarray, scales: np.ndarray
    ) -> None:
        """Scored errors (m) at horizons ``ks`` of a prediction published with ``radii_then``
        and the ``scales`` of then (see :meth:`radii`)."""
        self._errors[ks, self._count[ks] % self.window] = errors / scales
        self._count[ks] += 1
        miss = (errors > radii_then).astype(float)
        self.level[ks] = np.clip(self.level[ks] + self.gain * (miss - (1.0 - self.coverage)),
                                 0.0, 1.0)  # fmt: skip

    def radii(self, scales: np.ndarray) -> np.ndarray:
        """The radius of each horizon (K,), m, finite and > 0, for the current ``scales`` (K,):
        the scores are errors over the scale of their prediction (normalised conformal scores),
        so the radius follows at once what the scale sees change."""
        have = self._count >= self.min_errors
        if not have.any():
            return self.prior.copy()
        idx = np.flatnonzero(have)
        out = np.full(len(self.offsets), np.nan)
        errors = np.sort(self._errors[idx], axis=1)  # NaN (unfilled) last
        n = np.minimum(self._count[idx], self.window)
        pos = np.minimum(np.ceil(self.level[idx] * n).astype(int), n) - 1
        out[idx] = errors[np.arange(len(idx)), np.clip(pos, 0, None)]
        out[idx[-1] + 1:] = out[idx[-1]]
        gaps = ~np.isfinite(out)
        out[gaps] = np.interp(self.offsets[gaps], self.offsets[idx], out[idx])
        # the uncertainty of a later pose is never less than an earlier one's
        return np.maximum.accumulate(np.maximum(out * scales, 1e-3))


# ------------------------------------------------------------------------------- trust


@dataclass
class TrustStatus:
    """Per reference channel (x, y, psi, z): tracked or not, and why, in words."""

    tracked: np.ndarray
    reasons: tuple[str, ...]
    all_tracked: bool = field(init=False)  # (read at every step: worked out once)

    def __post_init__(self) -> None:
        self.all_tracked = bool(self.tracked.all())


class ReferenceTrust:
    """Whether the vehicle tracks each reference channel (module docstring).

    Every ``update``, the model in use is replayed over the last ``trust_horizon`` s from the
    estimate of then, with the references the estimator used since (``replay``), and its miss
    ``e_ref`` of where the vehicle is now compared with the miss ``e_free`` of constant velocity
    from the measurement of then. Both are squared, exponentially averaged over ``trust_time``.
    A channel becomes not tracked when ``E_ref > ratio^2 E_free`` and ``E_ref > floor^2``, and
    tracked again when ``E_ref < ratio^2 E_free`` or ``E_ref < (floor / 2)^2``.
    """

    def __init__(self, config: AnticipationConfig) -> None:
        self.config = config
        self.e_ref = np.full(4, np.nan)
        self.e_free = np.full(4, np.nan)
        self.followed = np.ones(4, dtype=bool)  # by the replay test
        self.all_followed = True  # (read at every step: kept beside followed)
        self.grounded = False
        self._last_t: float | None = None

    def clear(self) -> None:
        self.e_ref[:] = np.nan
        self.e_free[:] = np.nan
        self.followed[:] = True
        self.all_followed = True
        self.grounded = False
        self._last_t = None

    def update(self, t: float, miss_ref: np.ndarray, miss_free: np.ndarray) -> None:
        """Take the replay's and constant velocity's misses (4,) at time ``t``."""
        cfg = self.config
        if not cfg.trust:
            return
        dt = 0.2 if self._last_t is None else max(t - self._last_t, 0.0)
        self._last_t = t
        a = 1.0 - math.exp(-dt / cfg.trust_time)
        if COMPILED:  # (a new followed array, as np.where gives: steps may hold the old one)
            self.followed = self.followed.copy()
            self.all_followed = bool(kernels_models.trust_update(
                self.e_ref, self.e_free, self.followed, np.asarray(miss_ref, dtype=float),
                np.asarray(miss_free, dtype=float), a, cfg.trust_ratio**2,
                cfg.trust_floor**2))  # fmt: skip
            return
        for stat, new in ((self.e_ref, miss_ref**2), (self.e_free, miss_free**2)):
            fresh = np.isnan(stat)
            stat[fresh] = new[fresh]
            stat[~fresh] += a * (new[~fresh] - stat[~fresh])
        ratio2, floor2 = cfg.trust_ratio**2, cfg.trust_floor**2
        bad = (self.e_ref > ratio2 * self.e_free) & (self.e_ref > floor2)
        good = (self.e_ref <= ratio2 * self.e_free) | (self.e_ref < floor2 / 4.0)
        self.followed = np.where(bad, False, np.where(good, True, self.followed))
        self.all_followed = bool(self.followed.all())

    def set_commanded_altitude(self, z_d: float) -> None:
        ground = self.config.ground_altitude
        self.grounded = self.config.trust and ground >= 0 and z_d <= ground

    def status(self) -> TrustStatus:
        if self.grounded:
            return TrustStatus(np.zeros(4, dtype=bool),
                               ('commanded to the ground',) * 4)  # fmt: skip
        reasons = tuple(
            '' if ok else f'the model driven by it misses by {math.sqrt(er):.2f} '
            f'({"rad" if c == "psi" else "m"}), constant velocity by {math.sqrt(ef):.2f}'
            for c, ok, er, ef in zip(CHANNELS, self.followed, self.e_ref, self.e_free)
        )
        return TrustStatus(self.followed.copy(), reasons)


# -------------------------------------------------------------------- virtual reference


class VirtualReference:
    """The reference of each channel that the vehicle's own motion implies under a model.

    For a block with static gain ``g`` (position per unit reference) and mean delay ``tau``
    (``-G'(0) / G(0)`` of its transfer function from the reference to the position), a vehicle
    at ``p`` moving at ``v`` is, to first order, on the closed loop's steady ramp response to
    the reference ``(p + tau v) / g``. Driving the observer and the predictions with it uses no
    logged reference and leaves a constant-velocity motion unforced.
    """

    def __init__(self) -> None:
        self._key: bytes | None = None
        self.gain = np.ones(4)
        self.delay = np.full(4, 0.5)

    def update(self, theta: np.ndarray, coupling: np.ndarray, blocks) -> None:
        """From the model ``(theta, coupling)`` and its blocks (nothing to do if unchanged)."""
        key = theta.tobytes() + coupling.tobytes()
        if key == self._key:
            return
        self._key = key
        a, b = system_matrices(theta, coupling)
        for block in blocks:
            idx = list(block.states)
            try:
                inv = np.linalg.inv(a[np.ix_(idx, idx)])
            except np.linalg.LinAlgError:
                continue
            col = b[idx, block.reference]
            g0 = -(inv @ col)[0]
            g1 = -(inv @ inv @ col)[0]
            if abs(g0) > 0.1 and np.isfinite(g0) and np.isfinite(g1):
                self.gain[block.reference] = g0
                self.delay[block.reference] = float(np.clip(-g1 / g0, 0.0, 5.0))

    def of(self, zeta: np.ndarray) -> np.ndarray:
        """The virtual reference (4,) of the state ``zeta`` (12,)."""
        return (zeta[CHANNEL_STATE] + self.delay * zeta[CHANNEL_RATE]) / self.gain


# ---------------------------------------------------------------------------- envelope


def clip_to_envelope(
    p0: np.ndarray, v0: np.ndarray, offsets: np.ndarray, positions: np.ndarray,
    max_speed: float, max_acceleration: float,
) -> np.ndarray:  # fmt: skip
    """Positions (K, 3) moved, where needed, into the reach of a quadrotor at ``p0`` moving at
    ``v0`` (speed capped at ``max_speed``): within ``|v0| h + max_acceleration h^2 / 2`` of
    ``p0`` and ``max_speed h`` of it, ``h`` the ``offsets`` (K,) s."""
    speed = min(float(np.linalg.norm(v0)), max_speed)
    reach = np.minimum(speed * offsets + 0.5 * max_acceleration * offsets**2, max_speed * offsets)
    d = positions - p0
    dist = np.sqrt(np.sum(d * d, axis=1))
    scale = np.where(dist > reach, reach / np.maximum(dist, 1e-300), 1.0)
    return p0 + d * scale[:, None]


# -------------------------------------------------------------------------- candidates


def turn_positions(zeta: np.ndarray, coupling: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Constant speed and turn rate in x-y, constant vertical speed (K, 3): the horizontal
    acceleration is the tilt's (``c_x theta``, ``c_y phi``, the model's couplings), and the
    turn rate ``(v x a) / |v|^2``."""
    p, v = zeta[POSITION], zeta[VELOCITY]
    a = np.array([coupling[0] * zeta[2], coupling[1] * zeta[6]])
    out = np.empty((len(offsets), 3))
    out[:, 2] = p[2] + offsets * v[2]
    speed2 = float(v[:2] @ v[:2])
    omega = (v[0] * a[1] - v[1] * a[0]) / speed2 if speed2 > 1e-4 else 0.0
    if abs(omega) * offsets[-1] < 1e-3:
        out[:, :2] = p[:2] + np.outer(offsets, v[:2])
        return out
    s, c = np.sin(omega * offsets), np.cos(omega * offsets)
    out[:, 0] = p[0] + (s * v[0] - (1.0 - c) * v[1]) / omega
    out[:, 1] = p[1] + ((1.0 - c) * v[0] + s * v[1]) / omega
    return out


# ------------------------------------------------------------------------- anticipator


@dataclass
class Anticipation:
    """One prediction decision.

    Attributes:
        positions: Published positions (K, 3), m, at the pose offsets.
        radius: 95 % (``coverage``) radius of each pose (K,), m.
        weights: Weight of each candidate (``CANDIDATES``) per pose (K, M).
        trust: Whether each reference channel is tracked.
        intent: The future reference the closed loop was driven with (K, 4), or None (a plan).

    """

    positions: np.ndarray
    radius: np.ndarray
    weights: np.ndarray
    trust: TrustStatus
    intent: np.ndarray | None = None


class Anticipator:
    """Intent, trust, guard and radius of one vehicle (module docstring).

    The engine calls :meth:`observe` at every estimator step and, when a prediction is due,
    :meth:`update_steps` (the scores and the trust), :meth:`reference_path_steps` (the future
    reference to drive the closed loop with), then :meth:`combine_steps` with the closed loop's
    positions (generators of their costliest solves and model runs: :func:`run`,
    :func:`run_together`). :meth:`reference_for_estimator` gives the reference the
    estimator should use at a step.

    Args:
        config: Settings.
        step: Spacing of the predicted poses, s.
        n_poses: Number of predicted poses.
        rate: The engine's rate, Hz (the history's resolution).
        prediction_rate: Predictions per second (how many await their scores).
        ground_altitude: See :class:`ReferenceTrust` (the estimator's setting).

    """

    def __init__(
        self, config: AnticipationConfig, step: float, n_poses: int, rate: float,
        prediction_rate: float, ground_altitude: float,
    ) -> None:  # fmt: skip
        self.config = replace(config, ground_altitude=ground_altitude)
        self.step = step
        self.poses = step * np.arange(1, n_poses + 1)  # pose offsets
        self.starts = step * np.arange(n_poses)  # step starts (intent)
        span = max(config.centroid_window, config.intent_window, config.trust_horizon) + 1.0
        self.history = History(span + self.poses[-1], rate)
        pending = math.ceil((self.poses[-1] + 1.0) * prediction_rate) + 2
        period = 1.0 / prediction_rate
        self.guard = Ensemble((*CANDIDATES, 'published'), self.poses, 3, config.score_time,
                              period, pending, GROWTH)  # fmt: skip
        self.intent_scores = Ensemble(INTENT_MODELS, self.starts, 3, config.score_time, period,
                                      pending)  # fmt: skip
        self.intent = Intent(config.intent_window, self.starts)
        self.radius = CoverageRadius(self.poses, config.coverage)
        self._scales = np.full((pending, n_poses), np.nan)  # per guard slot (see update)
        self.trust = ReferenceTrust(self.config)
        self.virtual = VirtualReference()
        self._radii = np.full((pending, n_poses), np.nan)  # radius published, per guard slot
        self._scored_to: float | None = None
        self._snapshots: deque = deque()  # (t, theta, coupling) of the model in use, every 1 s
        self._frozen: list[tuple | None] = [None] * 4  # per channel: (since, theta, coupling)
        self._judge_key: bytes | None = None
        self._judge: tuple[np.ndarray, np.ndarray] | None = None

    def set_ground_altitude(self, ground_altitude: float) -> None:
        """Take the estimator's new ``ground_altitude`` (the node changes it while it runs): the
        reference trust reads it at the next commanded altitude."""
        self.config = replace(self.config, ground_altitude=ground_altitude)
        self.trust.config = self.config

    def clear(self) -> None:
        """Forget everything (a time jump or a reset)."""
        self.history.clear()
        self.guard.clear()
        self.intent_scores.clear()
        self.radius.clear()
        self.trust.clear()
        self._radii[:] = np.nan
        self._scales[:] = np.nan
        self._scored_to = None
        self._snapshots.clear()
        self._frozen = [None] * 4

    # ------------------------------------------------------------------------- steps

    def reference_for_estimator(
        self, zeta: np.ndarray, r: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The reference (4,) the estimator steps with, and which channels are tracked (4,):
        the logged one where it is tracked by the replay test, the virtual one elsewhere. (A
        vehicle commanded to the ground keeps its logged reference here; the identifier pauses
        for it anyway.)"""
        followed = self.trust.followed
        if self.trust.all_followed:
            return r, followed
        out = r.copy()
        virtual = self.virtual.of(zeta)
        out[~followed] = virtual[~followed]
        return out, followed

    def observe(self, t: float, measured: np.ndarray, estimate: np.ndarray,
                used: np.ndarray, logged: np.ndarray) -> None:  # fmt: skip
        """Record one estimator step at ``t`` s: the measured state, the estimate, the reference
        the estimator used and the reference as received."""
        self.history.append(t, measured, estimate, used, logged)
        self.trust.set_commanded_altitude(float(logged[3]))

    def update_steps(self, t: float, theta: np.ndarray, coupling: np.ndarray):
        """Score what has become due by ``t`` and update the reference trust, the model in use
        being ``(theta, coupling)``. As steps (see :func:`run`)."""
        since = -np.inf if self._scored_to is None else self._scored_to
        self._scored_to = t
        hist = self.history
        held_t = hist.ordered('t')
        scored = self.guard.score(since, t, held_t, hist.ordered('measured'), POSITION)
        slots, ks = scored.slots, scored.horizons
        if COMPILED:
            r = self.radius
            kernels_combine.coverage_scored(slots, ks, scored.squared, self._radii, self._scales,
                                            r._errors, r._count, r.level, r.gain,
                                            r.coverage)  # fmt: skip
        else:
            self._update_radius(slots, ks, np.sqrt(scored.squared[:, -1]))
        self.intent_scores.score(since, t, held_t, hist.ordered('logged'), POSITION_CHANNELS)
        self.virtual.update(np.asarray(theta, float), np.asarray(coupling, float), BLOCKS)
        yield from self._update_trust_steps(t, theta, coupling)

    def _update_radius(self, slots: np.ndarray, ks: np.ndarray, errors: np.ndarray) -> None:
        """The radius's update with the published prediction's ``errors`` (m) at the scored
        poses (slots ``slots``, horizons ``ks``), as :func:`~cloe_ros.core.kernels_combine.
        coverage_scored` does it compiled."""
        radii, scales = self._radii[slots, ks], self._scales[slots, ks]
        if len(ks) and len(np.unique(ks)) == len(ks):
            # each horizon scored once (as between two predictions): one update, the same
            self.radius.update(ks, errors, radii, scales)
        elif len(ks):  # prediction by prediction
            starts = np.flatnonzero(np.r_[True, slots[1:] != slots[:-1]])
            for a, b in zip(starts, [*starts[1:], len(slots)]):
                self.radius.update(ks[a:b], errors[a:b], radii[a:b], scales[a:b])

    def _judging_model(self, t: float, theta: np.ndarray, coupling: np.ndarray) -> tuple:
        """The model each channel's reference is judged with (:class:`ReferenceTrust`): the
        model in use ``trust_memory`` s ago, and, while a channel is not tracked, the one it was
        found not tracked with (for at most ``trust_hold`` s)."""
        cfg = self.config
        snaps = self._snapshots
        if not snaps or t - snaps[-1][0] >= 1.0 - 1e-9:
            snaps.append((t, np.array(theta, float), np.array(coupling, float)))
        while len(snaps) > 1 and snaps[1][0] <= t - cfg.trust_memory + 1e-9:
            snaps.popleft()
        _, old_theta, old_coupling = snaps[0]
        theta_j, coupling_j = old_theta.copy(), old_coupling.copy()
        for c in range(4):
            frozen = self._frozen[c]
            if frozen is not None and t - frozen[0] > cfg.trust_hold:
                self._frozen[c] = frozen = None  # judged long enough with it: look again
            source = (old_theta, old_coupling) if frozen is None else frozen[1:]
            for k, block in enumerate(BLOCKS):
                if block.reference == c:
                    theta_j[BLOCK_SLICES[k]] = source[0][BLOCK_SLICES[k]]
            if c < 2:
                coupling_j[c] = source[1][c]
        key = theta_j.tobytes() + coupling_j.tobytes()
        if key != self._judge_key:
            self._judge_key = key
            self._judge = discretise(theta_j, coupling_j, self.step)
        return self._judge, (theta_j, coupling_j)

    def _update_trust_steps(self, t: float, theta: np.ndarray, coupling: np.ndarray):
        """The hindsight replay of :class:`ReferenceTrust` over the last ``trust_horizon``. As
        steps (see :func:`run`): the replay is a request."""
        (ad, bd), judging = self._judging_model(t, theta, coupling)
        if COMPILED:
            hist = self.history
            held = hist.held
            miss_ref, miss_free = np.empty(4), np.empty(4)
            if not kernels_models.trust_replay(
                hist.t[held], hist.estimate[held], hist.measured[held], hist.logged[held], t,
                self.step, self.config.trust_horizon, ad, bd, miss_ref, miss_free,
            ):  # fmt: skip
                return
            self._judged(t, miss_ref, miss_free, judging)
            return
        horizon = self.config.trust_horizon
        n = max(1, round(horizon / self.step))
        t_then = t - n * self.step
        hist = self.history
        held_t = hist.ordered('t')
        if not len(held_t) or held_t[0] > t_then + 1e-9:
            return
        times = t_then + self.step * np.arange(n)
        refs = hist.at(times, 'logged', [0, 1, 2, 3])
        x = hist.at(np.array([t_then]), 'estimate', list(range(12)))[0]
        then = hist.at(np.array([t_then]), 'measured', list(range(12)))[0]
        now = hist.at(np.array([t]), 'measured', list(range(12)))[0]
        if not (np.isfinite(refs).all() and np.isfinite(x).all() and np.isfinite(now).all()):
            return
        x = (yield Propagation(ad, bd, x, refs))[-1]
        miss_ref = np.abs(x[CHANNEL_STATE] - now[CHANNEL_STATE])
        free = then[CHANNEL_STATE] + n * self.step * then[CHANNEL_RATE]
        miss_free = np.abs(free - now[CHANNEL_STATE])
        self._judged(t, miss_ref, miss_free, judging)

    def _judged(self, t: float, miss_ref: np.ndarray, miss_free: np.ndarray,
                judging: tuple) -> None:  # fmt: skip
        """Take the replay's misses into the trust; a channel found not tracked keeps being
        judged with the model ``judging`` that found it."""
        was = self.trust.followed.copy()
        self.trust.update(t, miss_ref, miss_free)
        for c in np.flatnonzero(was & ~self.trust.followed):
            self._frozen[c] = (t, *judging)  # keep judging with the model that found it
        for c in np.flatnonzero(self.trust.followed):
            self._frozen[c] = None

    # ------------------------------------------------------------------- predictions

    def reference_path_steps(self, t: float, zeta: np.ndarray, plan: np.ndarray | None):
        """The references (K, 4) over the steps of the next prediction from ``t`` (their starts):
        ``plan`` (K, 4) when given, else the intent (or the reference held, without intent);
        untracked channels take the virtual reference of ``zeta``, held. Also returns the intent
        candidates (M, K, 4) (None with a plan). As steps (see :func:`run`)."""
        hist = self.history
        idx = hist.last(self.config.intent_window + 0.5)
        logged = hist.logged[idx]
        candidates = None
        if plan is not None:
            path = np.array(plan, float)
        elif self.config.intent and len(logged) >= 2:
            candidates = yield from self.intent.candidates_steps(hist.t[idx], logged)
            w = yield from self.intent_scores.weights_steps()  # (K, M)
            path = np.einsum('km,mkc->kc', w, candidates)
            self.intent_scores.add(t, candidates[:, :, POSITION_CHANNELS])
        else:
            path = np.broadcast_to(logged[-1], (len(self.starts), 4)).copy()
        untracked = ~self.trust.followed
        if untracked.any():
            path[:, untracked] = self.virtual.of(zeta)[untracked]
        return path, candidates

    def combine_steps(self, t: float, model_positions: np.ndarray, measured: np.ndarray,
                      coupling: np.ndarray, center: tuple | None = None):  # fmt: skip
        """The published prediction (an :class:`Anticipation`) from ``t``: the candidates (the
        closed loop's ``model_positions`` (K, 3) and the reference-free ones from the
        ``measured`` state) combined by the guard, within the physical envelope about ``center``
        (the estimated position and velocity; default: the measured ones), with the radius. As
        steps (see :func:`run`)."""
        cfg = self.config
        hist = self.history
        paths = np.empty((len(CANDIDATES) + 1, len(self.poses), 3))
        recent = hist.measured[hist.last(cfg.centroid_window)]
        if COMPILED:
            kernels_combine.candidate_paths(measured, coupling, self.poses, recent,
                                            model_positions, paths)  # fmt: skip
        else:
            paths[0] = model_positions
            paths[1] = turn_positions(measured, coupling, self.poses)
            paths[2] = measured[POSITION] + np.outer(self.poses, measured[VELOCITY])
            paths[3] = measured[POSITION]
            paths[4] = (recent[:, POSITION].mean(axis=0) if len(recent)
                        else measured[POSITION])  # fmt: skip
        trust = self.trust.status()
        allowed = np.ones(len(CANDIDATES), dtype=bool)
        if self.trust.grounded:
            # commanded to the ground: it stops where it lands, neither where the model (with
            # a reference it does not follow) nor where its recent path would take it
            allowed[[CANDIDATES.index('model'), CANDIDATES.index('centroid')]] = False
        if cfg.guard:
            w = yield from self._weights_steps(allowed)
        else:
            w = np.zeros((len(self.poses), len(CANDIDATES)))
            w[:, 0 if allowed[0] else CANDIDATES.index('hold')] = 1.0
        p0, v0 = (measured[POSITION], measured[VELOCITY]) if center is None else center
        if COMPILED:
            scales, radius = np.empty(len(self.poses)), np.empty(len(self.poses))
            kernels_combine.publish(w, paths, p0, v0, self.poses, cfg.max_speed,
                                    cfg.max_acceleration, allowed, scales)  # fmt: skip
            published = paths[-1]
            r = self.radius
            kernels_combine.coverage_radii(r._errors, r._count, r.level, r.prior, r.offsets,
                                           r.min_errors, scales, radius)  # fmt: skip
        else:
            published = np.einsum('km,mkd->kd', w, paths[:-1])
            published = clip_to_envelope(p0, v0, self.poses, published,
                                         cfg.max_speed, cfg.max_acceleration)  # fmt: skip
            paths[-1] = published
            # the scale of the errors: how much the candidates disagree, plus a floor
            gap = paths[:-1][allowed] - published
            spread = np.sqrt(np.mean(np.sum(gap**2, axis=-1), axis=0))
            scales = spread + SCALE_FLOOR + SCALE_GROWTH * self.poses
            radius = self.radius.radii(scales)
        if not self.trust.grounded:
            # a vehicle at rest is predicted by every candidate alike: the guard and the radius
            # learn from flight only
            slot = self.guard.add(t, paths)
            self._radii[slot] = radius
            self._scales[slot] = scales
        return Anticipation(published, radius, w, trust)

    def _weights_steps(self, allowed: np.ndarray):
        """Guard weights over the candidates (the published path is scored, not weighted)."""
        m = len(CANDIDATES)
        g = self.guard
        if not g.scored.any():
            w = np.zeros((len(self.poses), m))
            w[:, int(np.flatnonzero(allowed)[0])] = 1.0
            return w
        if COMPILED:
            return compiled_weights(g, m, allowed)
        cross = g.expected_cross()[:, :m, :m]
        return (yield SimplexWeights(cross, allowed))
