"""Anticipation: integrate an identified closed loop ahead of the current estimate (DESIGN §4).

``zeta' = A(Theta, c) zeta + B(Theta) r`` from ``zeta_hat(t)`` over the horizon, with the reference
held at its latest value, or following a plan of future references when one is known. The model is
discretised exactly (``expm`` of the augmented system over the output step) and cached, so a
prediction costs one small matrix product per output pose.

Guard: a model with an unstable block is never extrapolated (:class:`Predictor` returns ``None``);
the caller says so instead of publishing nonsense.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from cloe_ros.core.model import BLOCKS, N_REFERENCES, N_STATES, system_matrices, unstable_blocks
from cloe_ros.errors import ConfigError

NS = 1_000_000_000


@dataclass(frozen=True)
class PredictionConfig:
    """Attributes:
    horizon: How far ahead, s (0 disables predictions).
    step: Spacing of the predicted poses, s.
    rate: Predictions per second of message time, Hz.
    """

    horizon: float = 5.0
    step: float = 0.1
    rate: float = 5.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.horizon) and 0.0 <= self.horizon <= 120.0):
            msg = f'prediction horizon must be within [0, 120] s, got {self.horizon!r}'
            raise ConfigError(msg)
        if not (np.isfinite(self.step) and 0.001 <= self.step <= 10.0):
            msg = f'prediction step must be within [0.001, 10] s, got {self.step!r}'
            raise ConfigError(msg)
        if self.horizon and self.step > self.horizon:
            msg = f'prediction step ({self.step:g} s) exceeds the horizon ({self.horizon:g} s)'
            raise ConfigError(msg)
        if not (np.isfinite(self.rate) and 0.01 <= self.rate <= 1000.0):
            msg = f'prediction rate must be within [0.01, 1000] Hz, got {self.rate!r}'
            raise ConfigError(msg)

    @property
    def enabled(self) -> bool:
        return self.horizon > 0.0

    @property
    def n_poses(self) -> int:
        return int(np.floor(self.horizon / self.step + 1e-9))


class Predictor:
    """Predicts states on ``t + k step`` (k = 1..n) for one vehicle; caches the discretisation."""

    def __init__(self, config: PredictionConfig) -> None:
        self.config = config
        self._key: bytes | None = None
        self._ad = np.eye(N_STATES)
        self._bd = np.zeros((N_STATES, N_REFERENCES))
        self._stable = False
        self._gains_key: bytes | None = None
        self._gains = np.ones(N_REFERENCES)

    def _discretise(self, theta: np.ndarray, coupling: np.ndarray) -> bool:
        key = np.concatenate([theta, coupling]).tobytes()
        if key != self._key:
            self._key = key
            self._stable = not unstable_blocks(theta, coupling)
            a, b = system_matrices(theta, coupling)
            m = np.zeros((N_STATES + N_REFERENCES, N_STATES + N_REFERENCES))
            m[:N_STATES, :N_STATES], m[:N_STATES, N_STATES:] = a, b
            e = expm(m * self.config.step)
            self._ad, self._bd = e[:N_STATES, :N_STATES], e[:N_STATES, N_STATES:]
        return self._stable

    def static_gains(self, theta: np.ndarray, coupling: np.ndarray) -> np.ndarray:
        """Steady-state position (yaw) per unit reference, for each reference channel (4,)."""
        key = np.concatenate([theta, coupling]).tobytes()
        if key != self._gains_key:
            a, b = system_matrices(np.asarray(theta, float), np.asarray(coupling, float))
            gains = np.ones(N_REFERENCES)
            for block in BLOCKS:
                idx = np.array(block.states)
                try:
                    x_ss = -np.linalg.solve(a[np.ix_(idx, idx)], b[idx, block.reference])
                    gains[block.reference] = x_ss[0]
                except np.linalg.LinAlgError:
                    gains[block.reference] = np.nan
            self._gains_key, self._gains = key, gains
        return self._gains

    def predict(
        self,
        zeta0: np.ndarray,
        theta: np.ndarray,
        coupling: np.ndarray,
        r_now: np.ndarray,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray | None:
        """States (n, 12) at ``t + step, ..., t + n step``; None if the model is unstable.

        Args:
            zeta0: Current estimate (12,).
            theta: Parameters (16,).
            coupling: Tilt couplings (2,).
            r_now: Current reference (4,), held over the horizon when there is no plan.
            plan: Future references: times relative to now (K,) s, increasing, and values
                (K, 4); over each step the plan's latest value at or before its start is held, the
                current reference before the plan's first time, its last value after its end.

        """
        if not self._discretise(np.asarray(theta, float), np.asarray(coupling, float)):
            return None
        n = self.config.n_poses
        refs = np.broadcast_to(r_now, (n, N_REFERENCES)).copy()
        if plan is not None and len(plan[0]):
            times, values = plan
            starts = self.config.step * np.arange(n)
            idx = np.searchsorted(times, starts + 1e-9, side='right') - 1
            have = idx >= 0
            refs[have] = values[idx[have]]
        out = np.empty((n, N_STATES))
        x = np.asarray(zeta0, dtype=float)
        for k in range(n):
            x = self._ad @ x + self._bd @ refs[k]
            out[k] = x
        return out


def constant_velocity(zeta: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Baseline: positions (len(dt), 3) extrapolated with the current world velocity."""
    p = zeta[[0, 4, 10]]
    v = zeta[[1, 5, 11]]
    return p + np.outer(dt, v)


def hold_position(zeta: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Baseline: the current position at every future time (len(dt), 3)."""
    return np.broadcast_to(zeta[[0, 4, 10]], (len(dt), 3)).copy()
