"""The compiled kernels add in numpy's order: under the golden test's pinned kernels (numpy's
baseline loops, OpenBLAS's Nehalem kernels), a kernel's sums equal numpy's bit for bit, so that
replacing numpy code by a kernel leaves the golden outputs as they were. And they are compiled
once, at import, into a cache that only the package's module uses, or without one where numba
cannot have it."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cloe_ros.core import kernels
from test.golden_outputs import REPO, bags, run_pinned_script

CHECK = r'''
import numpy as np
import pytest
from cloe_ros.core import kernels
from test.golden_outputs import check_pinned_kernels

check_pinned_kernels()
rng = np.random.default_rng(0)
for n in range(1, 30):  # einsum's sum of products, every length the identifier's steps use
    a, b = rng.normal(size=(2, 500, n))
    a[::7, 0] = 0.0
    got = np.array([kernels.einsum_dot(a, p, b, p, 0, n) for p in range(500)])
    assert np.array_equal(got, np.einsum('pj,pj->p', a, b)), n
    assert np.array_equal(got, np.einsum('npj,npj->np', a[None], b[None])[0]), n
    # a span of the rows (its start and length), and rows i of a against rows j of b
    wide_a, wide_b = rng.normal(size=(2, 40, n + 9))
    start = n % 5
    got = [kernels.einsum_dot(wide_a, i, wide_b, 39 - i, start, n) for i in range(40)]
    want = np.einsum('pj,pj->p', wide_a[:, start:start + n], wide_b[::-1, start:start + n])
    assert np.array_equal(got, want), n
omegas = 2.0 * np.pi / np.geomspace(1.5, 30.0, 60)
for v, n in ((1, 10), (7, 33), (20, 61)):  # the intent's harmonic fits: basis and residuals
    t = -np.sort(rng.uniform(0.0, 3.2, size=(v, n)), axis=1)
    y = rng.normal(size=(v, n, 4)) * 30.0
    wt = omegas[None, :, None] * t[:, None, :]
    basis = np.empty((*wt.shape, 3))
    basis[..., 0] = 1.0
    np.cos(wt, out=basis[..., 1])
    np.sin(wt, out=basis[..., 2])
    got = np.empty_like(basis)
    kernels.harmonic_basis(t, omegas, got)
    assert np.array_equal(got, basis), v
    coef = rng.normal(size=(v, len(omegas), 3, 4))
    resid = np.sum(np.square(basis @ coef - y[:, None]), axis=-2)
    got = np.empty_like(resid)
    kernels.harmonic_residuals(basis, coef, y, got)
    assert np.array_equal(got, resid), v
print('ok')
'''


def test_the_kernels_sums_are_numpys_bit_for_bit_under_the_pin():
    """einsum's sum of products, and the intent's harmonic basis and fit residuals."""
    done = run_pinned_script(CHECK, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr[-2000:]


def test_the_identifiers_step_is_the_numpy_formulas_on_one_vehicle():
    """One vehicle's filter step written out in numpy (the channels, the filter bank's outputs
    and next state, the regressors and the targets) equals the kernel's to round-off, whatever
    the machine (the bitwise equality under the pin is the golden test's)."""
    from cloe_ros.core import identifier as iv

    rng = np.random.default_rng(2)
    zeta0, r0 = rng.normal(size=(1, 12)), rng.normal(size=(1, 4))
    ident = iv.IvIdentifier(iv.IdentifierConfig(), 0.01, zeta0, r0)
    ident._fx[:] = rng.normal(size=ident._fx.shape)  # a state away from rest
    zeta, r = rng.normal(size=(1, 12)), rng.normal(size=(1, 4))
    fx, x_aux = ident._fx.copy(), ident.x_aux.copy()
    x_new = ident._aux_ad[0] @ x_aux[0] + ident._aux_bd[0] @ r[0]
    u = np.concatenate([zeta[0] / iv.STATE_SCALE, r[0] / iv.REFERENCE_SCALE,
                        (x_new - ident._aux_shift[0]) / iv.STATE_SCALE, [0.0]])  # fmt: skip
    f = np.append(fx[0] @ ident._cf + ident._df * u, 0.5)
    d = fx[0] @ ident._cd + ident._dd * u
    w = iv._StepWork.allocate(1)
    kernels.iv_filter(
        zeta, r, np.ones(1, bool), np.array([0.5]), ident._hist_z, ident._hist_r,
        ident._hist_active, ident._hist_next, ident._hist_count, ident._aux_ad, ident._aux_bd,
        ident.x_aux, ident._last_r, ident._aux_shift, ident._fx, ident._cf, ident._df, ident._cd,
        ident._dd, ident._ad_t, ident._bd, iv.STATE_SCALE, iv.REFERENCE_SCALE, *iv.PHI_GATHER,
        *iv.XI_GATHER, ident._mask_flat, iv.Y_F_GATHER_C, iv.Y_F_GATHER_A, iv.Y_D_GATHER_C,
        iv.Y_D_GATHER_A, w.gate, w.weight, 0.01, w.f, w.d, w.phi, w.xi, w.y, w.u, w.x, w.fx,
    )  # fmt: skip
    np.testing.assert_allclose(ident.x_aux[0], x_new, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(w.f[0], f, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(w.d[0], d, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(ident._fx[0], fx[0] @ ident._ad_t + u[:, None] * ident._bd,
                               rtol=1e-14, atol=1e-14)  # fmt: skip
    phi = np.einsum('c,rcw->rw', f, iv.PHI_MAP) * ident._mask
    xi = np.einsum('c,rcw->rw', f, iv.XI_MAP) * ident._mask
    np.testing.assert_allclose(w.phi[0], phi.ravel(), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(w.xi[0], xi.ravel(), rtol=1e-14, atol=1e-14)
    y = f @ iv.Y_F_MAP.T + d @ iv.Y_D_MAP.T
    np.testing.assert_allclose(w.y[0], y, rtol=1e-14, atol=1e-14)
    assert ident._hist_count[0] == 1 and np.array_equal(ident._hist_z[0, 0], zeta[0])


def test_the_kernels_loaded_under_another_name_leave_the_packages_cache_alone(tmp_path):
    """The machine code is cached by the file's path, and its entries name their module: the
    file loaded under another name (a script's importlib) compiles without the cache, so the
    package's own import still loads what is cached (an entry of the other name would fail it)."""
    load = (
        'import importlib.util, sys\n'
        'spec = importlib.util.spec_from_file_location("elsewhere", sys.argv[1])\n'
        'module = importlib.util.module_from_spec(spec)\n'
        'spec.loader.exec_module(module)\n'
    )  # fmt: skip
    # a cache of its own, empty: the first load compiles, and would write its entries there
    env = {**os.environ, 'PYTHONPATH': str(REPO), 'NUMBA_CACHE_DIR': str(tmp_path / 'cache'),
           'CLOE_ROS_KERNELS': 'jit'}  # (numba's JIT and its cache, not the kernels built ahead)
    for code, args in ((load, [kernels.__file__]), ('import cloe_ros.core.kernels', [])):
        done = subprocess.run([sys.executable, '-c', code, *args], env=env, cwd=tmp_path,
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
    assert any((tmp_path / 'cache').rglob('*.nbi'))  # (the package's import did cache)


def test_the_kernels_compile_without_a_cache_where_numba_cannot_have_one(tmp_path):
    """Where numba has no writable folder for its cache (the package read-only, and so the
    user's cache folder), the kernels compile without it, with one warning, instead of failing
    the import (numba raises 'no locator available'). Seen as a user without a writable home
    on a read-only copy of the package; a root test process can write anywhere, so numba's
    refusal is reproduced where it is raised."""
    code = (
        'import warnings\n'
        'from numba.core import dispatcher\n'
        'def refuse(self):\n'
        '    raise RuntimeError("cannot cache function: no locator available for file")\n'
        'dispatcher.Dispatcher.enable_caching = refuse\n'
        'with warnings.catch_warnings(record=True) as caught:\n'
        '    warnings.simplefilter("always")\n'
        '    import cloe_ros.core.kernels as k\n'
        'import numpy as np\n'
        'print(k._compiled.cached, sum("cannot cache" in str(w.message) for w in caught),\n'
        '      k.einsum_dot(np.ones((1, 3)), 0, np.arange(3.0)[None], 0, 0, 3))\n'
    )  # fmt: skip
    env = {**os.environ, 'PYTHONPATH': str(REPO), 'CLOE_ROS_KERNELS': 'jit'}
    done = subprocess.run([sys.executable, '-c', code], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ['False', '1', '3.0']


MODULES = ('kernels', 'kernels_identifier', 'kernels_covariance', 'kernels_ensemble',
           'kernels_combine', 'kernels_models', 'blas_kernels')

LOADED = r'''
import importlib, json, sys
from pathlib import Path

modules = [importlib.import_module(f'cloe_ros.core.{m}') for m in sys.argv[1].split(',')]
kernels = {f'{m.__name__}.{k}': v for m in modules for k, v in vars(m).items()
           if hasattr(v, 'overloads') and v.__module__ == m.__name__}
# a helper is a kernel without a signature of its own: numba may still compile it
helpers = sorted(name for name, k in kernels.items() if k._can_compile)
at_import = {name: len(k.overloads) for name, k in kernels.items()}
from test.golden_outputs import golden_outputs  # a recorded flight (cloe_iv, predictions on)
golden_outputs(Path(sys.argv[2]))
after = {name: len(k.overloads) for name, k in kernels.items()}
print(json.dumps([helpers, at_import, after]))
'''


def kernels_loaded(bag: str) -> tuple[list[str], dict[str, int], dict[str, int]]:
    """In a new process: the helper kernels' names, and how many signatures each kernel has
    compiled or loaded after the import and after ``bag`` ran through the engine."""
    env = {**os.environ, 'PYTHONPATH': str(REPO), 'CLOE_ROS_KERNELS': 'jit'}
    done = subprocess.run([sys.executable, '-c', LOADED, ','.join(MODULES), bag], env=env,
                          cwd=REPO, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    helpers, at_import, after = json.loads(done.stdout.splitlines()[-1])
    return helpers, at_import, after


def test_the_kernels_python_calls_are_compiled_at_import_and_never_at_a_call():
    """Every kernel Python calls has its one signature compiled (or loaded) when its module is
    imported, so no message waits on a compile, and a call with other types is refused rather
    than compiled. The helpers, which only kernels call, are in their callers' machine code:
    the import loads none of them, and neither does a flight through the engine (the package's
    Python code calls no helper, which would compile it there)."""
    with pytest.raises(TypeError):
        kernels.interpolate(np.zeros(3, np.float32), np.zeros((3, 1)), np.zeros(2),
                            np.zeros(1, np.intp), np.zeros((2, 1)))  # fmt: skip
    assert len(kernels.interpolate.overloads) == 1
    helpers, at_import, after_flight = kernels_loaded(str(bags()[0]))
    assert {'cloe_ros.core.kernels.maximum', 'cloe_ros.core.kernels.iv_filter'} <= set(helpers)
    called = set(at_import) - set(helpers)
    assert {'cloe_ros.core.kernels.interpolate', 'cloe_ros.core.kernels.iv_step_filter'} <= called
    assert {name: at_import[name] for name in called} == dict.fromkeys(called, 1)
    assert {name: at_import[name] for name in helpers} == dict.fromkeys(helpers, 0)
    assert after_flight == at_import


FIRST_STEPS = r'''
import json, sys
from cloe_ros.core import covariance
from cloe_ros.core.engine import EngineConfig, VehicleEngine
from cloe_ros.core.estimator import EstimatorConfig
from test.core.test_engine import in_time_order, messages, run, simulated_flight

inputs = in_time_order(*messages(simulated_flight()))[:400]
engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig(algorithm=sys.argv[1])))
made = set(sys.modules)
kernel = covariance._KERNEL
estimates = run(engine, inputs)
print(json.dumps([sorted(m for m in set(sys.modules) - made if m.startswith('cloe_ros')),
                  kernel is not None, len(estimates)]))
'''


@pytest.mark.parametrize('algorithm', ['cloe_iv', 'cloe_sm'])
def test_an_engine_loads_what_its_steps_call_when_it_is_made(algorithm):
    """The estimator's module and the error statistics' kernel are loaded (or compiled, where no
    cache has them) when an engine is made, which a node does before it subscribes, so the first
    message waits on neither: a flight then imports nothing more. (Seen in the node: the first
    odometry imported ``cloe_iv`` and ``kernels_covariance``, a stall of its own on top of the
    start, and a compile of them where the cache was empty.)"""
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    done = subprocess.run([sys.executable, '-c', FIRST_STEPS, algorithm], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    imported, kernel_loaded, estimates = json.loads(done.stdout.splitlines()[-1])
    assert estimates > 100  # (the flight ran through the engine)
    assert imported == []
    assert kernel_loaded
