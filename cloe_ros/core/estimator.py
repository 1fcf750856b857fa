"""CLOE and CLOE-SM estimator-identifiers (paper §4-5, docs/method.md), batched over N vehicles.

With ``e = zeta - zeta_hat`` (measured minus estimated), for every vehicle::

    zeta_hat' = A(Theta_hat) zeta_hat + B(Theta_hat) r + L e + Lambda |e|^p sign(e)    (observer)
    Theta_b'  = Gamma e_last(b) [zeta_hat_b ; r_b]                                  (identifier)
    l_i'      = gamma_i e_i^2                                                       (adaptive gain)

CLOE is ``Lambda = 0``; CLOE-SM uses the exponents 3/4, 1/2, 1/4, 0 along the 4-chains and 1/2, 0
along the 2-chains with the gains of the paper's Table 1. Explicit Euler diverges at <= 100 Hz once
L grows, so the ``L e`` term is taken implicitly (element-wise)::

    zeta_hat+ = (zeta_hat + h (f + L zeta)) / (1 + h L)
    f = A zeta_hat + B r + Lambda |e|^p sign(e)

and ``Theta_hat`` and ``L`` take an explicit Euler step with the error before the update.

Arrays carry a leading vehicle axis; one vehicle is the case N = 1. :func:`cloe_step` is the pure
step on caller-owned arrays; :class:`CloeEstimator` owns the state and the work buffers, so
stepping allocates nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cloe_ros.core import kernels
from cloe_ros.core.identifier import IdentifierConfig
from cloe_ros.core.model import (
    A_KNOWN,
    BLOCK_STARTS,
    BLOCKS,
    N_PARAMS,
    N_REFERENCES,
    N_STATES,
    PAPER_COUPLING,
    PARAM_ROW,
    REGRESSOR_INDEX,
    UNKNOWN_ROWS,
    check_shape,
)
from cloe_ros.core.rows import Rows
from cloe_ros.errors import ConfigError
from cloe_ros.settings import (  # noqa: F401 (ALGORITHMS and the SM_* tables: re-exported)
    ALGORITHMS,
    SM_EXPONENTS,
    SM_GAINS_TABLE1,
    check_fields,
    default,
)

# ALGORITHMS (the paper's two, and CLOE-SM with the IV identifier of cloe_ros.core.cloe_iv), the
# sliding-mode gains of the paper's Table 1 and the exponents, per state, are settings:
# cloe_ros.settings holds them (and every other setting's default and range).


@dataclass(frozen=True)
class EstimatorConfig:
    """Gains and initial values of one vehicle's estimator.

    Attributes:
        algorithm: ``'cloe'`` (no sliding-mode term), ``'cloe_sm'`` (both exactly as the paper) or
            ``'cloe_iv'`` (CLOE-SM observer with the IV identifier and a bounded L).
        gamma_theta: Identifier gain Gamma (paper: 400), 1/s per unit regressor.
        gamma_l: Adaptive-gain rate gamma_i of ``l_i' = gamma_i e_i^2`` (paper: 400).
        l_initial: Initial observer gain L(0), 1/s, the same on every state.
        theta_initial: Initial parameters (16,), or ``None`` for zeros (paper).
        sm_gains: Sliding-mode gains alpha per state (12,), used by ``cloe_sm``.
        sm_exponents: Sliding-mode exponents p per state (12,), 0 <= p < 1.
        l_leak: ``cloe_iv`` only: leakage sigma of ``l' = gamma e^2 - sigma (l - l_min)``, 1/s.
        gamma_d: ``cloe_iv`` only: rate of the observer's model-error state on the unknown rows,
            ``d' = gamma_d e_last - sigma d`` (1/s^2).
        l_min: ``cloe_iv`` only: lower bound of L, 1/s.
        l_max: ``cloe_iv`` only: upper bound of L, 1/s.
        identifier: ``cloe_iv`` only: settings of the IV identifier.
        ground_altitude: ``cloe_iv`` only: while the commanded altitude is at or below this (m)
            the vehicle counts as landed and identification pauses (negative: never).

    """

    algorithm: str = default('algorithm')
    gamma_theta: float = default('gamma_theta')
    gamma_l: float = default('gamma_l')
    l_initial: float = default('l_initial')
    theta_initial: tuple[float, ...] | None = None
    sm_gains: tuple[float, ...] = field(default=default('sm_gains'))
    sm_exponents: tuple[float, ...] = field(default=default('sm_exponents'))
    l_leak: float = default('l_leak')
    gamma_d: float = default('gamma_d')
    l_min: float = default('l_min')
    l_max: float = default('l_max')
    identifier: IdentifierConfig = field(default_factory=IdentifierConfig)
    ground_altitude: float = default('ground_altitude')

    def __post_init__(self) -> None:
        check_fields(self, 'estimator')  # defaults, ranges and choices: cloe_ros.settings
        if self.l_min > self.l_max:
            reason = f'must be at most l_max ({self.l_max:g}), got {self.l_min!r}'
            raise ConfigError(reason, 'l_min')
        if self.theta_initial is not None and len(self.theta_initial) != N_PARAMS:
            msg = f'theta_initial needs {N_PARAMS} entries, got {len(self.theta_initial)}'
            raise ConfigError(msg)

    @property
    def lambda_(self) -> np.ndarray:
        """The sliding-mode gain vector Lambda (12,): zero for CLOE."""
        if self.algorithm == 'cloe':
            return np.zeros(N_STATES)
        return np.asarray(self.sm_gains, dtype=float)


@dataclass
class StepBuffers:
    """Work arrays for :func:`cloe_step`, allocated once for N vehicles."""

    e: np.ndarray
    w: np.ndarray
    phi: np.ndarray
    f: np.ndarray
    rows: np.ndarray
    tmp: np.ndarray
    grad: np.ndarray

    @classmethod
    def allocate(cls, n: int) -> StepBuffers:
        return cls(
            e=np.zeros((n, N_STATES)),
            w=np.zeros((n, N_STATES + N_REFERENCES)),
            phi=np.zeros((n, N_PARAMS)),
            f=np.zeros((n, N_STATES)),
            rows=np.zeros((n, len(BLOCKS))),
            tmp=np.zeros((n, N_STATES)),
            grad=np.zeros((n, N_PARAMS)),
        )


#: For each entry of Theta: the reference channel of its block.
PARAM_CHANNEL = np.array([b.reference for b in BLOCKS for _ in range(b.n_params)], dtype=np.intp)


def _known_gathers() -> tuple[np.ndarray, np.ndarray]:
    """The known dynamics :data:`A_KNOWN` as one product per row: the state each row reads and
    its coefficient (0 where a row is unknown). With one term, ``A0 zeta_hat`` is that product
    whatever the order of the matrix product's sum."""
    channels, coefficients = np.zeros(N_STATES, dtype=np.intp), np.zeros(N_STATES)
    for i in range(N_STATES):
        (used,) = np.nonzero(A_KNOWN[i])
        if len(used) > 1:
            raise ValueError('a known row of A reads more than one state')
        if len(used):
            channels[i], coefficients[i] = used[0], A_KNOWN[i, used[0]]
    return channels, coefficients


