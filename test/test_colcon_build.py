"""The package builds with colcon into an install space that `ros2 run` can use."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
EXECUTABLES = ('quadrotor_sim', 'cloe_inference', 'bag_recorder', 'bag_player', 'cloe')


@pytest.mark.slow
def test_colcon_build_gives_the_ament_layout(tmp_path):
    build = subprocess.run(
        [sys.executable, '-m', 'colcon', 'build', '--base-paths', str(REPO),
         '--build-base', str(tmp_path / 'build'), '--install-base', str(tmp_path / 'install'),
         '--event-handlers', 'console_direct-'],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout + build.stderr
    prefix = tmp_path / 'install' / 'cloe_ros'
    # what `ros2 run cloe_ros <exe>` looks for: <prefix>/lib/<package>/<exe>, executable
    for name in EXECUTABLES:
        exe = prefix / 'lib' / 'cloe_ros' / name
        assert exe.is_file() and os.access(exe, os.X_OK), name
    assert (
        prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'cloe_ros'
    ).is_file()
    assert (prefix / 'share' / 'cloe_ros' / 'package.xml').is_file()
    assert {p.name for p in (prefix / 'share' / 'cloe_ros' / 'config').iterdir()} >= {
        'inference.yaml',
        'sim.yaml',
    }
    # the ament index finds the package, and an installed executable runs from the install space
    site = next(prefix.glob('lib/python3*/site-packages'))
    env = dict(os.environ, AMENT_PREFIX_PATH=str(prefix), PYTHONPATH=str(site))
    found = subprocess.run(
        [sys.executable, '-c', 'from ament_index_python.packages import '
         "get_package_share_directory as g; print(g('cloe_ros'))"],
        env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert found.returncode == 0, found.stderr
    assert Path(found.stdout.strip()) == prefix / 'share' / 'cloe_ros'
    run = subprocess.run(
        [str(prefix / 'lib' / 'cloe_ros' / 'cloe'), '--version'],
        env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0 and run.stdout.startswith('cloe '), run.stderr
    imported = subprocess.run(
        [sys.executable, '-c', 'import cloe_ros; print(cloe_ros.__file__)'],
        env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert imported.stdout.strip().startswith(str(site)), imported.stdout
