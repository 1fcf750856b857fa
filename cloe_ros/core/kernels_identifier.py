"""Compiled kernels (numba) of the IV identifier's periodic updates: its solve (20 Hz) and its
excitation and uncertainty measures (4 Hz).

:func:`iv_solve` and :func:`iv_excitation` replace, for the vehicles due, the numpy code of
:meth:`~cloe_ros.core.identifier.IvIdentifier._solve` and
:meth:`~cloe_ros.core.identifier.IvIdentifier._update_excitation`: some dozens of calls on
batches of 1x1 to 6x6 matrices. With one vehicle their call overhead was most of the
identifier's step; with 100 vehicles stepped together, LAPACK's own calls are most of their
cost (two ``eigh``, one ``svd`` and one ``inv`` per row for the measures, a ``dgesv`` per row for
the solve: about 1.6 µs per vehicle-step, which ``scripts/engine_benchmark.py`` prints beside
the estimator).

Each kernel gives the numpy code's values bit for bit (under the golden test's pinned kernels;
test/core/test_kernels_identifier.py checks it on random statistics with their edge cases and
on recorded flights), because it does the same floating-point operations in the same order:

* the decompositions and solves are LAPACK's, called as numpy calls them
  (:mod:`cloe_ros.core.blas`: ``dsyevd`` for ``eigh``, ``dgesdd`` for the singular values,
  ``dgesv`` for ``solve`` and ``inv``), and the products numpy hands to BLAS go to the same
  routine with the same strides (:func:`cloe_ros.core.blas.matmul` on views of a (WIDTH,
  WIDTH) matrix, as numpy's slices of the statistics are);
* ``einsum('...ij,...j,...kj->...ik')`` (the inverse square root) adds its products
  ``(v_ij s_j) v_kj`` one by one from zero; ``einsum('...ij,...jk,...lk->...il')`` (the
  covariance) adds ``(c_ij g_jk) c_lk`` one by one from zero, ``j`` outer, ``k`` inner, except
  for 2x2 matrices, where numpy sums each ``j``'s two products first and adds that to the
  total (its loops on these operands; the test pins it down);
* a trace, and the sums of squares of ``np.linalg.norm``, add from the first term on, left to
  right (numpy's reduction of under 8 terms);
* ``np.maximum`` keeps its first argument where it is NaN or not below the second
  (:func:`~cloe_ros.core.kernels.maximum`), and the rest is element-wise IEEE arithmetic in the
  numpy expressions' order and grouping (numba fuses no multiply-adds without ``fastmath``).

numpy raises :class:`numpy.linalg.LinAlgError` for a whole batch when one of its matrices
fails; the kernels then return an error code and write nothing, as the numpy code writes
nothing (the covariance's ``inv`` is the exception in both: a singular matrix leaves that
size's rows at an infinite uncertainty for every vehicle of the batch).

The kernels are defined only where :data:`cloe_ros.core.blas.AVAILABLE` (:data:`AVAILABLE`
says so); elsewhere the package runs its numpy code.
"""

from __future__ import annotations

import numpy as np

from cloe_ros.core import blas, kernels
from cloe_ros.core.kernels import maximum

#: Whether the kernels are defined (numpy's OpenBLAS found: :data:`cloe_ros.core.blas.AVAILABLE`).
AVAILABLE = blas.AVAILABLE

#: Return codes: success, and the numpy code's LinAlgError by the routine that failed.
OK, EIGH_FAILED, SVD_FAILED, SOLVE_FAILED = 0, 1, 2, 3

_compiled = kernels.Compiler(__name__, 'cloe_ros.core.kernels_identifier')


@_compiled.helper
def _nan_to_num(x):
    """``np.nan_to_num(x)`` of a float: NaN to 0, infinities to the largest finite floats."""
    if x != x:
        return 0.0
    if x == np.inf:
        return np.finfo(np.float64).max
    if x == -np.inf:
        return -np.finfo(np.float64).max
    return x


@_compiled.helper
def _square(n):
    """A new (n, n) matrix, C-ordered."""
    return np.empty((n, n))