KNOWN_C, KNOWN_A = _known_gathers()


def cloe_step(
    zeta_hat: np.ndarray,
    theta_hat: np.ndarray,
    gain_l: np.ndarray,
    zeta: np.ndarray,
    r: np.ndarray,
    h: float,
    gamma_theta: np.ndarray,
    gamma_l: np.ndarray,
    lambda_: np.ndarray,
    exponents: np.ndarray,
    buf: StepBuffers,
    use_sm: bool = True,
    theta_gate: np.ndarray | None = None,
) -> None:
    """Advance N estimators by one step of ``h`` seconds, in place, in one compiled call
    (:func:`~cloe_ros.core.kernels.cloe_step`, the observer's step shared with cloe_iv).

    Args:
        zeta_hat: Estimated states (N, 12), updated.
        theta_hat: Identified parameters (N, 16), updated.
        gain_l: Observer gains L (N, 12), updated.
        zeta: Measured states at the end of the step (N, 12).
        r: References (N, 4) held over the step.
        h: Step, s.
        gamma_theta: Identifier gains (N, 16).
        gamma_l: Adaptive-gain rates (N, 12).
        lambda_: Sliding-mode gains (N, 12) (zero rows for CLOE).
        exponents: Sliding-mode exponents (N, 12).
        buf: Work arrays from :meth:`StepBuffers.allocate`.
        use_sm: Skip the sliding-mode term altogether (all ``lambda_`` zero).
        theta_gate: (N, 16) 1 where a parameter adapts, 0 where it is held (its block's
            reference is not tracked); None: all adapt.

    """
    kernels.cloe_step(
        zeta_hat, theta_hat, gain_l, np.ascontiguousarray(zeta, dtype=float),
        np.ascontiguousarray(r, dtype=float), float(h), gamma_theta, gamma_l, lambda_, use_sm,
        exponents, buf.grad if theta_gate is None else np.ascontiguousarray(theta_gate, float),
        theta_gate is not None,
        KNOWN_C, KNOWN_A, REGRESSOR_INDEX, BLOCK_STARTS, UNKNOWN_ROWS, PARAM_ROW, buf.e, buf.w,
        buf.phi, buf.grad, buf.rows, buf.f, buf.tmp,
    )  # fmt: skip


