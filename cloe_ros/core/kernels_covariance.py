"""Compiled kernel (numba) of the estimator's error statistics' update
(:meth:`~cloe_ros.core.covariance.ErrorCovariance.update` and
:meth:`~cloe_ros.core.covariance.ErrorCovariance.update_many`).

In numpy the update is some twenty calls on arrays of twelve entries per step; compiled it is
one. :func:`covariance_update` gives the numpy code's values bit for bit (under the golden
test's pinned kernels; test/core/test_covariance.py compares the two on random steps): the
third differences ``D3 @ x`` are numpy's ``gemv`` of numpy's own OpenBLAS with the same
strides (:func:`cloe_ros.core.blas.matmul`), and the rest is element-wise IEEE arithmetic in
the numpy expressions' order and grouping, ``np.maximum`` and ``np.minimum`` keeping their
first argument where it is NaN.

Defined only where :data:`cloe_ros.core.blas.AVAILABLE` (:data:`AVAILABLE` says so); elsewhere
the package runs its numpy code.
"""

from __future__ import annotations

import numpy as np

from cloe_ros.core import blas, kernels
from cloe_ros.core.kernels import maximum

#: Whether the kernel is defined (numpy's OpenBLAS found: :data:`cloe_ros.core.blas.AVAILABLE`).
AVAILABLE = blas.AVAILABLE

_compiled = kernels.Compiler(__name__, 'cloe_ros.core.kernels_covariance')

if AVAILABLE:
    _F2 = 'float64[:, :]'

    @_compiled.helper
    def _weight(count, alpha):
        """``max(1.0 / count, alpha)``: the weight of a new sample in a running mean."""
        w = 1.0 / count
        return alpha if alpha > w else w

    _UPDATE = (
        # state (K, 156), counts (K, 3): count, count_d3, filled; measured, estimate, gains
        # (K, 12); D3 (1, 4); step, alpha, warm-up steps, E[(d3 n)^2] / R, floor, ceiling
        f'void(float64[:, ::1], int64[:, ::1], {_F2}, {_F2}, {_F2}, float64[:, ::1], float64,'
        ' float64, int64, float64, float64, float64)'
    )

    @_compiled(_UPDATE)
    def covariance_update(state, counts, measured, zeta_hat, gain_l, d3, step, alpha,
                          warmup_steps, d3_noise, floor, ceiling):  # fmt: skip
        """One step of each vehicle's error statistics (the rows of ``state`` and ``counts``,
        in place), as :meth:`~cloe_ros.core.covariance.ErrorCovariance.update` makes it:
        ``E[e^2]``; the last four measurements and estimates; once four are held, their third
        differences into ``R``, ``C`` and the forgetting ``rho``; after the warm-up, the
        variance ``P`` (see :func:`~cloe_ros.core.covariance.error_variance`)."""
        n = measured.shape[1]  # 12
        sm, noise, cross, var, rho_at, zh = 0, n, 2 * n, 3 * n, 4 * n, 5 * n
        depth = d3.shape[1]  # 4
        diffs = np.empty((1, n))
        for v in range(state.shape[0]):
            st = state[v]
            count = counts[v, 0] + 1
            w = _weight(count, alpha)
            for i in range(n):
                e = measured[v, i] - zeta_hat[v, i]
                st[sm + i] = st[sm + i] + w * (e * e - st[sm + i])
            # the last four measurements and estimates, newest first
            for a in range(2):
                base = zh + a * depth * n
                for j in range(depth - 1, 0, -1):
                    for i in range(n):
                        st[base + j * n + i] = st[base + (j - 1) * n + i]
            for i in range(n):
                st[zh + i] = measured[v, i]
                st[zh + depth * n + i] = zeta_hat[v, i]
            filled = min(counts[v, 2] + 1, depth)
            count_d3 = counts[v, 1]
            if filled == depth:
                held = st[zh:zh + 2 * depth * n].reshape(2, depth, n)
                count_d3 += 1
                wd = _weight(count_d3, alpha)
                blas.matmul(d3, held[0], diffs)
                dz = diffs.copy()
                blas.matmul(d3, held[1], diffs)
                for i in range(n):
                    rho = 1.0 / (1.0 + step * maximum(gain_l[v, i], 0.0))
                    f = 20.0 + rho * (-15.0 + rho * (6.0 - rho))
                    st[noise + i] = st[noise + i] + wd * (dz[0, i] * dz[0, i] / d3_noise
                                                          - st[noise + i])  # fmt: skip
                    st[cross + i] = st[cross + i] + wd * (dz[0, i] * diffs[0, i] / f
                                                          - st[cross + i])  # fmt: skip
                    st[rho_at + i] = rho
            if count >= warmup_steps and count_d3 > 0:
                for i in range(n):
                    r, c, rho = st[noise + i], st[cross + i], st[rho_at + i]
                    p = st[sm + i] - r + 2.0 * c
                    schwarz = c * c / r if r > 0.0 else 0.0
                    linear = (1.0 - rho) / (1.0 + rho) * r
                    p = maximum(maximum(maximum(p, schwarz), linear), floor)
                    st[var + i] = p if (p <= ceiling or p != p) else ceiling
            counts[v, 0], counts[v, 1], counts[v, 2] = count, count_d3, filled
