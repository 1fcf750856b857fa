"""The estimator's own error statistics: a causal, running estimate of the covariance of the
estimation error ``zeta_hat - zeta``, per state, and its REP-105 form for ``cloe/state``.

What is observed at every step ``k`` is the output error ``e = z - zeta_hat`` (measured minus
estimated), where the measurement ``z = zeta + n`` carries white noise ``n`` of variance ``R``.
With the estimation error ``eps = zeta_hat - zeta``, ``e = n - eps``, so per state

    E[e^2] = R - 2 C + P,    P = E[eps^2],    C = E[n eps]

(second moments about zero, so a bias of the estimate counts as error). Without measurement noise
``P = E[e^2]``: the output error *is* the estimation error. With noise, ``E[e^2]`` also holds the
noise (``R``) and misses what of it the estimator passed into its estimate (``C``). Both are
measured from the data, at high frequency, where a flying vehicle's motion is smooth and the
noise is not:

* ``R`` from the third difference of the measurement, ``d3 z_k = z_k - 3 z_k-1 + 3 z_k-2 -
  z_k-3``: the motion cancels to ``h^3`` times its third derivative, white noise gives
  ``E[(d3 n)^2] = 20 R``;
* ``C`` from the third differences of measurement and estimate together. An estimator that takes
  a fraction ``g`` of the new measurement's noise and then forgets it by ``rho`` per step
  (``eps_k = sum_j g rho^j n_k-j + ...``) gives ``E[d3 z d3 zeta_hat] = g R f(rho)`` with
  ``f(rho) = 19 - 12 rho + 3 rho^2 - (rho - 1)^3`` (10 at ``rho = 1``, 20 at ``rho = 0``), and
  ``C = g R``. The observer's own forgetting is ``rho = 1 / (1 + h L)`` (its implicit ``L e``
  step, :mod:`cloe_ros.core.estimator`), taken from the gains ``L`` of that step. Whatever of the
  observer takes the measurement in besides ``L`` (the sliding-mode terms, ``cloe_iv``'s
  model-error state) is measured as well: ``g`` is not assumed, only the forgetting.

so ``P = E[e^2] - R + 2 C``, bounded below by ``C^2 / R`` (Cauchy-Schwarz: ``C^2 <= R P``) and
by ``FLOOR``. The moments are exponentially weighted means with time constant ``time_constant``
(a running mean over the first ``time_constant``, so the first samples count fully). Until
``warmup`` s of steps have been seen since the start or a :meth:`ErrorCovariance.reset`, the
variance is the conservative prior ``PRIOR_SIGMA`` (0.5 m, 0.5 m/s, 0.1 rad, 1 rad/s), far larger
than the errors of any estimate that tracks its measurement. Every value is finite and positive.

Calibration (``cloe evaluate sim``, docs/covariance.md): the fraction of true errors inside the
2-sigma interval / ellipsoid is close to the Gaussian 95.4 % (1-D) and 73.9 % (3-D), with and
without noise.
"""

from __future__ import annotations

import math

import numpy as np

from cloe_ros.core.kinematics import euler_to_rotation
from cloe_ros.core.model import N_STATES

#: Conservative standard deviations before enough statistics, per state of ``zeta``: position
#: 0.5 m, velocity 0.5 m/s, angle 0.1 rad, rate 1 rad/s.
PRIOR_SIGMA = np.array([0.5, 0.5, 0.1, 1.0, 0.5, 0.5, 0.1, 1.0, 0.1, 1.0, 0.5, 0.5])
#: The smallest variance reported (of any unit): the covariance stays positive-definite.
FLOOR = 1e-14
#: The largest (the estimator restarts long before): every value stays finite.
CEILING = 1e12
#: Exponentially weighted time constant of the moments, s.
TIME_CONSTANT = 2.0
#: Steps' worth of time, s, after which the statistics replace the prior.
WARMUP = 1.0
#: Third-difference weights (newest first) and ``E[(d3 n)^2] / R`` for white noise.
D3 = np.array([1.0, -3.0, 3.0, -1.0])
D3_NOISE = float(D3 @ D3)  # 20
#: The layout of :class:`ErrorCovariance`'s state vector: E[e^2], R, C, the variance, rho (12
#: each), the last four measurements and estimates (4 x 12 each, newest first).
_SM, _NOISE, _CROSS, _VAR, _RHO = (slice(12 * i, 12 * i + 12) for i in range(5))
_ZH = slice(60, 156)  # (2, 4, 12): measurements, estimates
_STATE_SIZE = 156