class CloeEstimator(Rows):
    """CLOE / CLOE-SM for N vehicles; holds the state and steps without allocating.

    Args:
        configs: One :class:`EstimatorConfig` per vehicle (a single config is used for all
            ``n_vehicles``).
        zeta0: Initial estimate (N, 12) or (12,); usually the first measurement.
        n_vehicles: Number of vehicles when ``configs`` is a single config.

    Estimators of the same algorithm can share one (:mod:`cloe_ros.core.rows`).
    """

    ROW_FIELDS = ('zeta_hat', 'theta_hat', 'gain_l', 'gamma_theta', 'gamma_l', 'lambda_',
                  'exponents')  # fmt: skip
    ROW_TUPLES = ('configs',)

    def __init__(
        self,
        configs: EstimatorConfig | Sequence[EstimatorConfig],
        zeta0: np.ndarray,
        n_vehicles: int | None = None,
    ) -> None:
        if isinstance(configs, EstimatorConfig):
            rows = np.shape(zeta0)[0] if np.ndim(zeta0) == 2 else 1
            configs = [configs] * (n_vehicles or rows)
        self.configs = tuple(configs)
        n = len(self.configs)
        zeta0 = np.asarray(zeta0, dtype=float)
        check_shape('zeta0', zeta0, (N_STATES,))
        self.zeta_hat = np.array(np.broadcast_to(zeta0, (n, N_STATES)), order='C')
        self.theta_hat = np.array(
            [
                c.theta_initial if c.theta_initial is not None else [0.0] * N_PARAMS
                for c in configs
            ],
            dtype=float,
        )
        self.gain_l = np.array([[c.l_initial] * N_STATES for c in configs], dtype=float)
        # full-width gains: broadcasting a column would make numpy buffer (allocate) per step
        self.gamma_theta = np.array([[c.gamma_theta] * N_PARAMS for c in configs], dtype=float)
        self.gamma_l = np.array([[c.gamma_l] * N_STATES for c in configs], dtype=float)
        self.lambda_ = np.array([c.lambda_ for c in configs], dtype=float)
        self.exponents = np.array([c.sm_exponents for c in configs], dtype=float)
        self.use_sm = bool(np.any(self.lambda_))
        self._allocate_work(n)

    def shares_settings(self, other: Rows) -> bool:
        return isinstance(other, CloeEstimator) and other.use_sm == self.use_sm

    def _allocate_work(self, n: int) -> None:
        self.buffers = StepBuffers.allocate(n)

    @property
    def n_vehicles(self) -> int:
        return self.zeta_hat.shape[0]

    def step(
        self, zeta: np.ndarray, r: np.ndarray, h: float, tracked: np.ndarray | None = None
    ) -> None:
        """Advance ``h`` s to the measurement ``zeta`` (N, 12) with the reference ``r`` (N, 4).
        Where ``tracked`` (N, 4) is False, the parameters of that channel's block are held."""
        gate = None
        if tracked is not None and not np.all(tracked):
            gate = np.asarray(tracked, dtype=float)[:, PARAM_CHANNEL]
        cloe_step(
            self.zeta_hat,
            self.theta_hat,
            self.gain_l,
            zeta,
            r,
            h,
            self.gamma_theta,
            self.gamma_l,
            self.lambda_,
            self.exponents,
            self.buffers,
            self.use_sm,
            gate,
        )

    @property
    def error(self) -> np.ndarray:
        """``e = zeta - zeta_hat`` (N, 12) as used in the last step (before its update)."""
        return self.buffers.e

    @property
    def coupling(self) -> np.ndarray:
        """The paper's model has the tilt couplings fixed at ``+g`` and ``-g`` (N, 2)."""
        return np.tile(PAPER_COUPLING, (self.n_vehicles, 1))

    @property
    def model(self) -> tuple[np.ndarray, np.ndarray]:
        """The model the observer runs on: ``(theta_hat, coupling)``."""
        return self.theta_hat, self.coupling
