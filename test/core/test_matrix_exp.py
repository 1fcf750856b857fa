"""matrix_exp.expm gives scipy.linalg.expm's bits without importing scipy.linalg: on the models the
engine discretises and on every kind of matrix its steps branch on, alone and batched."""

from __future__ import annotations

from importlib.metadata import version

import numpy as np
import pytest
import scipy.linalg

from cloe_ros.core import matrix_exp
from cloe_ros.core.identifier import generic_prior
from cloe_ros.core.model import N_REFERENCES, N_STATES, discretise, system_matrices

CHECKED = tuple(int(p) for p in version('scipy').split('.')[:2]) in matrix_exp.CHECKED_SCIPY


def test_the_compiled_routines_load_for_a_checked_scipy():
    """(Else every comparison below would compare scipy with itself.)"""
    if not CHECKED:
        pytest.skip(f'scipy {version("scipy")} is not one of {matrix_exp.CHECKED_SCIPY}')
    assert matrix_exp._core() is not None


def _models(n: int, dt: float, seed: int) -> np.ndarray:
    """The augmented matrices ``[[A, B], [0, 0]] dt`` of ``n`` models about the prior, as
    :func:`~cloe_ros.core.model.discretise` builds them (some unstable, some with zero rows)."""
    rng = np.random.default_rng(seed)
    theta, coupling = generic_prior()
    thetas = theta * rng.uniform(-1.0, 3.0, (n, theta.size))
    thetas[: n // 10] = 0.0
    a, b = system_matrices(thetas, np.broadcast_to(coupling, (n, len(coupling))))
    m = np.zeros((n, N_STATES + N_REFERENCES, N_STATES + N_REFERENCES))
    m[:, :N_STATES, :N_STATES], m[:, :N_STATES, N_STATES:] = a, b
    return m * dt


@pytest.mark.parametrize('dt', [0.01, 0.05, 0.1, 0.5, 2.0])
def test_models_get_scipys_bits_alone_and_batched(dt):
    m = _models(300, dt, seed=int(dt * 100))
    assert np.array_equal(matrix_exp.expm(m), scipy.linalg.expm(m))
    for k in range(0, 300, 37):
        assert np.array_equal(matrix_exp.expm(m[k]), scipy.linalg.expm(m[k]))
    theta, coupling = generic_prior()  # and discretise is scipy's zero-order hold
    a, b = system_matrices(theta, coupling)
    want = scipy.linalg.expm(np.block([[a, b], [np.zeros((N_REFERENCES, len(a) + b.shape[1]))]])
                             * dt)  # fmt: skip
    ad, bd = discretise(theta, coupling, dt)
    assert np.array_equal(ad, want[:N_STATES, :N_STATES])
    assert np.array_equal(bd, want[:N_STATES, N_STATES:])


@pytest.mark.parametrize('kind', ['dense', 'upper', 'lower', 'repeated', 'diagonal', 'zero', 'nan',
                                  'large'])  # fmt: skip
@pytest.mark.parametrize('n', [2, 3, 7, 16])
def test_every_branch_gets_scipys_bits(kind, n):
    """Dense and triangular matrices large enough to be scaled and squared (the triangular
    ones' own squaring, with a diagonal of distinct or of repeated values), diagonal and zero
    ones (no Padé), non-finite entries."""
    rng = np.random.default_rng(n)
    x = rng.normal(size=(20, n, n)) * 4.0
    x = {'upper': np.triu(x), 'lower': np.tril(x), 'diagonal': x * np.eye(n),
         'repeated': np.triu(x, 1) + 1.5 * np.eye(n), 'zero': 0.0 * x,
         'large': 50.0 * x}.get(kind, x)  # fmt: skip
    if kind == 'nan':
        x[:, 0, -1] = np.nan
    with np.errstate(all='ignore'):
        assert np.array_equal(matrix_exp.expm(x), scipy.linalg.expm(x), equal_nan=True)


@pytest.mark.parametrize('a', [np.eye(3, dtype=np.float32), np.eye(3) * 1j, np.ones((1, 1)),
                               np.zeros((0, 0)), np.ones((2, 2), dtype=int)])  # fmt: skip
def test_what_the_steps_do_not_cover_is_scipys(a):
    got, want = matrix_exp.expm(a), scipy.linalg.expm(a)
    assert got.dtype == want.dtype and np.array_equal(got, want)


def test_another_scipy_release_is_scipys_own(monkeypatch):
    monkeypatch.setattr(matrix_exp, 'version', lambda name: '1.99.0')
    matrix_exp._core.cache_clear()
    try:
        assert matrix_exp._core() is None
        x = _models(5, 0.1, seed=3)
        assert np.array_equal(matrix_exp.expm(x), scipy.linalg.expm(x))
    finally:
        matrix_exp._core.cache_clear()


def test_the_engine_imports_no_scipy_linalg(infer_in_a_fresh_process):
    """A cloe_iv engine over a flight's inputs discretises models (the identifier, the predictions,
    the reference trust) without importing scipy.linalg: its import costs 0.35-0.4 s of CPU.
    Checked on the modules a fresh process imported, not on time."""
    code, modules, _ = infer_in_a_fresh_process
    assert code == 0
    assert ('scipy.linalg' in modules) == (not CHECKED)