@_compiled.helper
def _unpack(stats, which, packed, v, p, out):
    """``out`` (WIDTH, WIDTH) = the statistic ``which`` of row ``p`` of vehicle ``v``, from the
    identifier's packed statistics ``stats`` (len(STATISTICS), N_PACKED, N), ``packed`` being
    :data:`~cloe_ros.core.identifier.STAT_PACKED` (the entries not stored are 0)."""
    width = out.shape[0]
    base = p * width * width
    for i in range(width):
        for j in range(width):
            q = packed[base + i * width + j]
            out[i, j] = stats[which, q, v] if q >= 0 else 0.0


if AVAILABLE:
    _F1, _F2, _F3 = 'float64[::1]', 'float64[:, ::1]', 'float64[:, :, ::1]'

    @_compiled.helper
    def inv_sqrt(g, out, v, w, sizes, work, iwork):
        """``out`` (n, n) = ``identifier._inv_sqrt(g)`` of a symmetric ``g`` (n, n): ``eigh``,
        the eigenvalues below ``1e-12`` of the largest taken as infinite, ``einsum`` of the
        eigenvectors and ``1 / sqrt`` of the values (``v`` (n, n), ``w`` (n,): work; ``sizes``:
        :func:`blas.eigh_workspace`). Returns LAPACK's ``info``."""
        n = g.shape[0]
        info = blas.eigh(g, w, v, sizes, work, iwork)
        if info != 0:
            return info
        top = w[0]
        for i in range(1, n):
            top = maximum(top, w[i])
        scale = maximum(top, 1e-300)
        for i in range(n):
            w[i] = 1.0 / np.sqrt(w[i] if w[i] > 1e-12 * scale else np.inf)
        for i in range(n):
            for k in range(n):
                acc = 0.0
                for j in range(n):
                    acc += v[i, j] * w[j] * v[k, j]
                out[i, k] = acc
        return 0

    _IV_EXCITATION = (
        # vehicles due (K,), packed statistics (S, packed, N), entries' packing, rows (N, rows,
        # W), the drift's low-pass (N, rows, W) (in/out), weight_e (N,), res2 (N, rows)
        f'int64(intp[::1], {_F3}, intp[::1], {_F3}, {_F3}, {_F1}, {_F2},'
        # the rows' mask (rows, W), sizes (rows,), the sizes in increasing order, the coupling
        # rows, prior weight, tau, quiet, the low-pass's gain
        ' boolean[:, ::1], intp[::1], intp[::1], intp[::1], float64, float64, float64, float64,'
        # thresholds: identified, unidentifiable, excitation; whether the couplings are
        # estimated; out: excitation, uncertainty (N, rows), status (N, rows) int8
        f' float64, float64, float64, boolean, {_F2}, {_F2}, int8[:, ::1])'
    )

    @_compiled(_IV_EXCITATION)
    def iv_excitation(sel, stats, packed, rows, rows_slow, weight_e, res2, mask, row_size, sizes,
                      coupling_rows, prior_weight, tau, quiet, gain, identified, unidentifiable,
                      threshold, estimate_coupling, excitation, uncertainty, status):  # fmt: skip
        """:meth:`~cloe_ros.core.identifier.IvIdentifier._update_excitation` of the vehicles
        ``sel`` (none broken), in its order (see the module docstring). Returns :data:`OK`, or
        :data:`EIGH_FAILED` / :data:`SVD_FAILED` where numpy raises (nothing written)."""
        n_sel, n_rows, width = sel.shape[0], rows.shape[1], rows.shape[2]
        exc = np.zeros((n_sel, n_rows))
        unc = np.full((n_sel, n_rows), np.inf)
        # the statistics' (W, W) matrices: numpy slices them, and so do the products here
        full, gx, gp = np.empty((width, width)), np.empty((width, width)), np.empty((width, width))
        c, gl = np.empty((width, width)), np.empty((width, width))
        for g in range(sizes.shape[0]):
            size = sizes[g]
            first = -1
            for p in range(n_rows):
                if row_size[p] == size:
                    first = p
                    break
            if not mask[first, 0]:
                continue
            e_sizes = blas.eigh_workspace(size)
            e_work, e_iwork = np.empty(max(1, e_sizes[0])), np.empty(max(1, e_sizes[1]), np.int64)
            s_work = np.empty(blas.svd_workspace(size))
            s_iwork = np.empty(max(1, 8 * size), np.int64)
            # (size, size) results, C-ordered as numpy's
            wx, wp, m1, m2 = _square(size), _square(size), _square(size), _square(size)
            cl, ci, cov, vec = _square(size), _square(size), _square(size), _square(size)
            vals, s, pivots = np.empty(size), np.empty(size), np.empty(size, np.int64)
            singular = False
            for a in range(n_sel):
                v = sel[a]
                weight = maximum(weight_e[v], 1e-12)
                for p in range(n_rows):
                    if row_size[p] != size:
                        continue
                    # (views of (W, W) matrices, with the strides of numpy's slices)
                    _unpack(stats, 1, packed, v, p, gx)
                    _unpack(stats, 2, packed, v, p, gp)
                    _unpack(stats, 0, packed, v, p, c)
                    x, y, z = gx[:size, :size], gp[:size, :size], c[:size, :size]
                    if inv_sqrt(x, wx, vec, vals, e_sizes, e_work, e_iwork) != 0:
                        return EIGH_FAILED
                    if inv_sqrt(y, wp, vec, vals, e_sizes, e_work, e_iwork) != 0:
                        return EIGH_FAILED
                    blas.matmul(wx, z, m1)
                    blas.matmul(m1, wp, m2)
                    if blas.svd_values(m2, s, s_work, s_iwork) != 0:
                        return SVD_FAILED
                    trace = x[0, 0]
                    for i in range(1, size):
                        trace += x[i, i]
                    rms = np.sqrt(trace / weight / size)
                    exc[a, p] = _nan_to_num(s[size - 1]) if rms > quiet else 0.0
                    # the covariance of the long window's estimate
                    _unpack(stats, 3, packed, v, p, full)
                    for i in range(size):
                        for j in range(size):
                            cl[i, j] = full[i, j] + prior_weight * (1.0 if i == j else 0.0)
                    if blas.inv(cl, ci, pivots) != 0:
                        singular = True
                        continue
                    _unpack(stats, 4, packed, v, p, gl)
                    for i in range(size):
                        for k in range(size):
                            acc = 0.0
                            for j in range(size):
                                if size == 2:
                                    part = 0.0
                                    for q in range(size):
                                        part += ci[i, j] * gl[j, q] * ci[k, q]
                                    acc = part + acc
                                else:
                                    for q in range(size):
                                        acc += ci[i, j] * gl[j, q] * ci[k, q]
                            cov[i, k] = acc
                    trace = cov[0, 0]
                    for i in range(1, size):
                        trace += cov[i, i]
                    var = trace * (res2[v, p] / weight) * tau
                    total = rows[v, p, 0] * rows[v, p, 0]
                    for i in range(1, size):
                        total += rows[v, p, i] * rows[v, p, i]
                    unc[a, p] = np.sqrt(maximum(var, 0.0)) / maximum(np.sqrt(total), 1e-12)
            if singular:  # numpy's inv raised for the batch: that size stays infinite
                for a in range(n_sel):
                    for p in range(n_rows):
                        if row_size[p] == size:
                            unc[a, p] = np.inf
        n_coupling = coupling_rows.shape[0]
        for a in range(n_sel):
            v = sel[a]
            for p in range(n_rows):
                u = unc[a, p]
                if not np.isfinite(u):
                    u = np.inf
                for i in range(width):
                    rows_slow[v, p, i] = rows_slow[v, p, i] + gain * (rows[v, p, i]
                                                                      - rows_slow[v, p, i])
                d = rows[v, p, 0] - rows_slow[v, p, 0]
                moved, size = d * d, rows[v, p, 0] * rows[v, p, 0]
                for i in range(1, width):
                    d = rows[v, p, i] - rows_slow[v, p, i]
                    moved += d * d
                    size += rows[v, p, i] * rows[v, p, i]
                drift = np.sqrt(moved) / maximum(np.sqrt(size), 1e-12)
                total = maximum(u, drift)
                code = 1  # converging
                if total <= identified:
                    code = 2
                if exc[a, p] < threshold or u > unidentifiable:
                    code = 0
                excitation[v, p], uncertainty[v, p], status[v, p] = exc[a, p], total, code
            if not estimate_coupling:
                for q in range(n_coupling):
                    status[v, coupling_rows[q]] = 2
        return OK

    _IV_SOLVE = (
        # vehicles due (K,), packed statistics, entries' packing, rhs (N, rows, W), prior
        # (N, rows, W), the rows' mask (rows, W), prior weight, the rows' target scales (rows,)
        # and entries' scales (rows, W), the blocks' rows (blocks,) and first parameters
        # (blocks,), the coupling rows and the loop rows; out: rows (N, rows, W), theta
        # (N, 16), coupling (N, 2), loops (N, 2, 2)
        f'int64(intp[::1], {_F3}, intp[::1], {_F3}, {_F3}, boolean[:, ::1], float64, {_F1},'
        f' {_F2}, intp[::1], intp[::1], intp[::1], intp[::1], {_F3}, {_F2}, {_F2}, {_F3})'
    )

    @_compiled(_IV_SOLVE)
    def iv_solve(sel, stats, packed, rhs, prior, mask, prior_weight, target_scale, row_scale,
                 block_rows, block_starts, coupling_rows, loop_rows, rows, theta, coupling,
                 loops):  # fmt: skip
        """:meth:`~cloe_ros.core.identifier.IvIdentifier._solve` of the vehicles ``sel``: per
        row, ``(C + w I) x = b + w prior`` by ``dgesv`` (numpy's ``solve`` of the row's system
        and its right-hand side as a column), the entries outside the mask at the prior, into
        ``rows``; then the parameters in physical units, ``rows * target scale / row scale``,
        into ``theta``, ``coupling`` and ``loops``. Returns :data:`SOLVE_FAILED` where numpy
        raises (nothing written)."""
        n_sel, n_rows, width = sel.shape[0], rhs.shape[1], rhs.shape[2]
        out = np.empty((n_sel, n_rows, width))
        lhs, b, x = np.empty((width, width)), np.empty((width, 1)), np.empty((width, 1))
        work_a, work_b = np.empty((width, width)), np.empty((1, width))
        pivots = np.empty(width, np.int64)
        for a in range(n_sel):
            v = sel[a]
            for p in range(n_rows):
                _unpack(stats, 3, packed, v, p, lhs)
                for i in range(width):
                    for j in range(width):
                        lhs[i, j] = lhs[i, j] + prior_weight * (1.0 if i == j else 0.0)
                    b[i, 0] = rhs[v, p, i] + prior_weight * prior[v, p, i]
                if blas.solve(lhs, b, x, work_a, work_b, pivots) != 0:
                    return SOLVE_FAILED
                for i in range(width):
                    out[a, p, i] = x[i, 0] if mask[p, i] else prior[v, p, i]
        n_blocks = block_rows.shape[0]
        for a in range(n_sel):
            v = sel[a]
            rows[v] = out[a]
            for q in range(n_blocks):
                p, start = block_rows[q], block_starts[q]
                size = (block_starts[q + 1] if q + 1 < n_blocks else theta.shape[1]) - start
                for i in range(size):
                    theta[v, start + i] = out[a, p, i] * target_scale[p] / row_scale[p, i]
            for q in range(coupling_rows.shape[0]):
                p = coupling_rows[q]
                coupling[v, q] = out[a, p, 0] * target_scale[p] / row_scale[p, 0]
            for q in range(loop_rows.shape[0]):
                p = loop_rows[q]
                for i in range(2):
                    loops[v, q, i] = out[a, p, i] * target_scale[p] / row_scale[p, i]
        return OK