#: Whether the update runs compiled (:mod:`~cloe_ros.core.kernels_covariance`, bit for bit the
#: numpy code of :meth:`ErrorCovariance.update`): None until the first instance loads the
#: kernel (this module imports no numba itself; the kernel is loaded with the statistics, not at
#: their first update, which a message makes), then True, or False where numpy's OpenBLAS is not
#: found. False runs the numpy code (the tests set it to compare the two).
COMPILED: bool | None = None
_D3_ROW = D3.reshape(1, -1)
_KERNEL = None


def _kernel():
    """The compiled update (:func:`~cloe_ros.core.kernels_covariance.covariance_update`), or
    None where :data:`COMPILED` is False."""
    global COMPILED, _KERNEL
    if COMPILED is False:
        return None
    if _KERNEL is None:
        from cloe_ros.core import kernels_covariance

        COMPILED = kernels_covariance.AVAILABLE
        if not COMPILED:
            return None
        _KERNEL = kernels_covariance.covariance_update
    return _KERNEL


def forgetting_factor(rho: np.ndarray) -> np.ndarray:
    """``f(rho) = E[d3 z d3 zeta_hat] / (g R)`` for an estimate ``sum_j g rho^j n_k-j`` (module
    docstring): 10 at ``rho = 1``, 20 at ``rho = 0``."""
    rho = np.asarray(rho, dtype=float)
    return 20.0 + rho * (-15.0 + rho * (6.0 - rho))  # (expanded, by Horner)


def error_variance(
    second_moment: np.ndarray, noise: np.ndarray, cross: np.ndarray, rho: np.ndarray
) -> np.ndarray:
    """``P = E[e^2] - R + 2 C``, at most ``CEILING`` and at least ``FLOOR`` and two bounds (per
    state; the module docstring derives them): ``C^2 / R`` (Cauchy-Schwarz) and
    ``(1 - rho) / (1 + rho) R``, what the observer's ``L e`` term alone leaves of white noise in
    its estimate (gain ``1 - rho``, memory ``rho``)."""
    p = second_moment - noise + 2.0 * cross
    schwarz = np.divide(cross * cross, noise, out=np.zeros_like(noise), where=noise > 0.0)
    linear = (1.0 - rho) / (1.0 + rho) * noise
    np.maximum(p, schwarz, out=p)
    np.maximum(p, linear, out=p)
    np.maximum(p, FLOOR, out=p)
    return np.minimum(p, CEILING, out=p)


