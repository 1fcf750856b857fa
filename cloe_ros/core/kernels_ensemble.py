"""Compiled kernels of the ensembles' weights and of the intent's candidate references.

Two per-vehicle parts of :mod:`cloe_ros.core.anticipation` that numpy ran as a few hundred
small calls per prediction, here one call each:

* :func:`ensemble_weights`: the weights an :class:`~cloe_ros.core.anticipation.Ensemble`
  gives (the guard's over the candidates, the intent's over its models): the expected error
  cross-products (:func:`expected_cross`) and the minimum-variance weights on the simplex
  (:func:`simplex_weights`, the active-set loop's solves by LAPACK's ``dgesv``);
* :func:`intent_candidates`: :meth:`~cloe_ros.core.anticipation.Intent.candidates_steps`
  (the last jump of the reference, the constant-velocity fit by ``dgelsd``, the subsampling
  and the harmonic fits, :func:`harmonic_fits`, by OpenBLAS's ``syrk`` and ``gemm`` and
  ``dgesv``).

Each gives bitwise the values of the numpy code it replaces (under the golden test's pinned
kernels; test/core/test_kernels_ensemble.py checks it on random and recorded inputs), because
it does the same floating-point operations in the same order:

* element-wise arithmetic is written in the numpy expression's order and grouping (numba fuses
  no multiply-adds); ``np.log``, ``np.cos``, ``np.sin`` and ``np.power`` with an array exponent
  are libm's ``log``, ``cos``, ``sin`` and ``pow`` in either (under the pin: unpinned, numpy's
  own SIMD versions may differ in the last bit);
* the products, solves and the least-squares fit are numpy's own OpenBLAS and LAPACK routines
  called with the arguments numpy passes (:mod:`cloe_ros.core.blas`); a stacked ``matmul`` or
  ``solve`` runs the 2-D routine once per matrix, and each horizon's (each frequency's) result
  depends on its own matrix only, so one vehicle's equals the batched answer;
* numpy's ``sum`` along an axis of fewer than eight entries adds them in order from the first
  (``((a0 + a1) + a2) + ...``, measured for every count of rows); a median is a value of the
  sorted data, whatever partition finds it; ``argmin`` is the first minimum (the first NaN if
  any); ``np.maximum(w, 0)`` gives +0 for -0 (measured), ``np.clip`` and ``np.maximum``
  propagate NaN; Python's ``max(a, b)`` is ``b if b > a else a`` and ``round`` is
  round-half-even (``np.rint``).

Where the numpy code raises, a kernel returns a status instead (:data:`LINALG_ERROR`,
:data:`INDEX_ERROR`, :data:`VALUE_ERROR`), for its caller to raise.
"""

from __future__ import annotations

import numpy as np

from cloe_ros.core import blas, kernels
from cloe_ros.core.kernels import Compiler

_compiled = Compiler(__name__, 'cloe_ros.core.kernels_ensemble')

#: Whether the kernels that call numpy's BLAS and LAPACK are defined (see
#: :data:`cloe_ros.core.blas.AVAILABLE`).
AVAILABLE = blas.AVAILABLE

#: The kernels' statuses: done; where numpy raises ``np.linalg.LinAlgError`` (a singular solve,
#: a least-squares fit that does not converge); ``IndexError`` (no candidate allowed, no sample);
#: ``ValueError`` (Python's ``round`` of a NaN; ``OverflowError`` or ``ZeroDivisionError`` there
#: too).
OK, LINALG_ERROR, INDEX_ERROR, VALUE_ERROR = 0, 1, 2, 3

#: The error cross-products' floors of :meth:`~cloe_ros.core.anticipation.Ensemble.
#: expected_cross`, the largest growth exponent and the one of a single scored horizon.
_MSE_FLOOR, _SD_FLOOR, _MAX_GROWTH, _DEFAULT_GROWTH = 1e-12, 1e-24, 4.0, 2.0
#: :func:`~cloe_ros.core.anticipation.simplex_weights`'s ridge, relative to 1 + the largest
#: diagonal entry; :func:`~cloe_ros.core.anticipation.harmonic_fits_batch`'s.
_SIMPLEX_RIDGE, _HARMONIC_RIDGE = 1e-12, 1e-9
#: :meth:`~cloe_ros.core.anticipation.Intent.candidates_steps`: the last jump's factor and floor
#: (:func:`~cloe_ros.core.anticipation.last_jump`'s defaults), the constant-velocity fit's span
#: (s) and the least number of its samples, the latest its first sample may be (s), the least
#: number of subsampled samples of the harmonic fits.
_JUMP_FACTOR, _JUMP_FLOOR = 10.0, 0.1
_LINEAR_SPAN, _LINEAR_SAMPLES, _LINEAR_FIRST, _HARMONIC_SAMPLES = 1.0, 5, -0.5, 10

