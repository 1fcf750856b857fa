"""Scoring helpers of cloe_ros.core.evaluation on hand-built runs whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.evaluation import Run, status_calibration
from cloe_ros.core.identifier import CONVERGING, IDENTIFIED, N_ROWS, ROW_NAMES
from cloe_ros.core.model import BLOCK_SLICES, BLOCKS


def hand_run(theta_hat: np.ndarray, status: np.ndarray | None) -> Run:
    n = len(theta_hat)
    return Run(
        algorithm='cloe_iv', t=np.arange(n) * 0.1, theta_hat=theta_hat,
        coupling=np.zeros((n, 2)), gain_l=np.zeros((n, 12)), status=status, excitation=None,
        pred_t=np.zeros(0), pred_states=[], pred_zeta0=np.zeros((0, 12)),
        pred_ref=np.zeros((0, 4)), pred_status=[], withheld=0, engine=None,
    )  # fmt: skip


def test_status_calibration_counts_identified_estimates_that_are_wrong():
    theta_true = np.arange(1.0, 17.0)
    theta_hat = np.tile(theta_true, (10, 1))
    status = np.full((10, N_ROWS), CONVERGING, dtype=np.int8)
    x = BLOCK_SLICES[0]
    row_x = ROW_NAMES.index(BLOCKS[0].name)
    # x block: 20 % off for the first 4 samples, then exact; said identified from sample 2 on
    theta_hat[:4, x] *= 1.2
    status[2:, row_x] = IDENTIFIED
    # z block: always identified, 5 % off (below the 10 % line)
    z = BLOCK_SLICES[3]
    theta_hat[:, z] *= 1.05
    status[:, ROW_NAMES.index(BLOCKS[3].name)] = IDENTIFIED
    result = status_calibration(hand_run(theta_hat, status), theta_true)
    assert result[BLOCKS[0].name]['identified'] == pytest.approx(0.8)
    assert result[BLOCKS[0].name]['identified_but_wrong'] == pytest.approx(0.2)
    assert result[BLOCKS[0].name]['max_error_identified'] == pytest.approx(0.2)
    assert result[BLOCKS[3].name]['identified'] == pytest.approx(1.0)
    assert result[BLOCKS[3].name]['identified_but_wrong'] == 0.0
    assert result[BLOCKS[3].name]['max_error_identified'] == pytest.approx(0.05)
    # never identified: no error to report
    assert result[BLOCKS[1].name]['identified'] == 0.0
    assert np.isnan(result[BLOCKS[1].name]['max_error_identified'])


def test_status_calibration_needs_an_identifier():
    with pytest.raises(ValueError, match='no identifier status'):
        status_calibration(hand_run(np.zeros((3, 16)), None), np.ones(16))
