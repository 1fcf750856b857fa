"""The identifier's kernels (cloe_ros/core/kernels_identifier.py) give the numpy code of
``IvIdentifier._solve`` and ``IvIdentifier._update_excitation`` bit for bit: on random
statistics with the edge cases (a subset of vehicles due, a broken vehicle, a quiet one, a
singular system or covariance in a batch, fixed couplings) in this process, and on recorded
flights replayed through the engine under the golden test's pinned kernels."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from cloe_ros.core import identifier, kernels_identifier
from cloe_ros.core.identifier import (
    CROSS,
    GRAM_PHI,
    GRAM_XI,
    GRAM_XI_LONG,
    N_ROWS,
    ROW_SIZE,
    STAT_PACKED,
    WIDTH,
    IdentifierConfig,
    IvIdentifier,
)
from test.golden_outputs import REPO, run_pinned_script

pytestmark = pytest.mark.skipif(not kernels_identifier.AVAILABLE,
                                reason="numpy's OpenBLAS not found")  # fmt: skip

FIELDS = ('excitation', 'uncertainty', 'status', '_rows_slow', 'theta')
SOLVED = ('_rows', 'theta', 'coupling', 'loops')


def random_identifier(n: int, rng: np.random.Generator, **config) -> IvIdentifier:
    """An identifier of ``n`` vehicles whose statistics, solution and residuals are random
    (Gram matrices positive definite, of scales from 1e-8 to 1e4, cross matrices dense)."""
    ident = IvIdentifier(IdentifierConfig(**config), 0.01, np.zeros((n, 12)), np.zeros((n, 4)))
    full = np.zeros((n, 5, N_ROWS, WIDTH, WIDTH))
    for v in range(n):
        for p in range(N_ROWS):
            for which in (GRAM_XI, GRAM_PHI, GRAM_XI_LONG):
                x = rng.standard_normal((WIDTH, WIDTH + 3)) * 10.0 ** rng.uniform(-4, 2)
                full[v, which, p] = x @ x.T
            for which in (0, CROSS):
                scale = 10.0 ** rng.uniform(-3, 2)
                full[v, which, p] = rng.standard_normal((WIDTH, WIDTH)) * scale
    packed = full.reshape(n, 5, -1)[:, :, STAT_PACKED >= 0]
    order = np.argsort(STAT_PACKED[STAT_PACKED >= 0])
    ident.statistics = packed[:, :, order]
    ident._rows = rng.standard_normal(ident._rows.shape)
    ident._rows_slow = ident._rows + 0.1 * rng.standard_normal(ident._rows.shape)
    ident.res2 = rng.uniform(0.0, 1.0, ident.res2.shape)
    ident.weight_e = rng.uniform(0.5, 2.0, n)
    return ident


def both_ways(ident: IvIdentifier, which: np.ndarray | None, method: str = '_update_excitation',
              fields: tuple[str, ...] = FIELDS):
    """``method(which)`` compiled and in numpy, on copies of ``ident``: the ``fields`` it
    writes, or the error it raised."""
    out = []
    for compiled in (True, False):
        mine = copy.deepcopy(ident)
        identifier.COMPILED = compiled
        try:
            getattr(mine, method)(which)
            out.append([getattr(mine, f).copy() for f in fields])
        except np.linalg.LinAlgError as err:
            out.append(str(err))
        finally:
            identifier.COMPILED = kernels_identifier.AVAILABLE
    return out


def assert_same(compiled, numpy, fields: tuple[str, ...] = FIELDS) -> None:
    assert type(compiled) is type(numpy)
    if isinstance(numpy, str):
        assert compiled == numpy
        return
    for name, a, b in zip(fields, compiled, numpy):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name


@pytest.mark.parametrize('seed', range(6))
def test_the_excitation_kernel_is_numpys_on_random_statistics(seed):
    rng = np.random.default_rng(seed)
    ident = random_identifier(7, rng, estimate_coupling=bool(seed % 2))
    ident.statistics[2] = 0.0  # a quiet vehicle: no excitation, infinite uncertainty
    compiled, numpy = both_ways(ident, None)
    assert_same(compiled, numpy)
    assert np.all(compiled[0][2] == 0.0) and np.isfinite(compiled[1]).any()
    assert set(np.unique(compiled[2])) >= {0, 1}  # (both verdicts reached)
    assert_same(*both_ways(ident, np.array([True, False, True, True, False, False, True])))


def test_a_broken_vehicle_and_a_singular_covariance_are_handled_as_numpy_does():
    rng = np.random.default_rng(11)
    ident = random_identifier(5, rng)
    stats = ident.statistics
    stats[1, 0, 3] = np.inf  # vehicle 1's statistics overflowed: its estimate is set to NaN
    # vehicle 3: C + w I = 0 on the 3x3 rows: numpy's inv raises for the whole batch, and
    # every vehicle's 3x3 rows keep an infinite uncertainty
    size3 = np.flatnonzero(ROW_SIZE == 3)
    for p in size3:
        for i in range(3):
            for j in range(3):
                q = STAT_PACKED[(p * WIDTH + i) * WIDTH + j]
                stats[3, CROSS, q] = -ident.config.prior_weight if i == j else 0.0
    ident.statistics = stats
    compiled, numpy = both_ways(ident, None)
    assert_same(compiled, numpy)
    _, uncertainty, _, _, theta = compiled
    assert np.isnan(theta[1]).all() and np.isfinite(np.delete(theta, 1, axis=0)).all()
    assert np.all(np.isinf(uncertainty[np.ix_([0, 2, 3, 4], size3)]))
    assert np.isfinite(uncertainty[np.ix_([0, 2, 4], np.flatnonzero(ROW_SIZE == 5))]).all()


@pytest.mark.parametrize('seed', range(4))
def test_the_solve_kernel_is_numpys_on_random_statistics(seed):
    rng = np.random.default_rng(100 + seed)
    ident = random_identifier(6, rng, estimate_coupling=bool(seed % 2))
    ident.rhs = rng.standard_normal(ident.rhs.shape) * 10.0 ** rng.uniform(-3, 2)
    compiled, numpy = both_ways(ident, None, '_solve', SOLVED)
    assert_same(compiled, numpy, SOLVED)
    assert not np.array_equal(compiled[1], ident.theta)  # (it solved something)
    which = np.array([False, True, True, False, True, False])
    assert_same(*both_ways(ident, which, '_solve', SOLVED), SOLVED)


def test_a_singular_system_raises_for_the_batch_as_numpy_does():
    rng = np.random.default_rng(5)
    ident = random_identifier(4, rng)
    stats = ident.statistics
    for i in range(WIDTH):  # vehicle 2's z row: C = -w I, so C + w I = 0
        for j in range(WIDTH):
            q = STAT_PACKED[(3 * WIDTH + i) * WIDTH + j]
            if q >= 0:
                stats[2, CROSS, q] = -ident.config.prior_weight if i == j else 0.0
    ident.statistics = stats
    compiled, numpy = both_ways(ident, None, '_solve', SOLVED)
    assert compiled == numpy == 'Singular matrix'
    assert_same(*both_ways(ident, np.array([True, True, False, True]), '_solve', SOLVED), SOLVED)


BOTH_WAYS = r'''
import sys
from pathlib import Path

import numpy as np

from cloe_ros.core import identifier
from test.golden_outputs import check_pinned_kernels, golden_outputs

check_pinned_kernels()
assert identifier.COMPILED
compiled = golden_outputs(Path(sys.argv[1]))
identifier.COMPILED = False
numpy = golden_outputs(Path(sys.argv[1]))
bad = [k for k in numpy if not np.array_equal(compiled[k], numpy[k], equal_nan=True)]
assert not bad, bad
print('ok')
'''


@pytest.mark.parametrize('bag', ['position', 'trajectory'])
def test_the_excitation_kernel_is_numpys_on_recorded_flights(bag):
    done = run_pinned_script(BOTH_WAYS, str(REPO / 'bags' / bag))
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr[-3000:]
