"""Performance metrics of the paper's §6.1.3 (docs/method.md, "Metrics").

Errors are ``e = zeta - zeta_hat`` sampled at times ``t``; arrays have time as their first axis and
the 12 states as their last (any axes in between, e.g. vehicles, are kept).
"""

from __future__ import annotations

import numpy as np

from cloe_ros.core.model import BLOCK_SLICES, BLOCKS, N_STATES, SUBSYSTEMS, check_shape


def rmse_norm(err: np.ndarray) -> np.ndarray:
    """RMSE of the error norm: ``sqrt(mean_t ||e(t)||^2)`` over the last axis (paper eq. 50)."""
    err = np.asarray(err, dtype=float)
    return np.sqrt(np.mean(np.sum(err * err, axis=-1), axis=0))


def subsystem_rmse(err: np.ndarray) -> dict[str, np.ndarray]:
    """RMSE of the error norm of each physical subsystem (position, velocity, angles, rates)."""
    err = np.asarray(err, dtype=float)
    check_shape('err', err, (N_STATES,))
    return {name: rmse_norm(err[..., list(idx)]) for name, idx in SUBSYSTEMS.items()}


def itae(t: np.ndarray, err: np.ndarray) -> np.ndarray:
    """``int t ||e(t)|| dt`` over the samples (trapezoidal rule), norm over the last axis.

    ``t`` is measured from the start of the run (the paper's time origin), s.
    """
    t = np.asarray(t, dtype=float)
    norm = np.linalg.norm(np.asarray(err, dtype=float), axis=-1)
    weight = t.reshape(t.shape + (1,) * (norm.ndim - 1))
    return np.trapezoid(weight * norm, t, axis=0)


def subsystem_itae(t: np.ndarray, err: np.ndarray) -> dict[str, np.ndarray]:
    """ITAE of each physical subsystem (paper Tables 3 and 5)."""
    err = np.asarray(err, dtype=float)
    check_shape('err', err, (N_STATES,))
    return {name: itae(t, err[..., list(idx)]) for name, idx in SUBSYSTEMS.items()}


def parameter_error(theta_hat: np.ndarray, theta_true: np.ndarray) -> dict[str, np.ndarray]:
    """Relative parameter error ``||Theta_hat_b - Theta_b|| / ||Theta_b||`` per block and overall.

    Returns a dict with one entry per block name and ``'all'``; values keep the leading axes of
    ``theta_hat`` (..., 16).
    """
    theta_hat = np.asarray(theta_hat, dtype=float)
    theta_true = np.asarray(theta_true, dtype=float)
    out = {}
    for block, sl in zip(BLOCKS, BLOCK_SLICES):
        diff = np.linalg.norm(theta_hat[..., sl] - theta_true[sl], axis=-1)
        out[block.name] = diff / np.linalg.norm(theta_true[sl])
    out['all'] = np.linalg.norm(theta_hat - theta_true, axis=-1) / np.linalg.norm(theta_true)
    return out
