"""Anticipation: integrate an identified closed loop ahead of the current estimate.

(docs/identifier.md, "Anticipation".)

``zeta' = A(Theta, c) zeta + B(Theta) r`` from ``zeta_hat(t)`` over the horizon, with the reference
held at its latest value, or following a plan of future references when one is known. The model is
discretised exactly (``expm`` of the augmented system over the output step) and cached, so a
prediction costs one small matrix product per output pose.

Model error as a reference offset: a real vehicle does not follow the identified model exactly
(an unmodelled force, a controller's integrator, a setpoint logged late). Over a short horizon
that error acts like a constant offset on the reference, which :func:`fit_reference_offset`
estimates from the last ``disturbance_time`` seconds of estimates: the offset with which the model
best reproduces them. The caller adds it to the reference, fading over the horizon (see
``VehicleEngine._predict``).

Guard: a model with an unstable block is never extrapolated (:class:`Predictor` returns ``None``);
the caller says so instead of publishing nonsense.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cloe_ros.core import kernels_models
from cloe_ros.core.anticipation import COMPILED, Propagation, run, stack_fields
from cloe_ros.core.model import (
    BLOCKS,
    N_REFERENCES,
    N_STATES,
    discretise,
    system_matrices,
    unstable_blocks,
)
from cloe_ros.errors import ConfigError
from cloe_ros.settings import check_fields, default

NS = 1_000_000_000


@dataclass(frozen=True)
class PredictionConfig:
    """Attributes:
    horizon: How far ahead, s (0 disables predictions).
    step: Spacing of the predicted poses, s.
    rate: Predictions per second of message time, Hz.
    disturbance_time: Window of the recent-offset fit and time constant of its fading over the
        horizon, s (0: only steady-state offsets).
    phase: ``'aligned'``: a vehicle predicts when its estimate enters a new ``1 / rate`` period
        of message time, all vehicles on the same steps; ``'spread'``: the periods of each
        vehicle are shifted by a whole number of grid steps drawn from its namespace
        (:func:`~cloe_ros.core.engine.prediction_offset_ns`).
    """

    horizon: float = default('prediction_horizon')
    step: float = default('prediction_step')
    rate: float = default('prediction_rate')
    disturbance_time: float = default('prediction_disturbance_time')
    phase: str = default('prediction_phase')

    def __post_init__(self) -> None:
        check_fields(self, 'prediction')  # defaults and ranges: cloe_ros.settings
        if self.horizon and self.step > self.horizon:
            reason = f'must be at most prediction_horizon ({self.horizon:g}), got {self.step!r}'
            raise ConfigError(reason, 'prediction_step')

    @property
    def enabled(self) -> bool:
        return self.horizon > 0.0

    @functools.cached_property
    def n_poses(self) -> int:
        """Poses per prediction (asked for at every prediction: computed once, the config is
        frozen)."""
        return int(np.floor(self.horizon / self.step + 1e-9))


class Predictor:
    """Predicts states on ``t + k step`` (k = 1..n) for one vehicle; caches the discretisation."""

    def __init__(self, config: PredictionConfig) -> None:
        self.config = config
        self._key: bytes | None = None
        self._unstable: list[str] = []
        self._stable = False
        # (ad, bd) of the current model per step: the predictions' step, and the recent-offset
        # fit's, which is the same one whenever the rate is a multiple of 1 / step
        self._discrete: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._gains: np.ndarray | None = None  # static gains of the current model, once asked

    def _discretise(
        self, theta: np.ndarray, coupling: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The model's exact discretisation over ``dt`` (cached for the current model)."""
        self._use_model(theta, coupling)
        if dt not in self._discrete:
            self._discrete[dt] = discretise(theta, coupling, dt)
        return self._discrete[dt]

    def _use_model(self, theta: np.ndarray, coupling: np.ndarray) -> None:
        """Make ``(theta, coupling)`` the cached model (nothing to do if it is already)."""
        key = theta.tobytes() + coupling.tobytes()
        if key != self._key:
            self._key = key
            self._unstable = unstable_blocks(theta, coupling)
            self._stable = not self._unstable
            self._discrete.clear()
            self._gains = None

    def unstable_blocks(self, theta: np.ndarray, coupling: np.ndarray) -> list[str]:
        """:func:`~cloe_ros.core.model.unstable_blocks` of the model (cached for the current
        model: it changes far less often than a prediction is made)."""
        self._use_model(np.asarray(theta, float), np.asarray(coupling, float))
        return list(self._unstable)

    def discretisation(
        self, theta: np.ndarray, coupling: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The model's exact discretisation over the prediction step (cached)."""
        return self._discretise(np.asarray(theta, float), np.asarray(coupling, float),
                                self.config.step)  # fmt: skip

    def recent_offset_steps(
        self, theta: np.ndarray, coupling: np.ndarray, states: np.ndarray, refs: np.ndarray,
        dt: float,
    ):  # fmt: skip
        """:func:`fit_reference_offset` with this model, for states sampled every ``dt`` s; as
        steps (:func:`~cloe_ros.core.anticipation.run`): the fit is a request."""
        ad, bd = self._discretise(np.asarray(theta, float), np.asarray(coupling, float), dt)
        return (yield from fit_reference_offset_steps(ad, bd, states, refs))

    def static_gains(self, theta: np.ndarray, coupling: np.ndarray) -> np.ndarray:
        """Steady-state position (yaw) per unit reference, for each reference channel (4,)."""
        theta, coupling = np.asarray(theta, float), np.asarray(coupling, float)
        self._use_model(theta, coupling)
        if self._gains is None:
            a, b = system_matrices(theta, coupling)
            gains = np.ones(N_REFERENCES)
            for block in BLOCKS:
                idx = np.array(block.states)
                try:
                    x_ss = -np.linalg.solve(a[np.ix_(idx, idx)], b[idx, block.reference])
                    gains[block.reference] = x_ss[0]
                except np.linalg.LinAlgError:
                    gains[block.reference] = np.nan
            self._gains = gains
        return self._gains

    def predict(self, *args, **kwargs) -> np.ndarray | None:
        """:meth:`predict_steps` run at once (the arguments are its)."""
        return run(self.predict_steps(*args, **kwargs))

    def predict_steps(
        self,
        zeta0: np.ndarray,
        theta: np.ndarray,
        coupling: np.ndarray,
        r_now: np.ndarray,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
        offsets: np.ndarray | None = None,
    ):
        """States (n, 12) at ``t + step, ..., t + n step``; None if the model is unstable. As
        steps (:func:`~cloe_ros.core.anticipation.run`): the model's run is a request.

        Args:
            zeta0: Current estimate (12,).
            theta: Parameters (16,).
            coupling: Tilt couplings (2,).
            r_now: Current reference (4,), held over the horizon when there is no plan.
            plan: Future references: times relative to now (K,) s, increasing, and values
                (K, 4); over each step the plan's latest value at or before its start is held, the
                current reference before the plan's first time, its last value after its end.
            offsets: Added to the reference over each step (n, 4), e.g. a fading model-error
                offset.

        """
        ad, bd = self._discretise(np.asarray(theta, float), np.asarray(coupling, float),
                                  self.config.step)  # fmt: skip
        if not self._stable:
            return None
        n = self.config.n_poses
        refs = plan_references(r_now, plan, self.config.step * np.arange(n))
        if offsets is not None:
            refs += offsets
        if COMPILED:
            out = np.empty((n, N_STATES))
            kernels_models.propagate_one(ad, bd, np.asarray(zeta0, dtype=float), refs, out)
            return out
        return (yield Propagation(ad, bd, np.asarray(zeta0, dtype=float), refs))


def plan_references(
    r_now: np.ndarray, plan: tuple[np.ndarray, np.ndarray] | None, starts: np.ndarray
) -> np.ndarray:
    """The references (len(starts), 4) held over prediction steps starting at ``starts`` s from
    now: the latest planned value at or before each start (``plan``: times (K,) s relative to
    now, increasing, and values (K, 4)), ``r_now`` before the plan's first time."""
    refs = np.broadcast_to(np.asarray(r_now, float), (len(starts), N_REFERENCES)).copy()
    if plan is not None and len(plan[0]):
        times, values = plan
        idx = np.searchsorted(times, starts + 1e-9, side='right') - 1
        have = idx >= 0
        refs[have] = values[idx[have]]
    return refs


#: Outputs the offset is fitted on: x, y, yaw, z.
FIT_STATES = [0, 4, 8, 10]


def fit_reference_offset(
    ad: np.ndarray, bd: np.ndarray, states: np.ndarray, refs: np.ndarray, ridge: float = 1e-3
) -> np.ndarray:
    """The constant reference offset ``b`` (4,) with which the discrete model ``(ad, bd)`` best
    reproduces recent states.

    ``states`` (M + 1, 12) are sampled every step of the model, oldest first, and ``refs``
    (M + 1, 4) the references held over the step that follows each. From every sample the model
    is run to the last one with ``refs + b``; ``b`` minimises the squared errors of x, y, yaw and
    z over all those runs. The runs are affine in ``b`` (``x_k = x_k^0 + G_k b``), so this is a
    4 x 4 least-squares problem; ``ridge`` (m^2, rad^2) keeps an offset the window does not
    determine at zero. Zeros if the window has fewer than two samples or is not finite.
    """
    return run(fit_reference_offset_steps(ad, bd, states, refs, ridge))


def fit_reference_offset_steps(
    ad: np.ndarray, bd: np.ndarray, states: np.ndarray, refs: np.ndarray, ridge: float = 1e-3
):
    """:func:`fit_reference_offset` as steps (:func:`~cloe_ros.core.anticipation.run`): the fit
    is a request (:class:`OffsetFit`)."""
    if COMPILED:  # (its own checks: zeros for too short or a non-finite window)
        out = np.empty(N_REFERENCES)
        if kernels_models.recent_offset_one(ad, bd, states, refs, ridge, out):
            raise np.linalg.LinAlgError('the offset fit failed (singular matrix)')
        return out
    if len(states) < 2 or not (np.isfinite(states).all() and np.isfinite(refs).all()):
        return np.zeros(N_REFERENCES)
    return (yield OffsetFit(ad, bd, states, refs, ridge))


@dataclass(frozen=True)
class OffsetFit:
    """A request for :func:`fit_reference_offsets` of one model and window."""

    ad: np.ndarray
    bd: np.ndarray
    states: np.ndarray
    refs: np.ndarray
    ridge: float

    def key(self) -> tuple:
        return ('offset', self.states.shape, self.ridge)

    @classmethod
    def answer_all(cls, requests: list) -> list:
        fields = stack_fields(requests, ('ad', 'bd', 'states', 'refs'))
        return list(fit_reference_offsets(*fields, requests[0].ridge))


def fit_reference_offsets(
    ad: np.ndarray, bd: np.ndarray, states: np.ndarray, refs: np.ndarray, ridge: float
) -> np.ndarray:
    """:func:`fit_reference_offset` of V models and windows at once (V, 4), of finite windows
    of two samples or more: ``ad`` (V, 12, 12), ``bd`` (V, 12, 4), ``states`` (V, M + 1, 12),
    ``refs`` (V, M + 1, 4). The stacked products and solves take each model in a call of its
    own (BLAS, LAPACK), so each gets bitwise its fit alone."""
    v, m = states.shape[0], states.shape[1] - 1
    lhs = np.broadcast_to(ridge * np.eye(N_REFERENCES), (v, N_REFERENCES, N_REFERENCES)).copy()
    rhs = np.zeros((v, N_REFERENCES))
    x = states[:, :-1].copy()  # every run at once: run i starts at sample i
    g = np.zeros((v, m, N_STATES, N_REFERENCES))
    ad_t, bd_t = np.swapaxes(ad, 1, 2), np.swapaxes(bd, 1, 2)
    for k in range(m):
        # step k takes runs 0..k from sample k to sample k + 1
        x[:, : k + 1] = x[:, : k + 1] @ ad_t + refs[:, k, None, :] @ bd_t
        g[:, : k + 1] = ad[:, None] @ g[:, : k + 1] + bd[:, None]
        gk = g[:, : k + 1][:, :, FIT_STATES]  # (V, k + 1, 4, 4)
        err = states[:, k + 1][:, None, FIT_STATES] - x[:, : k + 1, FIT_STATES]
        lhs += np.einsum('viab,viac->vbc', gk, gk)
        rhs += np.einsum('viab,via->vb', gk, err)
    return np.linalg.solve(lhs, rhs[..., None])[..., 0]
