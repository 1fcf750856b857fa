"""The command lines of the benchmark scripts: a bad argument is an argparse error (usage, one
``error:`` line, exit status 2) before any work, never a traceback from the run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ('args', 'expected'),
    [
        (['--offline', '/nonexistent'], '--offline /nonexistent does not exist'),
        (['--offline', str(ROOT / 'bags' / 'position'), '--repeat', '0'],
         '--repeat must be at least 1, got 0'),
        (['--repeat', '-1'], '--repeat must be at least 1, got -1'),
        (['--shards', '0'], '--shards must be at least 1, got 0'),
    ],
)  # fmt: skip
def test_swarm_benchmark_refuses_bad_arguments(args, expected):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, str(ROOT / 'scripts' / 'swarm_benchmark.py'), *args],
                          env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert 'Traceback' not in proc.stderr
    assert proc.stderr.splitlines()[-1] == f'swarm_benchmark.py: error: {expected}'