class ErrorCovariance:
    """Running variance of ``zeta_hat - zeta`` per state (12,), from what each step gives.

    Args:
        step: The estimator's step ``h``, s.
        time_constant: Time constant of the exponentially weighted moments, s.
        warmup: Time of steps, s, before which :attr:`variance` is the prior.
        prior_sigma: Standard deviations (12,) reported until then.

    """

    def __init__(
        self,
        step: float,
        time_constant: float = TIME_CONSTANT,
        warmup: float = WARMUP,
        prior_sigma: np.ndarray = PRIOR_SIGMA,
    ) -> None:
        if not (step > 0.0 and time_constant >= step and warmup >= 0.0):
            msg = f'need step > 0, time_constant >= step, warmup >= 0; got {step}, ' \
                f'{time_constant}, {warmup}'
            raise ValueError(msg)
        self.step = float(step)
        self.alpha = step / time_constant  # weight of a new sample once the mean is full
        self.warmup_steps = math.ceil(warmup / step - 1e-9)
        self.prior = np.asarray(prior_sigma, dtype=float) ** 2
        if self.prior.shape != (N_STATES,):
            msg = f'prior_sigma: expected ({N_STATES},) but found {self.prior.shape}'
            raise ValueError(msg)
        _kernel()  # (loaded now, so that no message waits on it)
        self.reset()

    def reset(self) -> None:
        """Back to the prior: the statistics start over (a reset estimator)."""
        # one vector per vehicle (see _SM ... _ZH): E[e^2], R, C, the variance, the forgetting
        # rho of the last full difference, and the last four measurements and estimates
        self._state = np.zeros(_STATE_SIZE)
        self._state[_VAR] = self.prior
        self._state[_RHO] = 1.0
        self.count = 0  # samples in second_moment
        self.count_d3 = 0  # samples in noise and cross
        self.restart()

    def restart(self) -> None:
        """A new estimator on new data (a time or position jump): the differences start over,
        the statistics are kept."""
        self._state[_ZH] = 0.0
        self._filled = 0  # of the last four measurements and estimates (newest first)

    second_moment = property(lambda self: self._state[_SM], doc='E[e^2] (12,)')
    noise = property(lambda self: self._state[_NOISE], doc='R (12,)')
    cross = property(lambda self: self._state[_CROSS], doc='C (12,)')
    variance = property(lambda self: self._state[_VAR], doc='E[(zeta_hat - zeta)^2] (12,)')

    def _weight(self, count: int) -> float:
        return max(1.0 / count, self.alpha)

    def update(self, measured: np.ndarray, zeta_hat: np.ndarray, gain_l: np.ndarray) -> np.ndarray:
        """Take one step's measurement and estimate (12,) and the observer gains ``L`` (12,) it
        stepped with; returns :attr:`variance` (12,), the estimated ``E[(zeta_hat - zeta)^2]``."""
        kernel = _kernel()
        if kernel is not None:
            counts = np.array([[self.count, self.count_d3, self._filled]], dtype=np.int64)
            kernel(self._state[None], counts, _row(measured), _row(zeta_hat), _row(gain_l),
                   _D3_ROW, self.step, self.alpha, self.warmup_steps, D3_NOISE, FLOOR,
                   CEILING)  # fmt: skip
            self.count, self.count_d3, self._filled = counts[0].tolist()
            return self._state[_VAR]
        st = self._state
        e = measured - zeta_hat
        self.count += 1
        second = st[_SM]
        second += self._weight(self.count) * (e * e - second)
        zh = st[_ZH].reshape(2, len(D3), N_STATES)
        zh[:, 1:] = zh[:, :-1]
        zh[0, 0], zh[1, 0] = measured, zeta_hat
        self._filled = min(self._filled + 1, len(D3))
        if self._filled == len(D3):
            d3z, d3h = _third_difference(zh)
            rho = 1.0 / (1.0 + self.step * np.maximum(gain_l, 0.0))
            self.count_d3 += 1
            w = self._weight(self.count_d3)
            noise, cross = st[_NOISE], st[_CROSS]
            noise += w * (d3z * d3z / D3_NOISE - noise)
            cross += w * (d3z * d3h / forgetting_factor(rho) - cross)
            st[_RHO] = rho
        if self.count >= self.warmup_steps and self.count_d3 > 0:
            st[_VAR] = error_variance(st[_SM], st[_NOISE], st[_CROSS], st[_RHO])
        return st[_VAR]

    def _settings(self) -> tuple:
        return self.step, self.alpha, self.warmup_steps, self.prior.tobytes()

    @staticmethod
    def update_many(
        covs: list[ErrorCovariance], measured: np.ndarray, zeta_hat: np.ndarray,
        gain_l: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        """:meth:`update` of several vehicles' statistics at once, with their measurements,
        estimates and gains (K, 12): the same values, as arrays over the vehicles (each
        object's state becomes a row of them). Returns the variances (K, 12)."""
        first = covs[0]
        if any(c._settings() != first._settings() for c in covs[1:]):
            return np.array([c.update(m, zh, g) for c, m, zh, g in
                             zip(covs, measured, zeta_hat, gain_l)])  # fmt: skip
        k, n = len(covs), len(D3)
        state = np.array([c._state for c in covs])  # (K, _STATE_SIZE)
        counts = np.array([(c.count, c.count_d3, c._filled) for c in covs], dtype=np.int64)
        kernel = _kernel()
        if kernel is not None:
            kernel(state, counts, np.asarray(measured, dtype=float),
                   np.asarray(zeta_hat, dtype=float), np.asarray(gain_l, dtype=float), _D3_ROW,
                   first.step, first.alpha, first.warmup_steps, D3_NOISE, FLOOR,
                   CEILING)  # fmt: skip
            for c, st, (count, count_d3, filled) in zip(covs, state, counts.tolist()):
                c._state, c.count, c.count_d3, c._filled = st, count, count_d3, filled
            return state[:, _VAR]
        count = counts[:, 0] + 1
        e = measured - zeta_hat
        second = state[:, _SM]
        second += _weights(count, first.alpha) * (e * e - second)
        zh = state[:, _ZH].reshape(k, 2, n, N_STATES)
        zh[:, :, 1:] = zh[:, :, :-1]
        zh[:, 0, 0], zh[:, 1, 0] = measured, zeta_hat
        filled = np.minimum(counts[:, 2] + 1, n)
        full = filled == n
        count_d3 = counts[:, 1] + full
        if full.any():
            d3 = _third_difference(zh)
            d3z, d3h = d3[:, 0], d3[:, 1]
            rho = 1.0 / (1.0 + first.step * np.maximum(gain_l, 0.0))
            w = _weights(np.maximum(count_d3, 1), first.alpha)
            noise, cross = state[:, _NOISE], state[:, _CROSS]
            new_noise = noise + w * (d3z * d3z / D3_NOISE - noise)
            new_cross = cross + w * (d3z * d3h / forgetting_factor(rho) - cross)
            if full.all():
                noise[:], cross[:], state[:, _RHO] = new_noise, new_cross, rho
            else:
                noise[full], cross[full] = new_noise[full], new_cross[full]
                state[full, _RHO] = rho[full]
        ready = (count >= first.warmup_steps) & (count_d3 > 0)
        if ready.any():
            variance = error_variance(state[:, _SM], state[:, _NOISE], state[:, _CROSS],
                                      state[:, _RHO])  # fmt: skip
            state[:, _VAR] = np.where(ready[:, None], variance, state[:, _VAR])
        for i, c in enumerate(covs):
            c._state = state[i]
            c.count, c.count_d3, c._filled = int(count[i]), int(count_d3[i]), int(filled[i])
        return state[:, _VAR]


def _row(x) -> np.ndarray:
    """``x`` (12,) as a float (1, 12) array."""
    return np.asarray(x, dtype=float).reshape(1, -1)


def _third_difference(x: np.ndarray) -> np.ndarray:
    """``D3 . x`` along the next-to-last axis (the last four samples, newest first):
    ``x0 - 3 x1 + 3 x2 - x3``, one product per (4, 12) block whatever the batch."""
    return D3 @ x


def _weights(count: np.ndarray, alpha: float) -> np.ndarray:
    """:meth:`ErrorCovariance._weight` per vehicle, (K, 1)."""
    return np.maximum(1.0 / count, alpha)[:, None]


# --------------------------------------------------------------- REP-105 (nav_msgs/Odometry)

#: Indices in ``zeta`` of position (x, y, z), attitude (roll, pitch, yaw), world velocity and
#: Euler rates (roll, pitch, yaw rates).
POSITION, ATTITUDE, VELOCITY, EULER_RATES = [0, 4, 10], [6, 2, 8], [1, 5, 11], [7, 3, 9]
_DIAGONAL = np.arange(3)


def body_jacobians(zeta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R^T, T)`` (..., 3, 3) at the state ``zeta`` (..., 12): body velocity ``= R^T v_world``
    and body rates ``= T [roll_rate, pitch_rate, yaw_rate]`` (ZYX, as
    :func:`~cloe_ros.core.kinematics.state_to_odometry`)."""
    zeta = np.asarray(zeta, dtype=float)
    roll, pitch, yaw = zeta[..., 6], zeta[..., 2], zeta[..., 8]
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    zero, one = np.zeros_like(roll), np.ones_like(roll)
    rot = euler_to_rotation(roll, pitch, yaw)
    rates = np.stack([
        np.stack([one, zero, -sp], -1),
        np.stack([zero, cr, cp * sr], -1),
        np.stack([zero, -sr, cp * cr], -1),
    ], -2)  # fmt: skip
    return np.swapaxes(rot, -1, -2), rates


def odometry_covariance(zeta_hat: np.ndarray, variance: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(pose, twist)`` covariances (..., 6, 6) of ``cloe/state`` from the per-state variances
    (..., 12) (:class:`ErrorCovariance`) at the estimate ``zeta_hat`` (..., 12), REP-105:

    * pose in the world frame, ``[x, y, z, roll, pitch, yaw]``: the variances of the position and
      of the Euler angles (about the fixed X, Y, Z axes for small angles), no cross terms;
    * twist in the body frame, ``[vx, vy, vz, p, q, r]``: the world-velocity variances rotated
      into the body, ``R^T diag R``, and the Euler-rate variances mapped to body rates,
      ``T diag T^T``.

    Symmetric positive-definite wherever the Euler rates are defined (pitch within +-90 deg).
    One state (12,) takes a path of scalar trigonometry and 3x3 products (each ``cloe/state``
    message is one); it equals the batched one to round-off."""
    variance = np.asarray(variance, dtype=float)
    if variance.ndim == 1:
        return _odometry_covariance_one(np.asarray(zeta_hat, dtype=float), variance)
    rt, t = body_jacobians(zeta_hat)
    shape = variance.shape[:-1]
    pose = np.zeros((*shape, 6, 6))
    twist = np.zeros((*shape, 6, 6))
    pose[..., _DIAGONAL, _DIAGONAL] = variance[..., POSITION]
    pose[..., _DIAGONAL + 3, _DIAGONAL + 3] = variance[..., ATTITUDE]
    linear = np.einsum('...ij,...j,...kj->...ik', rt, variance[..., VELOCITY], rt)
    angular = np.einsum('...ij,...j,...kj->...ik', t, variance[..., EULER_RATES], t)
    twist[..., :3, :3] = 0.5 * (linear + np.swapaxes(linear, -1, -2))
    twist[..., 3:, 3:] = 0.5 * (angular + np.swapaxes(angular, -1, -2))
    return pose, twist


def _odometry_covariance_one(zeta: np.ndarray, variance: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`odometry_covariance` of one state (12,), by scalar arithmetic in one compiled call
    (:func:`~cloe_ros.core.kernels.state_message`: ``R^T diag R`` and ``T diag T^T`` written
    out, each symmetric pair computed once)."""
    from cloe_ros.core import kernels  # (numba: imported by the paths that write states)

    out = np.empty(85)
    kernels.state_message(np.asarray(zeta, dtype=float), np.asarray(variance, dtype=float),
                          True, out)  # fmt: skip
    return out[7:43].reshape(6, 6).copy(), out[49:85].reshape(6, 6).copy()
