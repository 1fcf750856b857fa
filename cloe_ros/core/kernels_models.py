"""Compiled kernels (numba) of the model runs of a prediction: the closed loop's propagation, the
recent reference-offset fit, and the reference trust's hindsight replay and statistics.

They replace, for one vehicle, :func:`~cloe_ros.core.model.propagate`,
:func:`~cloe_ros.core.prediction.fit_reference_offsets` (and the checks of
:func:`~cloe_ros.core.prediction.fit_reference_offset_steps` before it), the arithmetic of
:meth:`~cloe_ros.core.anticipation.Anticipator._update_trust_steps` once its judging model is
known, and the statistics of :meth:`~cloe_ros.core.anticipation.ReferenceTrust.update`. In numpy
each was dozens to hundreds of calls on arrays of a few dozen entries.

Each kernel gives the numpy code's values bit for bit (under the golden test's pinned kernels;
test/core/test_kernels_models.py checks it on random and recorded arguments), because it does
the same floating-point operations in the same order:

* every product numpy hands to BLAS is made by :func:`cloe_ros.core.blas.matmul` on the 2-D
  operands numpy's stacked matmul passes per model, with their strides (so the same routine:
  ``gemv`` for a matrix times a column or a row times a matrix, ``gemm`` otherwise), and the
  solve by :func:`cloe_ros.core.blas.solve` (``dgesv``);
* the offset fit's sensitivities ``G_j = Ad G_{j-1} + Bd`` (``G_0 = 0``) depend only on the
  number of steps ``j`` a run has made, so each is made once (the numpy code makes ``G_j`` again
  for every run, with the same operands: the same bits);
* its two ``einsum`` (``'viab,viac->vbc'`` and ``'viab,via->vb'``) add their products one by
  one from zero, fitted states outer and runs inner, and the sum is then added to the running
  total. That is the order of numpy's loops on these operands: the fancy-indexed ``gk`` and
  ``err`` hold the fitted-state axis outermost in memory (``gk``'s strides: run 32 B, state
  (k + 1) 32 B; ``err``'s: 8 B, (k + 1) 8 B), the iterator orders the axes by stride, and its
  inner loop runs along the output, one product added at a time. (On C-ordered operands the
  order would be runs outer: not numpy's here, off in the last bit on dense models.)
* the rest is element-wise IEEE arithmetic written in the numpy expressions' order and grouping
  (numba fuses no multiply-adds without ``fastmath``).

The kernels that call BLAS are defined only where :data:`cloe_ros.core.blas.AVAILABLE`
(:data:`AVAILABLE` says so); elsewhere the package runs its numpy code.
"""

from __future__ import annotations

import numpy as np

from cloe_ros.core import blas, kernels
from cloe_ros.core.kernels import Compiler

_compiled = Compiler(__name__, 'cloe_ros.core.kernels_models')

#: Whether the kernels that call BLAS and LAPACK are defined.
AVAILABLE = blas.AVAILABLE

_A1, _A2 = 'float64[:]', 'float64[:, :]'  # (any strides)

#: State index of each reference channel's position (or yaw), and of its rate: the offset fit's
#: ``FIT_STATES`` and the trust's ``CHANNEL_STATE``, ``CHANNEL_RATE``.
_CHANNEL_STATE = np.array([0, 4, 8, 10], dtype=np.intp)
_CHANNEL_RATE = np.array([1, 5, 9, 11], dtype=np.intp)


@_compiled(f'boolean({_A1}, {_A1}, boolean[:], {_A1}, {_A1}, float64, float64, float64)')
def trust_update(e_ref, e_free, followed, miss_ref, miss_free, a, ratio2, floor2):
    """The statistics of :meth:`~cloe_ros.core.anticipation.ReferenceTrust.update` once its
    weight ``a`` (``1 - exp(-dt / trust_time)``) is known, in place: the squared misses
    ``miss_ref``, ``miss_free`` (4,) (m, rad for yaw) averaged into ``e_ref``, ``e_free`` (4,)
    (a NaN statistic takes the new value), then ``followed`` (4,) set False where ``e_ref >
    ratio2 e_free`` and ``e_ref > floor2``, True where ``e_ref <= ratio2 e_free`` or ``e_ref <
    floor2 / 4``, else kept (``ratio2``, ``floor2``: ``trust_ratio**2``, ``trust_floor**2``).
    Returns whether every channel is followed (``all_followed``)."""
    for c in range(4):
        new = miss_ref[c] * miss_ref[c]  # (numpy's ** 2 is a product)
        if np.isnan(e_ref[c]):
            e_ref[c] = new
        else:
            e_ref[c] = e_ref[c] + a * (new - e_ref[c])
    for c in range(4):
        new = miss_free[c] * miss_free[c]
        if np.isnan(e_free[c]):
            e_free[c] = new
        else:
            e_free[c] = e_free[c] + a * (new - e_free[c])
    quarter = floor2 / 4.0
    every = True
    for c in range(4):
        scaled = ratio2 * e_free[c]
        if e_ref[c] > scaled and e_ref[c] > floor2:
            followed[c] = False
        elif e_ref[c] <= scaled or e_ref[c] < quarter:
            followed[c] = True
        every = every and followed[c]
    return every


