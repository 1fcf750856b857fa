"""The kernels built ahead of time (cloe_ros/core/ahead.py): which kernels a process runs, and
what it does with a build it cannot use. (Their numbers: test/test_golden.py.)"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import cloe_ros
from cloe_ros.core import ahead

REPO = Path(__file__).resolve().parents[2]
BUILT = ahead.module_path().is_file()
needs_build = pytest.mark.skipif(not BUILT, reason='the kernels were not built ahead here '
                                 '(python -m cloe_ros.core.ahead)')  # fmt: skip


def run(code: str, cwd: Path = REPO, **env: str) -> subprocess.CompletedProcess:
    """``python -c code`` with this checkout's package (or ``cwd``'s) and ``env``."""
    environ = {**os.environ, 'PYTHONPATH': str(cwd), **env}
    for name in ('CLOE_ROS_KERNELS', 'CLOE_ROS_CHECK_KERNELS'):
        if name not in env:
            environ.pop(name, None)
    return subprocess.run([sys.executable, '-c', code], env=environ, cwd=cwd,
                          capture_output=True, text=True, timeout=300)  # fmt: skip


@needs_build
def test_a_process_runs_the_kernels_built_ahead_without_importing_numba():
    done = run(
        'import sys\n'
        'from cloe_ros.core import ahead, anticipation, engine, kernels, kernels_models\n'
        'built = ahead.MODULE\n'
        'print(built.__name__, kernels.iv_step_filter is built.kernels__iv_step_filter,\n'
        '      kernels_models.trust_update is built.kernels_models__trust_update,\n'
        '      "numba" in sys.modules)\n'
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == [f'cloe_ros.core.{ahead.module_name()}', 'True', 'True', 'False']


def test_numba_jit_on_request_and_a_wrong_request_refused():
    code = ('from cloe_ros.core import ahead, kernels\n'
            'print(ahead.MODULE, type(kernels.interpolate).__name__)')
    done = run(code, CLOE_ROS_KERNELS='jit')
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ['None', 'CPUDispatcher']
    done = run(code, CLOE_ROS_KERNELS='aot')
    assert done.returncode != 0
    assert "CLOE_ROS_KERNELS='aot': expected unset, empty or \"jit\"" in done.stderr


def test_the_choice_is_made_before_the_kernels_are_imported():
    # (this process's kernels are numba's: test/conftest.py selected them before any import)
    from cloe_ros.core import kernels  # noqa: F401

    with pytest.raises(RuntimeError, match='after the kernels were imported'):
        ahead.select('')
    with pytest.raises(RuntimeError, match='after the kernels were imported'):
        ahead.build()


def test_the_built_module_is_named_by_its_sources(tmp_path, monkeypatch):
    for name in ahead.SOURCES:
        shutil.copy(ahead.HERE / f'{name}.py', tmp_path)
    monkeypatch.setattr(ahead, 'HERE', tmp_path)
    same = ahead.module_name()
    source = tmp_path / 'kernels_models.py'
    source.write_text(source.read_text() + '\n# a change\n')
    changed = ahead.module_name()
    assert same.startswith(ahead.PREFIX) and changed.startswith(ahead.PREFIX)
    assert changed != same
    assert ahead.module_path(tmp_path).name.startswith(changed + '.')


def test_a_built_module_that_does_not_load_is_said_and_numba_runs_instead(tmp_path):
    package = Path(cloe_ros.__file__).parent
    shutil.copytree(package, tmp_path / 'cloe_ros',
                    ignore=shutil.ignore_patterns('__pycache__', f'{ahead.PREFIX}*'))  # fmt: skip
    # a file by the right name that is no library (a copy cut short, another machine's build)
    (tmp_path / 'cloe_ros' / 'core' / ahead.module_path().name).write_bytes(b'\x7fELF cut')
    done = run('import warnings\n'
               'warnings.simplefilter("always")\n'
               'from cloe_ros.core import ahead\n'
               'print(ahead.MODULE)\n', cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ['None']
    assert 'the kernels built ahead' in done.stderr and 'do not load' in done.stderr
    assert 'numba compiles or loads them instead' in done.stderr


@needs_build
def test_checked_kernels_refuse_the_arguments_numba_would_refuse():
    """The built module's functions take arguments as given; checked (the suite's golden run),
    a call of other types than the signature's is a TypeError, as numba's dispatcher makes it."""
    code = (
        'import numpy as np\n'
        'from cloe_ros.core import ahead, kernels\n'
        'zeta, variance, out = np.zeros(12), np.zeros(12), np.zeros(85)\n'
        'kernels.state_message(zeta, variance, True, out)\n'
        'print("ok", ahead.CHECK)\n'
        'kernels.state_message(zeta, variance, True, out.astype(np.float32))\n'
    )  # fmt: skip
    done = run(code, CLOE_ROS_CHECK_KERNELS='1')
    assert done.stdout.split() == ['ok', 'True']
    assert done.returncode != 0
    assert 'TypeError: kernels.state_message: argument 3 is array(float32, 1d, C)' in done.stderr
