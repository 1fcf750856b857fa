"""The compiled kernels built ahead of time, into one extension module: a process that finds it
imports neither numba nor the kernels' cached machine code.

numba's cache (:class:`~cloe_ros.core.kernels.Compiler`) spares a process the compile, not the
load: with it, ``cloe infer``'s imports took 2.7 s of CPU on a slow 2-core host, 1.1 s with the
module built ahead (EVALUATION.md, section 4), on a run of 4-5 s in all. ``python -m
cloe_ros.core.ahead`` compiles the same kernels from the same source with numba's ahead-of-time
compiler (``numba.pycc``) into one extension module beside them (``make install`` runs it for
the installed package and for the work tree). A process imports it in under a millisecond.

Which kernels a process runs, chosen when this module is first imported:

* by default, the module built ahead, if one was built from these very sources (its name holds a
  hash of them: :func:`module_name`) and it loads; else numba's JIT with its cache, as without
  it. A module that is there but does not load is said once, in a warning;
* with ``CLOE_ROS_KERNELS=jit``, numba's JIT with its cache, always (:func:`select` does the
  same in a process that has not imported the kernels yet: the test suite's own process, whose
  tests call the helpers, which only numba's JIT compiles alone).

Both are the same Python compiled by the same numba, with the same options (no fast-math,
numpy's error model); the built module targets the generic x86-64, and neither contracts
arithmetic into fused multiply-adds, so they give the same bits, and the golden test holds in
either (test/test_golden.py runs the module built ahead on every bag, numba's JIT on
``bags/position``).

numba's dispatcher refuses arguments of other types than a kernel's signature; the built
module's functions take them as given. With ``CLOE_ROS_CHECK_KERNELS=1``, each is wrapped in
numba's check of its arguments against its signature, at numba's cost (test/test_golden.py
runs ``bags/position`` so: every call of a whole flight passes the check).

In a process that runs the module built ahead, a helper (:meth:`Compiler.helper
<cloe_ros.core.kernels.Compiler.helper>`) is its Python function, and :mod:`~cloe_ros.core.blas`'
helpers, which call OpenBLAS through numba, are not there.

``numba.pycc`` is pending deprecation in numba; the build needs it, a C compiler and Python's
headers. Where any is missing, the build says so and exits 1, and the package runs numba's JIT.
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib.machinery
import importlib.util
import os
import sys
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: The modules whose kernels are built, and whose source, with the build's (this module) and
#: the OpenBLAS calls' (:mod:`~cloe_ros.core.blas_kernels`), names the built module.
KERNEL_MODULES = ('kernels', 'kernels_combine', 'kernels_covariance', 'kernels_ensemble',
                  'kernels_identifier', 'kernels_models')  # fmt: skip
SOURCES = (*KERNEL_MODULES, 'blas', 'blas_kernels', 'ahead')
PREFIX = '_kernels_ahead_'
MODES = ('', 'jit')


def module_name() -> str:
    """The built module's name: :data:`PREFIX` and a hash of :data:`SOURCES`, so that a module
    built from other sources is never taken for this one."""
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update(name.encode() + b'\0' + (HERE / f'{name}.py').read_bytes() + b'\0')
    return PREFIX + digest.hexdigest()[:16]


def module_path(folder: Path = HERE) -> Path:
    """Where the built module of these sources is (or would be) in ``folder``."""
    return folder / (module_name() + importlib.machinery.EXTENSION_SUFFIXES[0])


def _load():
    """The built module, or None where there is none for these sources, where it needs numpy's
    OpenBLAS and has none (:data:`~cloe_ros.core.blas.AVAILABLE`), or where it does not load
    (with a warning)."""
    from cloe_ros.core import blas

    path = module_path()
    if not blas.AVAILABLE or not path.is_file():
        return None
    try:
        # its calls into OpenBLAS are linked by name when it loads: the library's symbols go
        # into the process's global scope first (numpy loaded it for itself alone)
        ctypes.CDLL(blas.LIBRARY, mode=os.RTLD_GLOBAL)
        spec = importlib.util.spec_from_file_location(f'cloe_ros.core.{path.name.split(".")[0]}',
                                                      path)  # fmt: skip
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (ImportError, OSError) as err:
        warnings.warn(f'cloe_ros: the kernels built ahead ({path.name}) do not load ({err}); '
                      'numba compiles or loads them instead', RuntimeWarning,
                      stacklevel=2)  # fmt: skip
        return None
    return module


def _mode() -> str:
    mode = os.environ.get('CLOE_ROS_KERNELS', '')
    if mode not in MODES:
        raise ValueError(f'CLOE_ROS_KERNELS={mode!r}: expected unset, empty or "jit"')
    return mode


#: Whether this process is the build (``python -m cloe_ros.core.ahead``): the kernels register
#: themselves (:func:`register`) as they compile (numba's JIT, its cache filled on the way).
BUILDING = False
#: The built module this process runs, or None (numba's JIT).
MODULE = None if _mode() == 'jit' else _load()
#: Whether each function is wrapped in a check of its arguments (``CLOE_ROS_CHECK_KERNELS=1``).
CHECK = os.environ.get('CLOE_ROS_CHECK_KERNELS', '') not in ('', '0')
#: The build's kernels: (module, name, signature, Python function), in the order decorated.
REGISTERED: list[tuple[str, str, object, object]] = []


def select(mode: str) -> None:
    """Run ``mode``'s kernels (``'jit'``: numba's, ``''``: the default) in this process. Only
    before any kernel module is imported: the kernels are bound when their module runs."""
    global MODULE
    _refuse_after_import(f'select({mode!r})')
    if mode not in MODES:
        raise ValueError(f'kernels {mode!r}: expected "" or "jit"')
    MODULE = None if mode == 'jit' else _load()


def _refuse_after_import(what: str) -> None:
    """A RuntimeError naming ``what`` where a kernel module was imported already (its kernels
    were bound then)."""
    loaded = [name for name in KERNEL_MODULES if f'cloe_ros.core.{name}' in sys.modules]
    if loaded:
        raise RuntimeError(f'{what} after the kernels were imported ({loaded})')


def function(module: str, name: str, signature):
    """The built module's kernel ``name`` of ``module`` (``kernels_models``), checked against
    ``signature`` under :data:`CHECK`."""
    kernel = getattr(MODULE, f'{module}__{name}')
    return _checked(kernel, signature, f'{module}.{name}') if CHECK else kernel


def _checked(kernel, signature, name: str):
    """``kernel`` behind numba's check of its arguments' types against ``signature``: a
    TypeError where numba's dispatcher would refuse them."""
    import functools

    from numba import typeof
    from numba.core import sigutils
    from numba.core.typing import Context

    expected, _ = sigutils.normalize_signature(signature)
    context = Context()

    @functools.wraps(kernel)
    def call(*args):
        if len(args) != len(expected):
            raise TypeError(f'{name}: {len(args)} arguments, expected {len(expected)}')
        for i, (arg, want) in enumerate(zip(args, expected)):
            got = typeof(arg)
            if context.can_convert(got, want) is None:
                raise TypeError(f'{name}: argument {i} is {got}, expected {want}')
        return kernel(*args)

    return call