if blas.AVAILABLE:

    @_compiled(f'void({_A2}, {_A2}, {_A1}, {_A2}, {_A2})')
    def propagate_one(ad, bd, x0, refs, out):
        """``out`` (n, 12) = ``propagate(ad[None], bd[None], x0[None], refs[None])[0]``
        (:func:`~cloe_ros.core.model.propagate`): the states of ``x_{k+1} = Ad x_k + Bd r_k``
        from ``x0`` (12,) over the references ``refs`` (n, 4), with ``ad`` (12, 12), ``bd``
        (12, 4). Each step is numpy's ``ad @ x + bd @ r``: two ``gemv`` (a matrix times a
        column of unit stride, into a contiguous column), then the sum."""
        n_states = ad.shape[0]
        x = np.empty((n_states, 1))
        ax = np.empty((n_states, 1))
        br = np.empty((n_states, 1))
        for i in range(n_states):
            x[i, 0] = x0[i]
        for k in range(refs.shape[0]):
            blas.matmul(ad, x, ax)
            blas.matmul(bd, refs[k : k + 1].T, br)  # (a column of unit stride, as r[:, k])
            for i in range(n_states):
                x[i, 0] = ax[i, 0] + br[i, 0]
                out[k, i] = x[i, 0]

    @_compiled.helper
    def fit_offset_one(ad, bd, states, refs, ridge, out):
        """``out`` (4,) = ``fit_reference_offsets(ad[None], bd[None], states[None],
        refs[None], ridge)[0]`` (:func:`~cloe_ros.core.prediction.fit_reference_offsets`):
        the reference offset with which the model ``ad`` (12, 12), ``bd`` (12, 4) best
        reproduces x, y, yaw and z of ``states`` (M + 1, 12), run from every sample with the
        references ``refs`` (M + 1, 4); ``ridge`` (m^2, rad^2). Returns LAPACK's ``info`` of
        the 4 x 4 solve: non-zero where numpy raises ``LinAlgError`` (a singular system; then
        ``out`` holds LAPACK's partial result). The caller checks the window first (see
        :func:`recent_offset_one`).

        The products are numpy's per model: ``x[:k+1] @ ad.T`` (``gemm``, ``gemv`` for one
        run), ``refs[k] @ bd.T`` (``gemv``), ``ad @ G`` (``gemm``); the ``einsum`` sums add
        their products from zero, fitted states outer and runs inner."""
        m = states.shape[0] - 1
        n_states, n_refs = bd.shape
        x = np.empty((max(m, 1), n_states))  # run i, at step k, is at sample k + 1
        for i in range(m):
            for j in range(n_states):
                x[i, j] = states[i, j]
        tmp = np.empty((max(m, 1), n_states))
        row = np.empty((1, n_states))
        g = np.zeros((m + 1, n_states, n_refs))  # g[j]: G_j, after j steps (G_0 = 0)
        prod = np.empty((n_states, n_refs))
        err = np.empty((max(m, 1), n_refs))
        lhs = np.empty((n_refs, n_refs))
        rhs = np.zeros((n_refs, 1))
        for b in range(n_refs):
            for c in range(n_refs):
                lhs[b, c] = ridge * (1.0 if b == c else 0.0)  # (ridge * np.eye)
        ad_t, bd_t = ad.T, bd.T
        fit = _CHANNEL_STATE
        for k in range(m):
            blas.matmul(x[: k + 1], ad_t, tmp[: k + 1])
            blas.matmul(refs[k : k + 1], bd_t, row)
            for i in range(k + 1):
                for j in range(n_states):
                    x[i, j] = tmp[i, j] + row[0, j]
            blas.matmul(ad, g[k], prod)  # G_{k+1}: run i takes G_{k-i} to G_{k-i+1}
            for i in range(n_states):
                for j in range(n_refs):
                    g[k + 1, i, j] = prod[i, j] + bd[i, j]
            for i in range(k + 1):
                for a in range(n_refs):
                    err[i, a] = states[k + 1, fit[a]] - x[i, fit[a]]
            for b in range(n_refs):
                for c in range(n_refs):
                    s = 0.0  # einsum('viab,viac->vbc'): states outer, runs inner, from 0
                    for a in range(n_refs):
                        for i in range(k + 1):
                            gi = g[k + 1 - i]
                            s = s + gi[fit[a], b] * gi[fit[a], c]
                    lhs[b, c] = lhs[b, c] + s
                s = 0.0  # einsum('viab,via->vb'), in the same order
                for a in range(n_refs):
                    for i in range(k + 1):
                        s = s + g[k + 1 - i, fit[a], b] * err[i, a]
                rhs[b, 0] = rhs[b, 0] + s
        solution = np.empty((n_refs, 1))
        info = blas.solve(lhs, rhs, solution, np.empty((n_refs, n_refs)),
                          np.empty((1, n_refs)), np.empty(n_refs, np.int64))  # fmt: skip
        for b in range(n_refs):
            out[b] = solution[b, 0]
        return info

    @_compiled(f'int64({_A2}, {_A2}, {_A2}, {_A2}, float64, {_A1})')
    def recent_offset_one(ad, bd, states, refs, ridge, out):
        """``out`` (4,) = ``run(fit_reference_offset_steps(ad, bd, states, refs, ridge))``
        (:func:`~cloe_ros.core.prediction.fit_reference_offset`): zeros for a window of fewer
        than two samples or with a non-finite state or reference, else
        :func:`fit_offset_one` (whose ``info`` it returns; 0 for the zeros)."""
        finite = states.shape[0] >= 2
        for i in range(states.shape[0]):
            for j in range(states.shape[1]):
                finite = finite and np.isfinite(states[i, j])
            for j in range(refs.shape[1]):
                finite = finite and np.isfinite(refs[i, j])
        if not finite:
            out[:] = 0.0
            return 0
        return fit_offset_one(ad, bd, states, refs, ridge, out)

    @_compiled(f'int64(float64[::1], {_A2}, {_A2}, {_A2}, float64, float64, float64, {_A2},'
               f' {_A2}, {_A1}, {_A1})')  # fmt: skip
    def trust_replay(held_t, estimate, measured, logged, t, step, horizon, ad, bd, miss_ref,
                     miss_free):  # fmt: skip
        """The misses of :meth:`~cloe_ros.core.anticipation.Anticipator._update_trust_steps`
        with the judging model ``ad`` (12, 12), ``bd`` (12, 4): the history's held rows (times
        ``held_t`` (T,) s, increasing; ``estimate``, ``measured`` (T, 12), ``logged`` (T, 4)),
        interpolated as :meth:`~cloe_ros.core.anticipation.History.at` does; the model run
        (:func:`propagate_one`) over the last ``n = max(1, round(horizon / step))`` steps of
        ``step`` s before ``t`` from the estimate of then, with the logged references.
        Returns 0 where the method returns early (no history as old as then; a non-finite
        reference, estimate of then or measurement of now), else 1 with ``miss_ref`` (4,) the
        replay's miss of where the vehicle is at ``t`` and ``miss_free`` (4,) constant
        velocity's from the measurement of then (m, rad for yaw)."""
        n = max(1, round(horizon / step))
        t_then = t - n * step
        if held_t.shape[0] == 0 or held_t[0] > t_then + 1e-9:
            return 0
        n_states = estimate.shape[1]
        times = np.empty(n)
        for k in range(n):
            times[k] = t_then + step * k
        refs = np.empty((n, logged.shape[1]))
        kernels.interpolate(held_t, logged, times, np.arange(logged.shape[1]), refs)
        one = np.empty(1)
        one[0] = t_then
        every = np.arange(n_states)
        x = np.empty((1, n_states))
        then = np.empty((1, n_states))
        now = np.empty((1, n_states))
        kernels.interpolate(held_t, estimate, one, every, x)
        kernels.interpolate(held_t, measured, one, every, then)
        one[0] = t
        kernels.interpolate(held_t, measured, one, every, now)
        for k in range(n):
            for c in range(refs.shape[1]):
                if not np.isfinite(refs[k, c]):
                    return 0
        for i in range(n_states):
            if not (np.isfinite(x[0, i]) and np.isfinite(now[0, i])):
                return 0
        run = np.empty((n, n_states))
        propagate_one(ad, bd, x[0], refs, run)
        span = n * step
        for c in range(4):
            s, v = _CHANNEL_STATE[c], _CHANNEL_RATE[c]
            miss_ref[c] = abs(run[n - 1, s] - now[0, s])
            miss_free[c] = abs(then[0, s] + span * then[0, v] - now[0, s])
        return 1
