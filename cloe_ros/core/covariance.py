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


def forgetting_factor(rho: np.ndarray) -> np.ndarray:
    """``f(rho) = E[d3 z d3 zeta_hat] / (g R)`` for an estimate ``sum_j g rho^j n_k-j`` (module
    docstring): 10 at ``rho = 1``, 20 at ``rho = 0``."""
    rho = np.asarray(rho, dtype=float)
    return 19.0 - 12.0 * rho + 3.0 * rho**2 - (rho - 1.0) ** 3


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
    return np.clip(np.maximum(p, np.maximum(schwarz, linear)), FLOOR, CEILING)


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
        self.reset()

    def reset(self) -> None:
        """Back to the prior: the statistics start over (a reset estimator)."""
        self.second_moment = np.zeros(N_STATES)  # E[e^2]
        self.noise = np.zeros(N_STATES)  # R
        self.cross = np.zeros(N_STATES)  # C
        self.count = 0  # samples in second_moment
        self.count_d3 = 0  # samples in noise and cross
        self.variance = self.prior.copy()
        self.restart()

    def restart(self) -> None:
        """A new estimator on new data (a time or position jump): the differences start over,
        the statistics are kept."""
        # the last four measurements and estimates, newest first (rows); _filled of them so far
        self._z = np.zeros((len(D3), N_STATES))
        self._zeta_hat = np.zeros((len(D3), N_STATES))
        self._filled = 0

    def _weight(self, count: int) -> float:
        return max(1.0 / count, self.alpha)

    def update(self, measured: np.ndarray, zeta_hat: np.ndarray, gain_l: np.ndarray) -> np.ndarray:
        """Take one step's measurement and estimate (12,) and the observer gains ``L`` (12,) it
        stepped with; returns :attr:`variance` (12,), the estimated ``E[(zeta_hat - zeta)^2]``."""
        e = measured - zeta_hat
        self.count += 1
        self.second_moment += self._weight(self.count) * (e * e - self.second_moment)
        z, h = self._z, self._zeta_hat
        z[1:] = z[:-1]
        h[1:] = h[:-1]
        z[0], h[0] = measured, zeta_hat
        self._filled = min(self._filled + 1, len(D3))
        if self._filled == len(D3):
            d3z, d3h = _third_difference(z), _third_difference(h)
            rho = 1.0 / (1.0 + self.step * np.maximum(gain_l, 0.0))
            self.count_d3 += 1
            w = self._weight(self.count_d3)
            self.noise += w * (d3z * d3z / D3_NOISE - self.noise)
            self.cross += w * (d3z * d3h / forgetting_factor(rho) - self.cross)
            self._rho = rho
        if self.count >= self.warmup_steps and self.count_d3 > 0:
            self.variance = error_variance(self.second_moment, self.noise, self.cross, self._rho)
        return self.variance

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
        n = len(D3)
        count = np.array([c.count for c in covs]) + 1
        e = measured - zeta_hat
        second = np.array([c.second_moment for c in covs])
        second += _weights(count, first.alpha) * (e * e - second)
        z = np.empty((len(covs), n, N_STATES))
        h = np.empty((len(covs), n, N_STATES))
        z[:, 1:] = [c._z[:-1] for c in covs]
        h[:, 1:] = [c._zeta_hat[:-1] for c in covs]
        z[:, 0], h[:, 0] = measured, zeta_hat
        filled = np.minimum(np.array([c._filled for c in covs]) + 1, n)
        full = filled == n
        noise = np.array([c.noise for c in covs])
        cross = np.array([c.cross for c in covs])
        count_d3 = np.array([c.count_d3 for c in covs]) + full
        rho = np.array([getattr(c, '_rho', np.ones(N_STATES)) for c in covs])
        variance = np.array([c.variance for c in covs])
        if full.any():
            d3z, d3h = _third_difference(z[full], axis=1), _third_difference(h[full], axis=1)
            rho_new = 1.0 / (1.0 + first.step * np.maximum(gain_l[full], 0.0))
            w = _weights(count_d3[full], first.alpha)
            noise[full] += w * (d3z * d3z / D3_NOISE - noise[full])
            cross[full] += w * (d3z * d3h / forgetting_factor(rho_new) - cross[full])
            rho[full] = rho_new
        ready = (count >= first.warmup_steps) & (count_d3 > 0)
        if ready.any():
            variance[ready] = error_variance(second[ready], noise[ready], cross[ready],
                                             rho[ready])  # fmt: skip
        for i, c in enumerate(covs):
            c.count, c.count_d3, c._filled = int(count[i]), int(count_d3[i]), int(filled[i])
            c.second_moment, c.noise, c.cross, c.variance = second[i], noise[i], cross[i], \
                variance[i]
            c._z, c._zeta_hat = z[i], h[i]
            if full[i] or hasattr(c, '_rho'):
                c._rho = rho[i]
        return variance


def _third_difference(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """``D3 . x`` along ``axis`` (newest first): ``x0 - 3 x1 + 3 x2 - x3``."""
    x0, x1, x2, x3 = np.moveaxis(x, axis, 0)
    return ((x0 - 3.0 * x1) + 3.0 * x2) - x3


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
    pose, twist = odometry_covariance_floats(zeta, variance)
    return np.array(pose).reshape(6, 6), np.array(twist).reshape(6, 6)


def odometry_covariance_floats(zeta, variance) -> tuple[list[float], list[float]]:
    """:func:`odometry_covariance` of one state (12,) as two row-major lists of 36 floats, by
    scalar arithmetic (each ``cloe/state`` message is one): ``R^T diag R`` and ``T diag T^T``
    written out, each symmetric pair computed once."""
    z = [float(c) for c in zeta]
    var = [float(c) for c in variance]
    cr, sr = math.cos(z[6]), math.sin(z[6])
    cp, sp = math.cos(z[2]), math.sin(z[2])
    cy, sy = math.cos(z[8]), math.sin(z[8])
    # R (world from body, ZYX) by rows; the world-velocity variances weigh its rows
    rot = ((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
           (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
           (-sp, cp * sr, cp * cr))  # fmt: skip
    v_world = (var[1], var[5], var[11])
    # T (body rates from Euler rates) by rows; the Euler-rate variances weigh its columns
    rates = ((1.0, 0.0, -sp), (0.0, cr, cp * sr), (0.0, -sr, cp * cr))
    v_euler = (var[7], var[3], var[9])
    pose = [0.0] * 36
    for k, value in enumerate((var[0], var[4], var[10], var[6], var[2], var[8])):
        pose[7 * k] = value
    twist = [0.0] * 36
    for i in range(3):
        for k in range(i, 3):
            linear = sum(rot[j][i] * v_world[j] * rot[j][k] for j in range(3))
            angular = sum(rates[i][j] * v_euler[j] * rates[k][j] for j in range(3))
            twist[6 * i + k] = twist[6 * k + i] = linear
            twist[6 * (i + 3) + k + 3] = twist[6 * (k + 3) + i + 3] = angular
    return pose, twist