def register(module: str, func, signature) -> None:
    """In the build, record a kernel Python calls."""
    REGISTERED.append((module, func.__name__, signature, func))


def build(folder: Path = HERE, *, verbose: bool = False) -> Path:
    """Compile the kernels of :data:`KERNEL_MODULES` into the module :func:`module_path` names
    in ``folder``, replacing any older build there; returns its path. In a process that has
    imported no kernel module yet (:data:`BUILDING` makes their decorators register them)."""
    import shutil
    import tempfile

    global BUILDING, MODULE
    _refuse_after_import('build()')
    from cloe_ros.core import blas

    if not blas.AVAILABLE:
        raise RuntimeError('numpy has no OpenBLAS the kernels can call (cloe_ros.core.blas): '
                           'nothing to build; the package runs its numpy code')  # fmt: skip
    BUILDING, MODULE = True, None
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')  # (numba.pycc's pending deprecation)
        from numba.pycc import CC, compiler

    for name in KERNEL_MODULES:
        importlib.import_module(f'cloe_ros.core.{name}')
    target = module_path(folder)
    stem = target.name.split('.')[0]  # (module_name(), without hashing the sources again)
    cc = CC(stem)
    cc.verbose = verbose
    for module, name, signature, func in REGISTERED:
        cc.export(f'{module}__{name}', signature)(func)

    class Flags(compiler.Flags):
        """numba's flags for the build, with the kernels' error model (``x / 0`` is inf or
        nan, as under :class:`~cloe_ros.core.kernels.Compiler`)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.error_model = 'numpy'

    compiler.Flags = Flags
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        cc.output_dir = tmp
        cc.compile()
        (built,) = Path(tmp).glob(f'{stem}*')
        shutil.move(built, target)  # (one rename: a process starting now loads all or none)
    for old in folder.glob(f'{PREFIX}*'):
        if old != target:
            old.unlink()
    return target


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog='python -m cloe_ros.core.ahead',
        description="Compile the package's kernels ahead of time into one extension module "
                    'beside them: its processes then import neither numba nor its cache.')
    parser.add_argument('--verbose', action='store_true', help="the compiler's commands")
    args = parser.parse_args(argv)
    try:
        path = build(verbose=args.verbose)
    except Exception as err:  # (no pycc, no compiler, no headers: the JIT serves)
        print(f'cloe_ros: the kernels were not built ahead ({type(err).__name__}: {err}); '
              "the package runs numba's JIT instead", file=sys.stderr)  # fmt: skip
        return 1
    print(f'built {path}')
    return 0


if __name__ == '__main__':
    from cloe_ros.core import ahead as _ahead  # (the module, not this __main__ copy)

    sys.exit(_ahead.main())
