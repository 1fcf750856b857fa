"""The routines of numpy's OpenBLAS (:mod:`~cloe_ros.core.blas`) that numba's kernels call, and
the helpers that call them as numpy does (see :mod:`~cloe_ros.core.blas`).

Imported by numba's JIT and by the build of the kernels ahead (:mod:`~cloe_ros.core.ahead`)
only, through :mod:`~cloe_ros.core.blas`, and only where :data:`~cloe_ros.core.blas.AVAILABLE`:
it imports numba.
"""

from __future__ import annotations

import numpy as np
from numba import types

from cloe_ros.core.blas import link_for_numba, symbol
from cloe_ros.core.kernels import Compiler

link_for_numba()  # (the kernels link to it by name)

_P = types.CPointer
_I, _D, _C = types.int64, types.float64, types.int32  # (blasint, double, CBLAS enums)
_dgesv = types.ExternalFunction(symbol('dgesv'), types.void(
    _P(_I), _P(_I), _P(_D), _P(_I), _P(_I), _P(_D), _P(_I), _P(_I)))
_dgelsd = types.ExternalFunction(symbol('dgelsd'), types.void(
    _P(_I), _P(_I), _P(_I), _P(_D), _P(_I), _P(_D), _P(_I), _P(_D), _P(_D), _P(_I),
    _P(_D), _P(_I), _P(_I), _P(_I)))
# (the character arguments' hidden lengths last, by value, as gfortran passes them)
_dsyevd = types.ExternalFunction(symbol('dsyevd'), types.void(
    _P(types.uint8), _P(types.uint8), _P(_I), _P(_D), _P(_I), _P(_D), _P(_D), _P(_I), _P(_I),
    _P(_I), _P(_I), _I, _I))
_dgesdd = types.ExternalFunction(symbol('dgesdd'), types.void(
    _P(types.uint8), _P(_I), _P(_I), _P(_D), _P(_I), _P(_D), _P(_D), _P(_I), _P(_D), _P(_I),
    _P(_D), _P(_I), _P(_I), _P(_I), _I))
_dgemv = types.ExternalFunction(symbol('cblas_dgemv'), types.void(
    _C, _C, _I, _I, _D, _P(_D), _I, _P(_D), _I, _D, _P(_D), _I))
_dgemm = types.ExternalFunction(symbol('cblas_dgemm'), types.void(
    _C, _C, _C, _I, _I, _I, _D, _P(_D), _I, _P(_D), _I, _D, _P(_D), _I))
_dsyrk = types.ExternalFunction(symbol('cblas_dsyrk'), types.void(
    _C, _C, _C, _I, _I, _D, _P(_D), _I, _D, _P(_D), _I))
_ddot = types.ExternalFunction(symbol('cblas_ddot'), _D(_I, _P(_D), _I, _P(_D), _I))

ROW_MAJOR, COL_MAJOR, NO_TRANS, TRANS, UPPER = 101, 102, 111, 112, 121
_compiled = Compiler(__name__, 'cloe_ros.core.blas_kernels')
_A1, _A2 = 'float64[:]', 'float64[:, :]'  # (any strides: one signature serves every view)

@_compiled.helper
def _blasable(s1, s2, d1, d2):
    """numpy's ``is_blasable2d`` with element strides: unit inner stride, an outer one
    at least the inner extent (and a BLAS int)."""
    return s2 == 1 and s1 >= d2 and s1 <= 2**31 - 1

@_compiled.helper
def _gemm_or_syrk(a, b, out):
    """numpy's matrix-matrix product of BLAS-able operands into a C-ordered ``out``:
    ``syrk`` for a matrix times its own transpose (the other triangle copied), else
    ``gemm``."""
    m, n = a.shape
    p = b.shape[1]
    s1m, s1n = a.strides[0] // 8, a.strides[1] // 8
    s2n, s2p = b.strides[0] // 8, b.strides[1] // 8
    if _blasable(s1m, s1n, m, n):
        trans1, lda = NO_TRANS, s1m
    else:
        trans1, lda = TRANS, s1n
    if _blasable(s2n, s2p, n, p):
        trans2, ldb = NO_TRANS, s2n
    else:
        trans2, ldb = TRANS, s2p
    ldc = out.strides[0] // 8
    if (a.ctypes.data == b.ctypes.data and m == p and s1m == s2p and s1n == s2n
            and trans1 != trans2):  # fmt: skip
        _dsyrk(ROW_MAJOR, UPPER, trans1, p, n, 1.0, a.ctypes,
               lda if trans1 == NO_TRANS else ldb, 0.0, out.ctypes, ldc)  # fmt: skip
        for i in range(p):
            for j in range(i + 1, p):
                out[j, i] = out[i, j]
    else:
        _dgemm(ROW_MAJOR, trans1, trans2, m, p, n, 1.0, a.ctypes, lda, b.ctypes, ldb, 0.0,
               out.ctypes, ldc)

