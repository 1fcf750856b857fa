"""`cloe evaluate sim|bag`: the identification and prediction scores it prints and writes as JSON.

The numbers are checked against what they must satisfy whatever the method's quality (the
per-axis errors add up to the total; the baselines are what their definitions give), plus the
known answers of the simulator: the identified model converges to its true Θ and, given the
future reference, predicts as well as the true model does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cloe_ros.cli.main import main

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / 'bags'


def check_score(score: dict) -> None:
    """Internal consistency of one prediction table."""
    model = np.array(score['model'])
    per_axis = np.array(score['model_per_axis_xyz'])
    assert score['horizons_s'] == [0.5, 1.0, 2.0, 5.0]
    assert min(score['count']) > 0
    # the 3-D RMSE is the root of the summed per-axis mean squares
    np.testing.assert_allclose(np.sqrt(np.sum(per_axis**2, axis=1)), model, rtol=1e-9)
    assert np.all(np.isfinite(score['constant_velocity']))
    assert np.all(np.isfinite(score['hold_position']))


def test_evaluate_sim_identifies_and_predicts_like_the_true_model(tmp_path, capsys):
    out = tmp_path / 'sim.json'
    args = ['--scenario', 'position', '--duration', '40', '--algorithms', 'cloe_iv']
    status = main(['evaluate', 'sim', *args, '--score-from', '20', '-q', '--json', str(out)])
    printed = capsys.readouterr().out
    assert status == 0
    assert 'parameter error' in printed and 'known future reference' in printed
    result = json.loads(out.read_text())['algorithms']['cloe_iv']
    errors = result['parameter_error']
    assert set(errors) == {'10.0', '20.0', '30.0', '40.0'}  # the table's times and the end
    # every block within 5 % of the simulator's true linearisation after 30 s
    assert max(errors['30.0'][b] for b in ('x_theta', 'y_phi', 'psi', 'z')) < 0.05
    # without noise, a block said to be identified is within 10 % of the truth the whole time
    calibration = result['status_calibration']
    assert set(calibration) == {'x_theta', 'y_phi', 'psi', 'z'}
    assert all(c['identified_but_wrong'] == 0.0 for c in calibration.values())
    # (a row is reported identified only once it has stopped moving, from about 30 s on)
    assert all(c['identified'] > 0.1 for c in calibration.values())
    assert 'reported identified' in printed
    for key in ('prediction', 'prediction_whole_run', 'prediction_with_plan'):
        check_score(result[key])
    plan = result['prediction_with_plan']
    # with the future reference known, the identified model predicts like the true one and far
    # better than constant velocity
    np.testing.assert_array_less(plan['model'], 1.5 * np.array(plan['true_model']))
    np.testing.assert_array_less(3 * np.array(plan['model'][1:]), plan['constant_velocity'][1:])


def test_evaluate_bag_scores_a_recording(tmp_path, capsys):
    out = tmp_path / 'bag.json'
    status = main(['evaluate', 'bag', str(SAMPLES / 'position'), '--algorithms', 'cloe_iv',
                   '--plan-from-reference', '-q', '--json', str(out)])  # fmt: skip
    printed = capsys.readouterr().out
    assert status == 0
    assert 'issued and landing in flight' in printed
    result = json.loads(out.read_text())
    assert result['plan_from_reference'] is True
    scores = result['algorithms']['cloe_iv']
    check_score(scores['prediction_in_flight'])
    check_score(scores['prediction_all'])


def test_evaluate_bag_scores_only_up_to_score_to(tmp_path, capsys):
    """``--score-to T`` keeps a prediction only if it is issued and reaches its horizon by T: the
    5 s predictions kept with T are the 1 s ones kept with T - 4 s (same issue times)."""

    def counts(score_to: float) -> np.ndarray:
        out = tmp_path / f'{score_to:g}.json'
        status = main(['evaluate', 'bag', str(SAMPLES / 'position'), '--algorithms', 'cloe_iv',
                       '--score-to', f'{score_to:g}', '-q', '--json', str(out)])  # fmt: skip
        assert status == 0
        result = json.loads(out.read_text())
        assert result['score_to'] == score_to
        for key in ('prediction_in_flight', 'prediction_all'):
            check_score(result['algorithms']['cloe_iv'][key])
        return np.array(result['algorithms']['cloe_iv']['prediction_in_flight']['count'])

    late, early = counts(30.0), counts(26.0)
    assert 'from t >= 5 s to 26 s' in capsys.readouterr().out
    assert late[3] == early[1]
    assert late[1] - late[3] == round(4 / 0.2)  # predictions at 5 Hz


@pytest.mark.parametrize(
    ('args', 'expected'),
    [
        (['evaluate', 'bag', str(ROOT / 'README.md')], 'is a file, not a bag'),
        (['evaluate', 'bag', str(SAMPLES / 'position'), '--vehicle', '/uav9'],
         "no vehicle '/uav9'"),
        (['evaluate', 'sim', '--duration', '-1'], 'duration'),
        (['evaluate', 'bag', str(SAMPLES / 'position'), '--score-to', '4'],
         '--score-to (4 s) must be after --score-from (5 s)'),
    ],
)  # fmt: skip
def test_evaluate_refuses_bad_input_with_one_error_line(args, expected, capsys):
    status = main(args)
    err = capsys.readouterr().err
    assert status != 0
    assert 'Traceback' not in err
    assert err.strip().splitlines()[-1].startswith('ERROR: ')
    assert expected in err
