"""numpy's own BLAS and LAPACK, called from compiled kernels, as numpy calls them.

A compiled kernel that replaces numpy code holds the golden test only if it gives bitwise
numpy's values. For products and solves that numpy hands to BLAS and LAPACK, an equivalent
loop is not enough (OpenBLAS sums in its own blocked order, and LAPACK's pivoting and
decompositions are not reproduced by small-matrix code: EVALUATION.md, section 4). So the
kernels call the very routines numpy calls, in the library numpy loaded, with the arguments
numpy passes:

* :func:`matmul` is ``a @ b`` of two 2-D arrays: numpy's dispatch (``dot`` for a row times a
  column, ``gemv`` for a matrix times a vector, ``syrk`` for a matrix times its own transpose,
  ``gemm`` otherwise, its plain loop where BLAS cannot take the strides);
* :func:`solve` is ``np.linalg.solve`` (``dgesv`` on Fortran-ordered copies);
* :func:`lstsq` is ``np.linalg.lstsq(a, b, rcond=None)`` (``dgelsd``, with numpy's workspace
  query and default ``rcond``);
* :func:`inv` is ``np.linalg.inv`` (``dgesv`` on the identity), :func:`eigh` is
  ``np.linalg.eigh`` (``dsyevd``, eigenvectors, lower triangle) and :func:`svd_values` is
  ``np.linalg.svd(a, compute_uv=False)`` (``dgesdd``, values only), each with numpy's workspace
  query (:func:`eigh_workspace`, :func:`svd_workspace`: once per size, as numpy makes it once per
  call).

The routines are found by name in numpy's OpenBLAS (the ``scipy-openblas64`` library of
numpy's wheels: symbols ``scipy_<name>64_``, 64-bit integers). :data:`AVAILABLE` says whether
they were; where they were not (a numpy built against another BLAS), the kernels that need
them are not defined and the package runs its numpy code instead.

This module finds the library and imports no numba; the functions above, and the routines'
declarations for numba, are :mod:`~cloe_ros.core.blas_kernels`', reached through this module
(``blas.matmul``) and imported on the first such use, by numba's JIT or the build of the
kernels ahead (:mod:`~cloe_ros.core.ahead`). A process that runs the kernels built ahead
never imports it: the built module calls the library by name.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os

import numpy as np

PREFIX, SUFFIX = 'scipy_', '64_'
#: The Fortran routines and CBLAS functions the kernels call.
ROUTINES = ('dgesv', 'dgelsd', 'dsyevd', 'dgesdd', 'cblas_dgemv', 'cblas_dgemm', 'cblas_dsyrk',
            'cblas_ddot')


def _find_library() -> str | None:
    """The path of numpy's OpenBLAS if it holds every routine of :data:`ROUTINES` by the names
    numpy's wheels give them, else None."""
    here = os.path.dirname(np.__file__)
    for path in sorted(glob.glob(os.path.join(here, os.pardir, 'numpy.libs',
                                              'libscipy_openblas64_*'))):  # fmt: skip
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        if all(hasattr(lib, symbol(name)) for name in ROUTINES):
            return os.path.abspath(path)
    return None


def symbol(name: str) -> str:
    """The exported name of routine ``name`` (``dgesv``, ``cblas_dgemm``) in numpy's OpenBLAS."""
    return f'{PREFIX}{name}{SUFFIX}' if name.startswith('cblas_') else f'{PREFIX}{name}_{SUFFIX}'


LIBRARY = _find_library()
#: Whether the kernels can call numpy's BLAS and LAPACK (see the module docstring).
AVAILABLE = LIBRARY is not None and os.environ.get('CLOE_ROS_NO_BLAS_KERNELS', '') in ('', '0')


@functools.cache
def link_for_numba() -> None:
    """Make :data:`LIBRARY` known to numba's linker (llvmlite), once per process: a kernel that
    calls it, compiled or loaded from numba's cache, is linked to its routines by name."""
    import llvmlite.binding

    llvmlite.binding.load_library_permanently(LIBRARY)


def __getattr__(name: str):
    """The helpers and constants of :mod:`~cloe_ros.core.blas_kernels`, imported when one is
    first asked for (a kernel compiling, a test): importing this module imports no numba."""
    from cloe_ros.core import ahead

    if AVAILABLE and ahead.MODULE is None and not name.startswith('__'):
        from cloe_ros.core import blas_kernels

        if hasattr(blas_kernels, name):
            return getattr(blas_kernels, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
