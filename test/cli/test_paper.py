"""`cloe paper`: the reproduction command end to end (quick settings)."""

from __future__ import annotations

import json

import pytest

from cloe_ros.cli.main import main


@pytest.mark.slow
def test_paper_quick_prints_tables_and_writes_figures(tmp_path, capsys):
    out = tmp_path / 'paper'
    assert main(['paper', '--quick', '-q', '-o', str(out)]) == 0
    text = capsys.readouterr().out
    for title in ('Position control (50 s): RMSE', 'Trajectory control (140 s): RMSE'):
        assert title in text
    assert 'paper (dist.)' in text and 'paper CLOE' in text and 'paper SM' in text
    assert 'Euler angles (theta, phi, psi)' in text
    assert 'parameter error' in text
    for name in (
        'fig6_errors_disturbance_free',
        'fig7_velocity_errors',
        'fig8_errors_disturbance',
        'fig10_parameters_cloe',
        'fig11_parameters_cloe_sm',
        'fig12_trajectory_control',
    ):
        png = out / f'{name}.png'
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', name
    results = json.loads((out / 'results.json').read_text())
    pos = results['position']
    # what the paper found and the prototype confirmed: CLOE-SM beats CLOE on the error norm and
    # far on the Euler angles
    assert pos['disturbance/cloe_sm']['rmse'] < pos['disturbance/cloe']['rmse']
    assert (
        pos['disturbance/cloe_sm']['itae']['angles']
        < 0.2 * pos['disturbance/cloe']['itae']['angles']
    )


def test_paper_refuses_a_bad_rate(capsys):
    assert main(['paper', '--rate', '5', '--no-plots']) == 1
    assert 'ERROR: --rate must be within [20, 10000] Hz, got 5' in capsys.readouterr().err
