"""One BLAS thread in the package's processes, unless the user set the threads."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from cloe_ros.threads import BLAS_THREAD_VARIABLES

PROBE = """
import json, os, numpy
from threadpoolctl import threadpool_info
from cloe_ros.threads import limit_blas_threads
set_it = limit_blas_threads()
print(json.dumps({'set': set_it, 'env': os.environ.get('OPENBLAS_NUM_THREADS'),
                  'threads': [i['num_threads'] for i in threadpool_info()
                              if i['user_api'] == 'blas']}))
"""


def probe(**env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run(
        [sys.executable, '-c', PROBE], env={**clean, **env}, capture_output=True, text=True,
        check=True, timeout=120,
    )  # fmt: skip
    return json.loads(out.stdout.splitlines()[-1])


def test_blas_runs_on_one_thread_and_the_processes_started_later_inherit_it():
    got = probe()
    assert got['set'] is True
    assert got['threads'] and set(got['threads']) == {1}  # numpy's OpenBLAS, loaded before
    assert got['env'] == '1'  # for BLAS libraries loaded later, and child processes


@pytest.mark.parametrize('variable', BLAS_THREAD_VARIABLES)
def test_threads_the_user_chose_are_left_as_they_are(variable):
    got = probe(**{variable: '2'})
    assert got['set'] is False
    assert got['env'] == ('2' if variable == 'OPENBLAS_NUM_THREADS' else None)