@_compiled.helper
def _gemv(a, x, y, s_m, s_n):
    """``y = a @ x`` for ``a`` (m, n) blasable with element strides ``(s_m, s_n)``:
    numpy's ``gemv`` (column-major with the transpose, or row-major)."""
    m, n = a.shape
    if _blasable(s_m, s_n, m, n):
        order, lda = COL_MAJOR, s_m
    else:
        order, lda = ROW_MAJOR, s_n
    _dgemv(order, TRANS, n, m, 1.0, a.ctypes, lda, x.ctypes, x.strides[0] // 8, 0.0, y.ctypes,
           y.strides[0] // 8)

@_compiled.helper
def _dot(x, y, out):
    """``out[0, 0]`` = numpy's ``dot`` of two vectors: ``cblas_ddot`` where the strides
    allow it, else a plain sum in order."""
    n = x.shape[0]
    sx, sy = x.strides[0] // 8, y.strides[0] // 8
    if sx > 0 and sy > 0:
        out[0, 0] = _ddot(n, x.ctypes, sx, y.ctypes, sy)
    else:
        s = 0.0
        for i in range(n):
            s += x[i] * y[i]
        out[0, 0] = s

@_compiled.helper
def _noblas(a, b, out):
    """numpy's matmul loop without BLAS: each entry summed from 0 in order."""
    m, n = a.shape
    p = b.shape[1]
    for i in range(m):
        for j in range(p):
            s = 0.0
            for k in range(n):
                s += a[i, k] * b[k, j]
            out[i, j] = s

@_compiled.helper
def matmul(a, b, out):
    """``out[...] = a @ b`` for 2-D float64 ``a`` (m, n), ``b`` (n, p), ``out`` (m, p) (any
    strides; ``out`` may not overlap them): numpy's matmul, the same routine and
    arguments, so the same bits."""
    m, n = a.shape
    p = b.shape[1]
    s1m, s1n = a.strides[0] // 8, a.strides[1] // 8
    s2n, s2p = b.strides[0] // 8, b.strides[1] // 8
    som, sop = out.strides[0] // 8, out.strides[1] // 8
    if m == 0 or p == 0:
        return
    if n == 0:
        out[:, :] = 0.0
        return
    i1_c, i2_c = _blasable(s1m, s1n, m, n), _blasable(s2n, s2p, n, p)
    i1_f, i2_f = _blasable(s1n, s1m, n, m), _blasable(s2p, s2n, p, n)
    i1, i2 = i1_c or i1_f, i2_c or i2_f
    o_c = _blasable(som, sop, m, p)
    if m == 1 or n == 1 or p == 1:
        if m == 1 and p == 1:
            _dot(a[0, :], b[:, 0], out)
        elif n == 1:
            _noblas(a, b, out)
        elif m == 1 and i2 and _blasable(s1n, 1, n, 1):
            # vector @ matrix: gemv of b's transpose
            _gemv(b.T, a[0, :], out[0, :], s2p, s2n)
        elif p == 1 and i1 and _blasable(s2n, 1, n, 1):
            _gemv(a, b[:, 0], out[:, 0], s1m, s1n)
        else:
            _noblas(a, b, out)
        return
    if i1 and i2 and o_c:
        _gemm_or_syrk(a, b, out)
        return
    # numpy copies what BLAS cannot take to C-ordered buffers, then multiplies those
    tmp = np.empty((m, p))
    _gemm_or_syrk(a if i1 else np.ascontiguousarray(a),
                  b if i2 else np.ascontiguousarray(b), tmp)  # fmt: skip
    out[:, :] = tmp

@_compiled.helper
def _transposed(a, out):
    """``out[j, i] = a[i, j]`` for ``a`` (m, n): a matrix to or from LAPACK's column-major
    order (``out`` may be larger than (n, m): the rest is left as it is)."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[j, i] = a[i, j]

@_compiled.helper
def solve(a, b, out, work_a, work_b, pivots):
    """``out`` (n, k) = ``np.linalg.solve(a, b)`` for ``a`` (n, n), ``b`` (n, k): ``dgesv``
    on Fortran-ordered copies (``work_a`` (n, n), ``work_b`` (k, n), ``pivots`` (n,) int64).
    Returns LAPACK's ``info`` (> 0: ``a`` is singular, where numpy raises)."""
    n, k = b.shape
    _transposed(a, work_a)
    _transposed(b, work_b)
    sizes = np.empty(3, np.int64)  # n, k, info
    sizes[0], sizes[1], sizes[2] = n, k, 0
    _dgesv(sizes[0:].ctypes, sizes[1:].ctypes, work_a.ctypes, sizes[0:].ctypes,
           pivots.ctypes, work_b.ctypes, sizes[0:].ctypes, sizes[2:].ctypes)
    _transposed(work_b, out)
    return sizes[2]

@_compiled.helper
def lstsq(a, b, out):
    """``out`` (n, k) = ``np.linalg.lstsq(a, b, rcond=None)[0]`` for ``a`` (m, n), ``b``
    (m, k): ``dgelsd`` as numpy calls it (its workspace query, ``rcond`` = eps max(m, n)).
    Returns LAPACK's ``info`` (> 0: no convergence, where numpy raises)."""
    m, n = a.shape
    k = b.shape[1]
    ldb = max(1, m, n)
    fa = np.empty((n, max(1, m)))
    fb = np.zeros((k, ldb))
    _transposed(a, fa)
    _transposed(b, fb)
    s = np.empty(max(1, min(m, n)))
    ints = np.empty(8, np.int64)
    ints[0], ints[1], ints[2], ints[3], ints[4] = m, n, k, max(1, m), ldb
    ints[5], ints[6], ints[7] = 0, -1, 0  # rank, lwork, info
    rcond = np.empty(1)
    rcond[0] = np.finfo(np.float64).eps * max(m, n)
    query = np.empty(1)
    iquery = np.empty(1, np.int64)
    _dgelsd(ints[0:].ctypes, ints[1:].ctypes, ints[2:].ctypes, fa.ctypes, ints[3:].ctypes,
            fb.ctypes, ints[4:].ctypes, s.ctypes, rcond.ctypes, ints[5:].ctypes, query.ctypes,
            ints[6:].ctypes, iquery.ctypes, ints[7:].ctypes)
    work = np.empty(max(1, int(query[0])))
    iwork = np.empty(max(1, iquery[0]), np.int64)
    ints[6] = work.shape[0]
    _dgelsd(ints[0:].ctypes, ints[1:].ctypes, ints[2:].ctypes, fa.ctypes, ints[3:].ctypes,
            fb.ctypes, ints[4:].ctypes, s.ctypes, rcond.ctypes, ints[5:].ctypes, work.ctypes,
            ints[6:].ctypes, iwork.ctypes, ints[7:].ctypes)
    _transposed(fb[:, :n], out)
    return ints[7]

@_compiled.helper
def inv(a, out, pivots):
    """``out`` (n, n) = ``np.linalg.inv(a)``: :func:`solve` of ``a`` on the identity, as
    numpy's ``inv`` calls ``dgesv`` (``pivots`` (n,) int64). Returns LAPACK's ``info`` (> 0:
    ``a`` is singular, where numpy raises)."""
    n = a.shape[0]
    return solve(a, np.eye(n), out, np.empty((n, n)), np.empty((n, n)), pivots)

_JOBZ_V, _JOBZ_N, _UPLO_L = ord('V'), ord('N'), ord('L')

@_compiled.helper
def eigh_workspace(n):
    """numpy's workspace of ``dsyevd`` for ``eigh`` of (n, n) matrices: ``[lwork, liwork]``
    from LAPACK's query."""
    chars = np.array([_JOBZ_V, _UPLO_L], np.uint8)
    ints = np.empty(5, np.int64)  # n, lda, lwork, liwork, info
    ints[0], ints[1], ints[2], ints[3], ints[4] = n, max(n, 1), -1, -1, 0
    a, w, query = np.empty(max(n * n, 1)), np.empty(max(n, 1)), np.empty(1)
    iquery = np.empty(1, np.int64)
    _dsyevd(chars[0:].ctypes, chars[1:].ctypes, ints[0:].ctypes, a.ctypes, ints[1:].ctypes,
            w.ctypes, query.ctypes, ints[2:].ctypes, iquery.ctypes, ints[3:].ctypes,
            ints[4:].ctypes, 1, 1)  # fmt: skip
    out = np.empty(2, np.int64)
    out[0], out[1] = int(query[0]), iquery[0]
    return out

@_compiled.helper
def eigh(a, w, v, sizes, work, iwork):
    """``w`` (n,), ``v`` (n, n) = ``np.linalg.eigh(a)``: ``dsyevd`` ('V', lower triangle)
    on a Fortran-ordered copy of ``a``, with the workspace ``work`` and ``iwork`` of
    :func:`eigh_workspace` (``sizes``: that function's result). Returns LAPACK's ``info``
    (> 0: no convergence, where numpy raises)."""
    n = a.shape[0]
    fa = np.empty((n, n))
    _transposed(a, fa)
    chars = np.array([_JOBZ_V, _UPLO_L], np.uint8)
    ints = np.empty(5, np.int64)
    ints[0], ints[1], ints[2], ints[3], ints[4] = n, max(n, 1), sizes[0], sizes[1], 0
    vals = np.empty(n)
    _dsyevd(chars[0:].ctypes, chars[1:].ctypes, ints[0:].ctypes, fa.ctypes, ints[1:].ctypes,
            vals.ctypes, work.ctypes, ints[2:].ctypes, iwork.ctypes, ints[3:].ctypes,
            ints[4:].ctypes, 1, 1)  # fmt: skip
    if ints[4] == 0:
        w[:] = vals
        _transposed(fa, v)
    return ints[4]

@_compiled.helper
def svd_workspace(n):
    """numpy's ``lwork`` of ``dgesdd`` for the singular values of (n, n) matrices, from
    LAPACK's query (at least 1)."""
    chars = np.array([_JOBZ_N], np.uint8)
    ints = np.empty(6, np.int64)  # m, n, lda, ldu, ldvt, lwork
    ints[0], ints[1], ints[2], ints[3], ints[4], ints[5] = n, n, max(n, 1), max(n, 1), 1, -1
    info = np.zeros(1, np.int64)
    a, s, u, vt = np.empty(max(n * n, 1)), np.empty(max(n, 1)), np.empty(1), np.empty(1)
    query, iwork = np.empty(1), np.empty(max(8 * n, 1), np.int64)
    _dgesdd(chars.ctypes, ints[0:].ctypes, ints[1:].ctypes, a.ctypes, ints[2:].ctypes,
            s.ctypes, u.ctypes, ints[3:].ctypes, vt.ctypes, ints[4:].ctypes, query.ctypes,
            ints[5:].ctypes, iwork.ctypes, info.ctypes, 1)  # fmt: skip
    return max(1, int(query[0]))

@_compiled.helper
def svd_values(a, s, work, iwork):
    """``s`` (n,) = ``np.linalg.svd(a, compute_uv=False)`` of a square ``a``: ``dgesdd``
    ('N') on a Fortran-ordered copy, with the workspace ``work`` (:func:`svd_workspace`
    long) and ``iwork`` (8 n). Returns LAPACK's ``info`` (> 0: no convergence, where
    numpy raises)."""
    n = a.shape[0]
    fa = np.empty((n, n))
    _transposed(a, fa)
    chars = np.array([_JOBZ_N], np.uint8)
    ints = np.empty(7, np.int64)  # m, n, lda, ldu, ldvt, lwork, info
    ints[0], ints[1], ints[2], ints[3], ints[4] = n, n, max(n, 1), max(n, 1), 1
    ints[5], ints[6] = work.shape[0], 0
    vals, u, vt = np.empty(n), np.empty(1), np.empty(1)
    _dgesdd(chars.ctypes, ints[0:].ctypes, ints[1:].ctypes, fa.ctypes, ints[2:].ctypes,
            vals.ctypes, u.ctypes, ints[3:].ctypes, vt.ctypes, ints[4:].ctypes, work.ctypes,
            ints[5:].ctypes, iwork.ctypes, ints[6:].ctypes, 1)  # fmt: skip
    if ints[6] == 0:
        s[:] = vals
    return ints[6]
