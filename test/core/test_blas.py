"""The kernels' BLAS and LAPACK calls give numpy's values bit for bit (cloe_ros/core/blas.py):
the same routines of the same library, with the arguments numpy passes, whatever the shapes
and strides."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core import blas

pytestmark = pytest.mark.skipif(not blas.AVAILABLE, reason="numpy's OpenBLAS not found")

RNG = np.random.default_rng(20261205)


def operands():
    """Pairs (a, b) of the shapes and layouts the kernels multiply: contiguous, transposed
    views, strided views, vectors as rows and columns, one operand the other's transpose."""
    for m, n, p in [(12, 12, 1), (1, 12, 12), (7, 12, 12), (3, 61, 3), (3, 61, 4), (1, 5, 1),
                    (5, 1, 4), (4, 4, 4), (50, 12, 4), (2, 3, 2)]:  # fmt: skip
        a, b = RNG.standard_normal((m, n)), RNG.standard_normal((n, p))
        yield a, b
        yield np.asfortranarray(a), b
        yield a, np.asfortranarray(b)
        big = RNG.standard_normal((m, 2 * n + 1))
        yield big[:, 1 : 2 * n + 1 : 2], b  # inner stride 2: not BLAS-able
        yield big[:, :n], b  # row stride larger than the row
    basis = RNG.standard_normal((61, 3))
    yield basis.T, basis  # a matrix times its own transpose: syrk
    yield basis, basis.T
    stack = RNG.standard_normal((4, 61, 3))
    yield np.swapaxes(stack, -1, -2)[2], stack[2]


@pytest.mark.parametrize('k', range(53))
def test_matmul_is_numpys(k):
    a, b = list(operands())[k]
    want = a @ b
    out = np.full(want.shape, np.nan)
    blas.matmul(a, b, out)
    np.testing.assert_array_equal(out, want)


def test_matmul_writes_into_a_strided_output():
    a, b = RNG.standard_normal((5, 6)), RNG.standard_normal((6, 4))
    out = np.zeros((5, 8))
    blas.matmul(a, b, out[:, ::2])
    np.testing.assert_array_equal(out[:, ::2], a @ b)
    assert not out[:, 1::2].any()


@pytest.mark.parametrize('n, k', [(3, 4), (4, 1), (5, 1), (6, 1), (12, 12)])
def test_solve_is_numpys(n, k):
    for _ in range(50):
        a, b = RNG.standard_normal((n, n)), RNG.standard_normal((n, k))
        out = np.empty((n, k))
        info = blas.solve(a, b, out, np.empty((n, n)), np.empty((k, n)),
                          np.empty(n, np.int64))  # fmt: skip
        assert info == 0
        np.testing.assert_array_equal(out, np.linalg.solve(a, b))


def test_solve_says_singular_where_numpy_raises():
    a = np.ones((3, 3))
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(a, np.ones((3, 1)))
    info = blas.solve(a, np.ones((3, 1)), np.empty((3, 1)), np.empty((3, 3)), np.empty((1, 3)),
                      np.empty(3, np.int64))  # fmt: skip
    assert info > 0


@pytest.mark.parametrize('m, n, k', [(20, 2, 4), (5, 2, 4), (61, 2, 3), (2, 2, 1), (8, 3, 2)])
def test_lstsq_is_numpys(m, n, k):
    for _ in range(20):
        a, b = RNG.standard_normal((m, n)), RNG.standard_normal((m, k))
        a[:, 0] = 1.0
        out = np.empty((n, k))
        assert blas.lstsq(a, b, out) == 0
        np.testing.assert_array_equal(out, np.linalg.lstsq(a, b, rcond=None)[0])


@pytest.mark.parametrize('n', [1, 2, 3, 5, 6])
def test_eigh_svd_and_inv_are_numpys(n):
    sizes, lwork = blas.eigh_workspace(n), blas.svd_workspace(n)
    work, iwork = np.empty(sizes[0]), np.empty(sizes[1], np.int64)
    svd_work, svd_iwork = np.empty(lwork), np.empty(8 * n, np.int64)
    for trial in range(50):
        x = RNG.standard_normal((n, n + 2)) * 10.0 ** RNG.uniform(-6, 6)
        g = x @ x.T
        view = np.zeros((n + 1, n + 1))[:n, :n]  # (a slice's strides, as the kernels pass)
        view[...] = g if trial % 2 else RNG.standard_normal((n, n))
        w, v = np.empty(n), np.empty((n, n))
        assert blas.eigh(view, w, v, sizes, work, iwork) == 0
        want_w, want_v = np.linalg.eigh(view)
        np.testing.assert_array_equal(w, want_w)
        np.testing.assert_array_equal(v, want_v)
        s = np.empty(n)
        assert blas.svd_values(view, s, svd_work, svd_iwork) == 0
        np.testing.assert_array_equal(s, np.linalg.svd(view, compute_uv=False))
        out = np.empty((n, n))
        assert blas.inv(view, out, np.empty(n, np.int64)) == 0
        np.testing.assert_array_equal(out, np.linalg.inv(view))


def test_inv_says_singular_where_numpy_raises():
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.inv(np.ones((3, 3)))
    assert blas.inv(np.ones((3, 3)), np.empty((3, 3)), np.empty(3, np.int64)) > 0