_F1, _F2, _F3 = 'float64[::1]', 'float64[:, ::1]', 'float64[:, :, ::1]'


# ----------------------------------------------------------------------------- helpers


@_compiled.helper
def argmin(a):
    """``np.argmin(a)`` of a non-empty 1-D ``a`` (any stride): the first minimum, or the first
    NaN if there is one."""
    best = 0
    low = a[0]
    if np.isnan(low):
        return 0
    for i in range(1, a.shape[0]):
        x = a[i]
        if np.isnan(x):
            return i
        if x < low:
            low = x
            best = i
    return best


@_compiled.helper
def median(x):
    """:func:`~cloe_ros.core.anticipation.median` (``np.median``) of a 1-D ``x``: NaN if any
    entry is (or ``x`` is empty), else the middle entry of the sorted values, or the two middle
    ones' ``(a + b) / 2.0``."""
    n = x.shape[0]
    if n == 0:
        return np.nan
    for i in range(n):
        if np.isnan(x[i]):
            return np.nan
    k = n // 2
    p = np.partition(x, k)
    if n % 2:
        return p[k]
    below = p[0]  # the largest of the k smallest
    for i in range(1, k):
        if p[i] > below:
            below = p[i]
    return (below + p[k]) / 2.0


@_compiled.helper
def last_jump(r, factor, floor):
    """:func:`~cloe_ros.core.anticipation.last_jump` of the positions ``r`` (T, C), C < 8: the
    index just after the last step ``|r[i + 1] - r[i]|`` above ``max(floor, factor *
    median)`` of the steps (0 if none, or T < 3). The squared components are added in order
    (numpy's sum of fewer than eight)."""
    n, n_c = r.shape
    if n < 3:
        return 0
    d = np.empty(n - 1)
    for i in range(n - 1):
        e = r[i + 1, 0] - r[i, 0]
        s = e * e
        for c in range(1, n_c):
            e = r[i + 1, c] - r[i, c]
            s = s + e * e
        d[i] = np.sqrt(s)
    limit = factor * median(d)
    if not limit > floor:  # Python's max(floor, limit) (the floor where the median is NaN)
        limit = floor
    for i in range(n - 2, -1, -1):
        if d[i] > limit:
            return i + 1
    return 0


# ----------------------------------------------------------------------------- ensemble


@_compiled.helper
def expected_cross(cross, scored, offsets, min_growth, m, out):
    """``out`` (K, m, m) = :meth:`~cloe_ros.core.anticipation.Ensemble.expected_cross`
    ``[:, :m, :m]`` of an ensemble's error cross-products ``cross`` (K, M, M), m <= M, its
    scored horizons ``scored`` (K,), its pose offsets ``offsets`` (K,) s and its least growth
    exponents ``min_growth`` (M,): the horizons after the longest scored one extrapolated
    (each candidate's error grown like ``h^(alpha/2)`` from that horizon, ``alpha`` from the
    growth between it and the scored horizon near its half, clipped to [0, 4], at least
    ``min_growth``; the correlations of that horizon), the unscored ones before it copied from
    the next scored one. Each entry (i, j) depends on candidates i and j only, so the leading
    block is the full one's."""
    n_k = cross.shape[0]
    for k in range(n_k):
        for i in range(m):
            for j in range(m):
                out[k, i, j] = cross[k, i, j]
    last = -1
    for k in range(n_k):
        if scored[k]:
            last = k
    if last < 0:
        return
    if last + 1 < n_k:
        half = last
        if last > 0:  # the first scored horizon from (last + 1) // 2 - 1 on (searchsorted)
            half = (last + 1) // 2 - 1
            while not scored[half]:
                half += 1
        h_last, h_half = offsets[last], offsets[half]
        alpha = np.empty(m)
        sd_last = np.empty(m)
        sd = np.empty(m)
        for i in range(m):
            if last > half:
                ratio = (cross[last, i, i] + _MSE_FLOOR) / (cross[half, i, i] + _MSE_FLOOR)
                a = np.log(ratio) / np.log(h_last / h_half)
                if a < 0.0:  # np.clip(a, 0, 4): NaN stays
                    a = 0.0
                elif a > _MAX_GROWTH:
                    a = _MAX_GROWTH
            else:
                a = _DEFAULT_GROWTH
            g = min_growth[i]
            alpha[i] = a if (a >= g or np.isnan(a)) else g  # np.maximum: NaN propagates
            sd_last[i] = np.sqrt(cross[last, i, i] + _SD_FLOOR)
        for q in range(last + 1, n_k):
            grown = offsets[q] / h_last
            for i in range(m):
                sd[i] = sd_last[i] * grown ** (alpha[i] / 2.0)
            for i in range(m):
                for j in range(m):
                    rho = cross[last, i, j] / (sd_last[i] * sd_last[j])
                    out[q, i, j] = rho * sd[i] * sd[j]
    following = last  # unscored horizons before the last scored: the next scored one's
    for k in range(last - 1, -1, -1):
        if scored[k]:
            following = k
        else:
            out[k, :, :] = out[following]


