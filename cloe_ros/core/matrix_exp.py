"""``scipy.linalg.expm``'s values, bit for bit, without importing ``scipy.linalg``.

:func:`~cloe_ros.core.model.discretise` needs the matrix exponential, and it needs scipy's bits.
The golden test holds the engine's numbers to 1e-9, and the identifier carries a last-bit
difference past that: a Padé 13 exponential in numpy that agrees with scipy's to 5e-13 moved
them by up to 4e-9 (EVALUATION.md, section 4). Importing ``scipy.linalg`` costs 0.35-0.4 s of
CPU, a third of what ``cloe infer`` and the inference node import.

scipy's ``expm`` is Python around the two compiled routines of its extension module
``scipy.linalg._matfuncs_expm``: the Padé degree and scaling (``pick_pade_structure``), and the
approximant (``pade_UV_calc``). That extension needs nothing of ``scipy.linalg`` but its own
OpenBLAS. :func:`expm` loads it by itself and runs the same steps around it as scipy's ``expm``
of the scipy versions in :data:`CHECKED_SCIPY`. test/core/test_matrix_exp.py compares the bits
with ``scipy.linalg.expm`` on the models the engine discretises, dense, triangular, diagonal and
non-finite matrices, alone and batched. With another scipy, or without that extension where scipy
keeps it, :func:`expm` is ``scipy.linalg.expm`` itself.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

__all__ = ['CHECKED_SCIPY', 'expm']

#: scipy releases (major, minor) whose ``expm`` the steps of :func:`_expm` are.
CHECKED_SCIPY = ((1, 17),)
_EXTENSION = 'scipy.linalg._matfuncs_expm'


@cache
def _core():
    """scipy's compiled routines ``(pick_pade_structure, pade_UV_calc)``, or None where this
    scipy is not one of :data:`CHECKED_SCIPY` or its extension cannot be loaded by itself."""
    try:
        release = tuple(int(p) for p in version('scipy').split('.')[:2])
        spec = importlib.util.find_spec('scipy')  # (finds the package, imports nothing)
    except (PackageNotFoundError, ValueError, ImportError):
        return None
    if release not in CHECKED_SCIPY or spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(next(iter(spec.submodule_search_locations))) / 'linalg'
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = folder / f'_matfuncs_expm{suffix}'
        if path.is_file():
            module_spec = importlib.util.spec_from_file_location(_EXTENSION, path)
            try:
                module = importlib.util.module_from_spec(module_spec)
                module_spec.loader.exec_module(module)
                return module.pick_pade_structure, module.pade_UV_calc
            except (ImportError, AttributeError, OSError):
                return None
    return None


def expm(a: np.ndarray) -> np.ndarray:
    """The exponential of the square matrices ``a`` (..., n, n), float64: the values of
    ``scipy.linalg.expm(a)``, bit for bit."""
    core = _core()
    a = np.asarray(a)
    square = a.ndim >= 2 and a.shape[-1] == a.shape[-2] >= 2 and a.size
    if core is None or not square or a.dtype != np.float64:
        from scipy.linalg import expm as scipy_expm  # (what the steps below do not cover)

        return scipy_expm(a)
    return _expm(a, *core)


def _bandwidth(a: np.ndarray) -> tuple[int, int]:
    """``scipy.linalg.bandwidth``: the lower and upper bandwidth of the square ``a`` (the most
    diagonals below and above the main one holding a nonzero, NaN counting as one)."""
    rows, cols = np.nonzero(a)
    offsets = rows - cols
    return int(max(offsets.max(initial=0), 0)), int(max(-offsets.min(initial=0), 0))


def _exp_sinch(x: np.ndarray) -> np.ndarray:
    """Higham's formula (10.42), as scipy's ``expm`` computes it."""
    lexp_diff = np.diff(np.exp(x))
    l_diff = np.diff(x)
    mask_z = l_diff == 0.0
    lexp_diff[~mask_z] /= l_diff[~mask_z]
    lexp_diff[mask_z] = np.exp(x[:-1][mask_z])
    return lexp_diff


def _expm(a: np.ndarray, pick_pade_structure, pade_uv_calc) -> np.ndarray:
    """The steps of scipy's ``expm`` (scipy/linalg/_matfuncs.py) for float64 (..., n, n),
    n >= 2: per matrix, a diagonal one directly, else the scaled Padé approximant from the
    compiled routines, squared back (a triangular one with its diagonal and first off-diagonal
    recomputed at each squaring, Higham's code fragment 2.1)."""
    n = a.shape[-1]
    out = np.empty(a.shape, dtype=a.dtype)
    work = np.empty((5, n, n), dtype=a.dtype)  # the routines' scratch: the powers of A
    for ind in np.ndindex(a.shape[:-2]):
        aw = a[ind]
        lu = _bandwidth(aw)
        if not any(lu):  # diagonal
            out[ind] = np.diag(np.exp(np.diag(aw)))
            continue
        work[0, :, :] = aw
        m, s = pick_pade_structure(work)
        if m < 0:
            msg = f'the matrix exponential could not allocate its work memory (error {m})'
            raise MemoryError(msg)
        info = pade_uv_calc(work, m)
        if info != 0:
            msg = f'the matrix exponential failed in LAPACK (error {info})'
            raise RuntimeError(msg)
        eaw = work[0]
        if s != 0:
            if lu[1] == 0 or lu[0] == 0:  # lower or upper triangular
                diag_aw = np.diag(aw)
                np.einsum('ii->i', eaw)[:] = np.exp(diag_aw * 2 ** (-s))
                sd = np.diag(aw, k=-1 if lu[1] == 0 else 1)
                for i in range(s - 1, -1, -1):
                    eaw = eaw @ eaw
                    np.einsum('ii->i', eaw)[:] = np.exp(diag_aw * 2.0 ** (-i))
                    exp_sd = _exp_sinch(diag_aw * (2.0 ** (-i))) * (sd * 2 ** (-i))
                    if lu[1] == 0:
                        np.einsum('ii->i', eaw[1:, :-1])[:] = exp_sd
                    else:
                        np.einsum('ii->i', eaw[:-1, 1:])[:] = exp_sd
            else:
                for _ in range(s):
                    eaw = eaw @ eaw
        if lu[0] == 0 or lu[1] == 0:
            out[ind] = np.triu(eaw) if lu[0] == 0 else np.tril(eaw)
        else:
            out[ind] = eaw
    return out
