"""Test-wide settings: DDS on this machine only, a domain id of our own, rcl logs out of ~/.ros.

Every test process holds DDS domains no other process on the machine holds
(:func:`~cloe_ros.cli.processes.reserve_domain_id`, a lock file per id): with ``pytest -n N``
(pytest-xdist, as ``make test`` runs it) each worker process imports this file and so reserves its
own ``ROS_DOMAIN_ID`` for the contexts its in-process tests create, and process-level tests
reserve one more each (``private_domain``, ``reserve_domain_id``), given back when the test ends.
Two workers, or two suites run side by side from different work trees, never see each other's
nodes.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from cloe_ros.core import ahead

# numba's JIT in the suite's own processes, whose tests call the kernels' helpers (only the JIT
# compiles a helper alone); the processes they start run the kernels built ahead, as users do
ahead.select('jit')

import pytest  # noqa: E402
from ros_helpers import release_test_domains  # noqa: E402

from cloe_ros.cli.processes import reserve_domain_id  # noqa: E402
from cloe_ros.threads import limit_blas_threads  # noqa: E402

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
#: This process's domain: the xdist controller's, or one worker's (``PYTEST_XDIST_WORKER``).
DOMAIN_ID = reserve_domain_id()
os.environ['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
os.environ.setdefault('ROS_LOG_DIR', os.path.join(tempfile.gettempdir(), 'cloe_ros_test_logs'))
os.environ.setdefault('MPLBACKEND', 'Agg')
# one BLAS thread, as in the package's processes (their children inherit it): the parallel
# workers' spinning BLAS threads would otherwise take each other's cores
limit_blas_threads()


def pytest_report_header(config) -> str:
    worker = os.environ.get('PYTEST_XDIST_WORKER', 'main process')
    return f'ROS_DOMAIN_ID {DOMAIN_ID} ({worker}); each process-level test reserves its own'


def pytest_collection_modifyitems(config, items) -> None:
    """Modules with a test of the slow tier first (each module kept together, so its module
    fixtures are made once per worker), in collection order, then the rest: the parallel workers
    start on the long tests and the short ones fill in around them, instead of one long test
    ending the run alone."""
    slow_modules = {item.module for item in items if item.get_closest_marker('slow')}
    items.sort(key=lambda item: item.module not in slow_modules)


@pytest.fixture(autouse=True)
def _release_domains():
    """The domains a test reserved are given back when it ends (its nodes are stopped by then)."""
    yield
    release_test_domains()


#: What :func:`infer_in_a_fresh_process` runs: ``cloe infer`` on a bag in a new interpreter,
#: then prints its exit status and the names of the modules that process imported.
_FRESH_INFER = """import json, sys
from cloe_ros.cli.main import main
code = main(['infer', '-q', sys.argv[1], '-o', sys.argv[2]])
print(json.dumps([code, sorted(sys.modules)]))
"""


@pytest.fixture(scope='session')
def infer_in_a_fresh_process(tmp_path_factory) -> tuple[int, frozenset[str], Path]:
    """``cloe infer bags/position`` as a user's run makes it, in a new interpreter (once per test
    process): its exit status, the modules it imported, and its output bag. For the tests that
    check what a run imports (on the modules, not on time)."""
    import json
    import subprocess

    root = Path(__file__).resolve().parents[1]
    out = tmp_path_factory.mktemp('fresh_infer') / 'out'
    env = dict(os.environ, PYTHONPATH=str(root))
    proc = subprocess.run([sys.executable, '-c', _FRESH_INFER, str(root / 'bags' / 'position'),
                           str(out)], env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    code, modules = json.loads(proc.stdout.strip().splitlines()[-1])
    return code, frozenset(modules), out