if blas.AVAILABLE:

    @_compiled.helper
    def _simplex_one(s, allowed, shrink, out, shrunk, sa, b, x, work_a, work_b, pivots,
                     active, w):  # fmt: skip
        """One horizon of :func:`simplex_weights`: ``out`` (m,) from ``s`` (m, m); the others
        are work arrays (m, m), (m, m), (m, 1), (m, 1), (m, m), (1, m), (m,), (m,), (m,)."""
        m = s.shape[0]
        biggest = s[0, 0]  # diag.max(): NaN propagates
        for i in range(1, m):
            v = s[i, i]
            if not np.isnan(biggest) and (np.isnan(v) or v > biggest):
                biggest = v
        ridge = _SIMPLEX_RIDGE * (1.0 + biggest)
        keep = 1.0 - shrink
        for i in range(m):
            toward = shrink * s[i, i]
            for j in range(m):
                eye = 1.0 if i == j else 0.0
                v = keep * s[i, j] + toward * eye
                shrunk[i, j] = v + ridge * eye
        for i in range(m):
            active[i] = allowed[i]
            w[i] = 0.0
        for _ in range(m):
            # the active set's system (inactive rows and columns become the identity's)
            for i in range(m):
                off = 0.0 if active[i] else 1.0
                for j in range(m):
                    v = shrunk[i, j] if active[i] and active[j] else 0.0
                    sa[i, j] = v + off * (1.0 if i == j else 0.0)
                b[i, 0] = 1.0 if active[i] else 0.0
            if blas.solve(sa, b, x, work_a, work_b, pivots) != 0:
                return LINALG_ERROR
            total = x[0, 0]  # x.sum(): fewer than eight, in order
            for i in range(1, m):
                total = total + x[i, 0]
            worst = -1
            low = np.inf
            for i in range(m):
                w[i] = x[i, 0] / total
                if active[i] and w[i] < 0.0 and w[i] < low:  # argmin's first minimum
                    low = w[i]
                    worst = i
            if worst < 0:
                break
            active[worst] = False
        for i in range(m):  # np.where(active, np.clip(w, 0, None), 0): +0 for -0, NaN stays
            out[i] = (w[i] if (w[i] > 0.0 or np.isnan(w[i])) else 0.0) if active[i] else 0.0
        return OK

    @_compiled.helper
    def simplex_weights(s, allowed, shrink, out):
        """``out`` (K, m) = :func:`~cloe_ros.core.anticipation.simplex_weights` ``(s, allowed,
        shrink)`` of the cross-products ``s`` (K, m, m) over the ``allowed`` (m,) candidates:
        per horizon, ``s`` shrunk towards its diagonal plus a ridge, then the active-set loop
        (the system on the active candidates solved by ``dgesv``, normalised to sum 1, the
        most negative weight's candidate dropped), the weights clipped at 0. Returns
        :data:`LINALG_ERROR` where a system is singular, :data:`VALUE_ERROR` where there is no
        candidate (numpy raises), else :data:`OK`."""
        n_k, m = s.shape[0], s.shape[1]
        if m == 0 and n_k > 0:
            return VALUE_ERROR  # (the maximum of no diagonal entry)
        shrunk, sa = np.empty((m, m)), np.empty((m, m))
        b, x = np.empty((m, 1)), np.empty((m, 1))
        work_a, work_b = np.empty((m, m)), np.empty((1, m))
        pivots = np.empty(m, np.int64)
        active, w = np.empty(m, np.bool_), np.empty(m)
        for k in range(n_k):
            status = _simplex_one(s[k], allowed, shrink, out[k], shrunk, sa, b, x, work_a,
                                  work_b, pivots, active, w)  # fmt: skip
            if status != OK:
                return status
        return OK

    @_compiled(f'intp({_F3}, boolean[::1], {_F1}, {_F1}, intp, boolean[::1], {_F2})')
    def ensemble_weights(cross, scored, offsets, min_growth, m, allowed, out):
        """``out`` (K, m) = the weights over an ensemble's first ``m`` candidates, the
        ``allowed`` (m,) ones: for ``m`` = M, ``run(ensemble.weights_steps(allowed))``; for
        ``m`` < M, :meth:`~cloe_ros.core.anticipation.Anticipator._weights_steps`'s (the
        guard's ``m`` candidates of its M columns, the last being the published path). From
        the ensemble's ``cross`` (K, M, M), ``scored`` (K,), ``offsets`` (K,) s and
        ``min_growth`` (M,). No horizon scored: the first allowed candidate alone (none allowed:
        :data:`INDEX_ERROR`, where numpy raises); else :func:`simplex_weights` of
        :func:`expected_cross`, with its status."""
        n_k = cross.shape[0]
        any_scored = False
        for k in range(n_k):
            any_scored = any_scored or scored[k]
        if not any_scored:
            first = -1
            for i in range(m - 1, -1, -1):
                if allowed[i]:
                    first = i
            if first < 0:
                return INDEX_ERROR
            out[:, :] = 0.0
            out[:, first] = 1.0
            return OK
        s = np.empty((n_k, m, m))
        expected_cross(cross, scored, offsets, min_growth, m, s)
        return simplex_weights(s, allowed, 0.1, out)


