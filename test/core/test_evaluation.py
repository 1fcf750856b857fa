"""Scoring helpers of cloe_ros.core.evaluation on hand-built runs whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from cloe_ros.core.evaluation import Run, score_positions, status_calibration
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


def test_score_positions_against_closed_form():
    """Vehicles flying 1 m/s along x from the origin, predicted off by known amounts in y: the
    model's RMSE, the exact constant-velocity baseline, hold position off by the lead; a missing
    pose, outcome or start leaves that prediction out of that horizon only (start: of all)."""
    lead = np.tile([1.0, 2.0], (4, 1))
    start = np.zeros((4, 12))
    start[:, 1] = 1.0  # vx
    start[3, 6] = np.nan  # no start state: never scored
    actual = np.zeros((4, 2, 3))
    actual[..., 0] = lead
    predicted = actual.copy()
    predicted[..., 1] = [[0.3, 0.6], [0.4, 0.8], [np.nan, 1.0], [0.0, 0.0]]
    actual[1, 1] = np.nan  # the second vehicle's outcome at 2 s is unknown
    score = score_positions((1.0, 2.0), predicted, actual, start, lead, actual.copy(),
                            withheld=5, t_from=1.0, t_to=9.0)  # fmt: skip
    expected = [np.sqrt((0.3**2 + 0.4**2) / 2), np.sqrt((0.6**2 + 1.0**2) / 2)]
    np.testing.assert_allclose(score.model, expected, rtol=1e-12)
    assert score.count.tolist() == [2, 2]
    np.testing.assert_allclose(score.constant_velocity, 0.0, atol=1e-15)
    np.testing.assert_allclose(score.hold_position, [1.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(score.true_model, 0.0, atol=1e-15)
    np.testing.assert_allclose(score.model_per_axis[:, 1], expected, rtol=1e-12)
    np.testing.assert_allclose(score.model_per_axis[:, [0, 2]], 0.0, atol=1e-15)
    assert (score.withheld, score.t_from, score.t_to) == (5, 1.0, 9.0)
    none = score_positions((1.0, 2.0), np.zeros((0, 2, 3)), np.zeros((0, 2, 3)),
                           np.zeros((0, 12)), np.zeros((0, 2)))  # fmt: skip
    assert none.count.tolist() == [0, 0] and np.isnan(none.model).all()
    assert none.true_model is None and np.isnan(none.model_per_axis).all()
