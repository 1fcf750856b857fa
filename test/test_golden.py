"""The engine's published numbers on the sample bags and the corpus equal the golden ones
(scripts/golden.py wrote them from the engine before the lean codecs and the faster
anticipation) to 1e-9: the state and ``cloe/parameters`` of every 50th estimate, the predicted
positions and radii at 0.5 to 10 s of every 5th prediction, the counts, and sums over the whole
run. A change meant to move the numbers rewrites them (``python scripts/golden.py write``) and
says so in its commit.

Both sides are computed with pinned numeric kernels (test/golden_outputs.py): numpy's and
OpenBLAS's own choice of kernels per CPU moves ``cloe/parameters`` by up to 3e-8, which would make
the test's outcome depend on the machine it runs on."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core import ahead
from test.golden_outputs import (
    GOLDEN,
    PINNED_KERNELS,
    bags,
    compare,
    pinned_golden_outputs,
    run_golden_process,
)

BAGS = bags()


@pytest.mark.slow
@pytest.mark.parametrize('bag', BAGS, ids=[b.name for b in BAGS])
def test_published_numbers_equal_the_golden_ones(bag):
    golden = GOLDEN / f'{bag.name}.npz'
    assert golden.is_file(), f'no golden outputs for {bag.name}: python scripts/golden.py write'
    want = dict(np.load(golden))
    got = pinned_golden_outputs(bag)
    # (the kernels a user's process runs: the ones built ahead where they were built)
    assert bool(got['kernels_ahead']) == ahead.module_path().is_file()
    errors = compare(want, got)
    assert want['counts'][1] > 0  # the bag has predictions to compare
    bad = {key: err for key, err in errors.items() if not err <= 1e-9}
    assert not bad, bad


@pytest.mark.slow
@pytest.mark.parametrize('env', [{'CLOE_ROS_KERNELS': 'jit'}, {'CLOE_ROS_CHECK_KERNELS': '1'}],
                         ids=['numba-jit', 'built-ahead-checked'])  # fmt: skip
def test_numba_jit_and_the_checked_kernels_built_ahead_give_the_golden_numbers(env):
    """The same numbers from numba's JIT (the package's kernels where none were built ahead), and
    from the kernels built ahead with every call's arguments checked against the kernel's
    signature, as numba's dispatcher checks them (a call of other types would be refused)."""
    ahead_wanted = 'CLOE_ROS_KERNELS' not in env
    if ahead_wanted and not ahead.module_path().is_file():
        pytest.skip('the kernels were not built ahead here (python -m cloe_ros.core.ahead)')
    bag = BAGS[0]
    want = dict(np.load(GOLDEN / f'{bag.name}.npz'))
    got = pinned_golden_outputs(bag, **env)
    assert bool(got['kernels_ahead']) == ahead_wanted
    bad = {key: err for key, err in compare(want, got).items() if not err <= 1e-9}
    assert not bad, bad


def test_the_golden_process_refuses_kernels_that_are_not_pinned():
    # OpenBLAS's Core2 kernels run on every CPU numpy 2.4 runs on, and are not the pinned ones
    kernels = {**PINNED_KERNELS, 'OPENBLAS_CORETYPE': 'Core2'}
    run = run_golden_process('no-bag', 'no-out.npz', kernels, capture_output=True, text=True)
    assert run.returncode != 0
    assert 'the kernels are not pinned' in run.stderr
