"""``cloe_iv``: the CLOE-SM observer with an identifier that converges, and a bounded gain L.

The observer is CLOE-SM's (docs/method.md), semi-implicit in ``L e``::

    zeta_hat' = A(Theta_m, c_m) zeta_hat + B(Theta_m) r + L e + Lambda |e|^p sign(e)

but the model it runs on, ``(Theta_m, c_m)``, is the identifier's *usable* model: per block the
latest estimate that was stable and at least converging (see
:meth:`~cloe_ros.core.identifier.IvIdentifier._update_model`), so a transiently wrong estimate
never destabilises the observer. The identifier is the filtered
recursive instrumental-variable one of :mod:`cloe_ros.core.identifier`, fed with the measurements
and the reference; its estimate ``Theta_hat`` is what is published.

The gain L adapts as in the paper, plus leakage (sigma-modification) and a cap, so it stays
bounded under persistent disturbance and noise::

    l_i' = gamma_i e_i^2 - sigma (l_i - l_min),   l_min <= l_i <= l_max

What the model misses on the rows it does not know (wrong or not yet identified parameters,
disturbances) is estimated as an extended state ``d`` per unknown row and added to the drift,
``d' = gamma_d e_last - sigma d``, the classical disturbance-observer augmentation: on a real
flight, where the model stays approximate, it keeps the estimated rates within 0.2 rad/s of the
measurements instead of 0.9 rad/s (B2 flight, ``cloe infer``).

The floor ``l_min`` keeps the observer tied to the measurements while the model is still wrong
(with the paper's L(0) = 0 and leakage, L would settle where the model error makes it, and the
estimate would lag full-state measurements by centimetres).

Identification pauses while the commanded altitude is at or below ``ground_altitude``: a vehicle
told to stay on (or go to) the ground does not follow the closed-loop model, and recorded flights
often end with a zero setpoint under a vehicle parked elsewhere. (The measured altitude is no
guide: a landed vehicle's tracking marker sits a few centimetres up, and a simulated vehicle may
fly at ground level.)
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cloe_ros.core import kernels
from cloe_ros.core.estimator import KNOWN_A, KNOWN_C, EstimatorConfig, StepBuffers
from cloe_ros.core.identifier import ROW_CHANNEL, IvIdentifier
from cloe_ros.core.model import (
    BLOCK_STARTS,
    COUPLED_BLOCKS,
    N_STATES,
    PAPER_COUPLING,
    REGRESSOR_INDEX,
    UNKNOWN_ROWS,
    check_shape,
)
from cloe_ros.core.rows import Rows

_COUPLED_ROWS = np.array([b.states[1] for b in COUPLED_BLOCKS], dtype=np.intp)
_COUPLED_COLS = np.array([b.states[2] for b in COUPLED_BLOCKS], dtype=np.intp)


def _shared(config: EstimatorConfig) -> EstimatorConfig:
    """The settings vehicles in one estimator share (all but where each one starts)."""
    return replace(config, theta_initial=None)


class CloeIvEstimator(Rows):
    """CLOE-SM observer + IV identifier for N vehicles (same interface as ``CloeEstimator``).

    Args:
        config: ``algorithm='cloe_iv'``; ``sm_gains``, ``sm_exponents``, ``gamma_l``,
            ``l_initial``, ``l_leak``, ``l_max`` and ``identifier`` are used.
        zeta0: First measurement (N, 12) or (12,).
        r0: First reference (N, 4) or (4,).
        h: Step, s (the identifier's filters are discretised for it).
        n_vehicles: Number of vehicles when ``zeta0`` is (12,).

    Vehicles started apart (each its own ``theta_initial``) can share one estimator
    (:mod:`cloe_ros.core.rows`) when the rest of their settings is the same.
    """

    ROW_FIELDS = ('zeta_hat', 'gain_l', 'lambda_', 'exponents', 'flying', 'model_error')
    ROW_PARTS = ('identifier',)

    def __init__(
        self,
        config: EstimatorConfig,
        zeta0: np.ndarray,
        r0: np.ndarray,
        h: float,
        n_vehicles: int | None = None,
    ) -> None:
        zeta0 = np.asarray(zeta0, dtype=float)
        r0 = np.asarray(r0, dtype=float)
        check_shape('zeta0', zeta0, (N_STATES,))
        n = zeta0.shape[0] if zeta0.ndim == 2 else (n_vehicles or 1)
        self.config = config
        self.h = float(h)
        self.zeta_hat = np.array(np.broadcast_to(zeta0, (n, N_STATES)), order='C')
        r0 = np.array(np.broadcast_to(r0, (n, 4)))
        self.identifier = IvIdentifier(
            config.identifier,
            h,
            self.zeta_hat,
            r0,
            None if config.theta_initial is None else np.asarray(config.theta_initial),
        )
        self.gain_l = np.full((n, N_STATES), max(float(config.l_initial), config.l_min))
        self.lambda_ = np.tile(np.asarray(config.sm_gains, dtype=float), (n, 1))
        self.exponents = np.tile(np.asarray(config.sm_exponents, dtype=float), (n, 1))
        self._allocate_work(n)
        self.flying = np.ones(n, dtype=bool)
        self.model_error = np.zeros((n, len(UNKNOWN_ROWS)))

    def shares_settings(self, other: Rows) -> bool:
        return (
            isinstance(other, CloeIvEstimator)
            and other.h == self.h
            and _shared(other.config) == _shared(self.config)
        )

    def _allocate_work(self, n: int) -> None:
        self.buffers = StepBuffers.allocate(n)

    @property
    def theta_hat(self) -> np.ndarray:
        """The identifier's estimate (N, 16)."""
        return self.identifier.theta

    @property
    def coupling(self) -> np.ndarray:
        """Identified tilt couplings ``[c_x, c_y]`` (N, 2) (paper: ``+g``, ``-g``)."""
        return self.identifier.coupling

    @property
    def model(self) -> tuple[np.ndarray, np.ndarray]:
        """The model the observer and the predictions use: ``(theta (N, 16), c (N, 2))``, the
        identifier's usable model (stable, from rows at least converging)."""
        return self.identifier.model_theta, self.identifier.model_coupling

    @property
    def n_vehicles(self) -> int:
        return self.zeta_hat.shape[0]

    @property
    def error(self) -> np.ndarray:
        return self.buffers.e

    def step(
        self, zeta: np.ndarray, r: np.ndarray, h: float, tracked: np.ndarray | None = None
    ) -> None:
        """Advance ``h`` s (the constructor's step) to the measurement ``zeta`` (N, 12) with the
        reference ``r`` (N, 4) of the same time. Where ``tracked`` (N, 4) is False, that
        channel's reference is not one the vehicle follows: its rows are not identified."""
        if abs(h - self.h) > 1e-12:
            msg = f'cloe_iv runs at a fixed step of {self.h} s, got {h}'
            raise ValueError(msg)
        cfg, buf = self.config, self.buffers
        theta_m, coupling_m = self.model
        # the observer (one compiled call): the identified tilt couplings replace +-g in the
        # velocity rows; what the model misses on the rows it does not know is an extended
        # state (see the module doc); the bounded adaptive gain
        # l' = gamma e^2 - sigma (l - l_min), clipped to [l_min, l_max]
        kernels.iv_observer(
            np.ascontiguousarray(zeta, dtype=float), self.zeta_hat, theta_m, coupling_m,
            np.ascontiguousarray(r, dtype=float), self.model_error, self.gain_l, self.lambda_,
            self.exponents, float(h), cfg.gamma_d, cfg.l_leak, cfg.gamma_l, cfg.l_min, cfg.l_max,
            _COUPLED_ROWS, _COUPLED_COLS, PAPER_COUPLING, UNKNOWN_ROWS, KNOWN_C, KNOWN_A,
            REGRESSOR_INDEX, BLOCK_STARTS, buf.e, buf.w, buf.phi, buf.grad, buf.rows, buf.f,
        )  # fmt: skip
        # identify only while commanded to fly: on the ground the closed-loop model does not hold
        self.flying = r[:, 3] > cfg.ground_altitude
        active = self.flying
        if tracked is not None and not np.all(tracked):
            active = self.flying[:, None] & np.asarray(tracked, dtype=bool)[:, ROW_CHANNEL]
        self.identifier.step(zeta, r, active)
