"""The predictions run compiled (anticipation.COMPILED) give bit for bit what the numpy code
gives: a recorded flight replayed through the engine both ways, under the golden test's pinned
kernels, publishes the same bits (states, parameters, predictions, radii)."""

from __future__ import annotations

import pytest

from cloe_ros.core import anticipation
from test.golden_outputs import REPO, run_pinned_script

BOTH_WAYS = r'''
import sys
from pathlib import Path

import numpy as np

from cloe_ros.core import anticipation, prediction
from test.golden_outputs import check_pinned_kernels, golden_outputs

check_pinned_kernels()
assert anticipation.COMPILED and prediction.COMPILED
compiled = golden_outputs(Path(sys.argv[1]))
anticipation.COMPILED = prediction.COMPILED = False
numpy = golden_outputs(Path(sys.argv[1]))
assert compiled['counts'][1] > 100, compiled['counts']  # (predictions to compare)
bad = [k for k in numpy if not np.array_equal(compiled[k], numpy[k], equal_nan=True)]
assert not bad, bad
print('ok')
'''


@pytest.mark.skipif(not anticipation.COMPILED, reason="numpy's OpenBLAS not found")
@pytest.mark.parametrize('bag', ['position', 'trajectory'])
def test_the_compiled_predictions_are_the_numpy_codes_bit_for_bit(bag):
    done = run_pinned_script(BOTH_WAYS, str(REPO / 'bags' / bag))
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr[-3000:]