# ------------------------------------------------------------------------------ intent

if blas.AVAILABLE:

    @_compiled.helper
    def harmonic_fits(t, y, ahead, omegas, joint, separate, shared):
        """:func:`~cloe_ros.core.anticipation.harmonic_fits` of one series: ``y`` (T, C)
        sampled at ``t`` (T,) s (<= 0), extrapolated to ``ahead`` (K,) s with the fit ``c + a
        cos(w t) + b sin(w t)`` of least squared error over the frequencies ``omegas`` (W,)
        rad/s, per column into ``separate`` (K, C) and with one frequency for the columns
        ``joint`` (J < 8) into ``shared`` (K, J). Per frequency, numpy's order: the basis
        (:func:`kernels.harmonic_basis`), the Gram matrix (``syrk``) plus ``1e-9 I``, the
        right-hand side (``gemm``), ``dgesv``, the residuals
        (:func:`kernels.harmonic_residuals`). Returns :data:`LINALG_ERROR` where a Gram matrix
        is singular, :data:`VALUE_ERROR` without frequencies (numpy raises), else :data:`OK`."""
        n_t, n_c = y.shape
        n_w, n_k = omegas.shape[0], ahead.shape[0]
        if n_w == 0:
            return VALUE_ERROR  # (the argmin over no frequency)
        t2 = np.empty((1, n_t))
        y3 = np.empty((1, n_t, n_c))
        for i in range(n_t):
            t2[0, i] = t[i]
            for c in range(n_c):
                y3[0, i, c] = y[i, c]
        basis = np.empty((1, n_w, n_t, 3))
        kernels.harmonic_basis(t2, omegas, basis)
        coef = np.empty((1, n_w, 3, n_c))
        gram, rhs = np.empty((3, 3)), np.empty((3, n_c))
        work_a, work_b = np.empty((3, 3)), np.empty((n_c, 3))
        pivots = np.empty(3, np.int64)
        for w in range(n_w):
            b = basis[0, w]
            blas.matmul(b.T, b, gram)  # (the basis's transposed view: syrk, as numpy)
            for i in range(3):
                for j in range(3):
                    gram[i, j] = gram[i, j] + _HARMONIC_RIDGE * (1.0 if i == j else 0.0)
            blas.matmul(b.T, y3[0], rhs)
            if blas.solve(gram, rhs, coef[0, w], work_a, work_b, pivots) != 0:
                return LINALG_ERROR
        resid = np.empty((1, n_w, n_c))
        kernels.harmonic_residuals(basis, coef, y3, resid)
        for c in range(n_c):
            best = argmin(resid[0, :, c])
            omega = omegas[best]
            c0, c1, c2 = coef[0, best, 0, c], coef[0, best, 1, c], coef[0, best, 2, c]
            for q in range(n_k):
                wa = ahead[q] * omega
                separate[q, c] = c0 + c1 * np.cos(wa) + c2 * np.sin(wa)
        n_j = joint.shape[0]
        if n_j == 0:
            return OK
        together = np.empty(n_w)
        for w in range(n_w):  # the sum over the joint columns: in order
            s = resid[0, w, joint[0]]
            for j in range(1, n_j):
                s = s + resid[0, w, joint[j]]
            together[w] = s
        best = argmin(together)
        omega = omegas[best]
        for j in range(n_j):
            c = joint[j]
            c0, c1, c2 = coef[0, best, 0, c], coef[0, best, 1, c], coef[0, best, 2, c]
            for q in range(n_k):
                wa = ahead[q] * omega
                shared[q, j] = c0 + c1 * np.cos(wa) + c2 * np.sin(wa)
        return OK

    @_compiled(f'intp({_F1}, {_F2}, {_F1}, {_F1}, float64, float64, {_F3})')
    def intent_candidates(t, r, ahead, omegas, window, subsample_hz, out):
        """``out`` (4, K, 4) = ``run(Intent(window, ahead).candidates_steps(t, r))`` with
        ``Intent.OMEGAS`` = ``omegas`` (W,) and ``Intent.SUBSAMPLE_HZ`` = ``subsample_hz``: the
        futures of the references ``r`` (T, 4) sampled at the increasing ``t`` (T,) s (the last
        sample now) at ``ahead`` (K,) s after now, by the models ``INTENT_MODELS`` (held;
        constant velocity, the least-squares line through the last second from the last jump
        on, ``dgelsd``; the harmonic fits per channel, and x-y with one frequency, over
        ``window`` s subsampled to ``subsample_hz``, :func:`harmonic_fits`). Returns
        :data:`LINALG_ERROR`, :data:`INDEX_ERROR` (no sample) or :data:`VALUE_ERROR` (a
        non-finite subsampling step) where numpy raises, else :data:`OK`."""
        n_all = t.shape[0]
        n_k = ahead.shape[0]
        if n_all == 0:
            return INDEX_ERROR
        for model in range(out.shape[0]):
            for q in range(n_k):
                for c in range(4):
                    out[model, q, c] = r[n_all - 1, c]
        now = t[n_all - 1]
        positions = np.empty((n_all, 3))  # the position channels x, y, z
        for i in range(n_all):
            positions[i, 0], positions[i, 1], positions[i, 2] = r[i, 0], r[i, 1], r[i, 3]
        start = last_jump(positions, _JUMP_FACTOR, _JUMP_FLOOR)
        n = n_all - start
        rel = np.empty(n)
        for i in range(n):
            rel[i] = t[start + i] - now
        # constant velocity: the samples of the last second
        count = 0
        first = np.nan
        for i in range(n):
            if rel[i] >= -_LINEAR_SPAN:
                if count == 0:
                    first = rel[i]
                count += 1
        if count >= _LINEAR_SAMPLES and first <= _LINEAR_FIRST:
            basis, y = np.empty((count, 2)), np.empty((count, 4))
            j = 0
            for i in range(n):
                if rel[i] >= -_LINEAR_SPAN:
                    basis[j, 0], basis[j, 1] = 1.0, rel[i]
                    for c in range(4):
                        y[j, c] = r[start + i, c]
                    j += 1
            coef = np.empty((2, 4))
            if blas.lstsq(basis, y, coef) != 0:
                return LINALG_ERROR
            for q in range(n_k):
                for c in range(4):
                    out[1, q, c] = coef[0, c] + ahead[q] * coef[1, c]
        # the harmonic fits, on every step-th sample back from now
        if n >= 2 and rel[0] <= -0.5 * window:
            spacing = np.empty(n - 1)
            for i in range(n - 1):
                spacing[i] = rel[i + 1] - rel[i]
            typical = median(spacing)
            if 1e-6 > typical:  # Python's max(typical, 1e-6): NaN stays
                typical = 1e-6
            rate = subsample_hz * typical
            if rate == 0.0:
                return VALUE_ERROR  # (ZeroDivisionError)
            exact = 1.0 / rate
            if not np.isfinite(exact):
                return VALUE_ERROR  # (round: ValueError, OverflowError)
            rounded = np.rint(exact)  # Python's round: half to even
            step = 1 if rounded < 1.0 else (n if rounded > n else int(rounded))
            n_s = (n - 1) // step + 1
            if n_s >= _HARMONIC_SAMPLES:
                offset = n - 1 - (n_s - 1) * step
                ts, rs = np.empty(n_s), np.empty((n_s, 4))
                for i in range(n_s):
                    ts[i] = rel[offset + i * step]
                    for c in range(4):
                        rs[i, c] = r[start + offset + i * step, c]
                separate, shared = np.empty((n_k, 4)), np.empty((n_k, 2))
                joint = np.arange(2)  # x and y
                status = harmonic_fits(ts, rs, ahead, omegas, joint, separate, shared)
                if status != OK:
                    return status
                for q in range(n_k):
                    for c in range(4):
                        out[2, q, c] = separate[q, c]
                        out[3, q, c] = shared[q, c] if c < 2 else separate[q, c]
        return OK
