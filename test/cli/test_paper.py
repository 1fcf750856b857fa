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


def test_paper_quick_help_says_what_changes(capsys):
    """--quick lowers the rate and shortens the parameter run; the table lengths stay."""
    with pytest.raises(SystemExit):
        main(['paper', '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    assert '200 Hz instead of --rate' in text
    assert '50 s position run for the parameter figures instead of --parameter-duration' in text
    assert 'shorter runs' not in text


def test_paper_refuses_a_bad_rate(capsys):
    assert main(['paper', '--rate', '5', '--no-plots']) == 1
    assert 'ERROR: --rate must be within [20, 10000] Hz, got 5' in capsys.readouterr().err


def test_paper_refuses_an_output_in_the_way_before_any_work(tmp_path, capsys):
    """A file, or a folder with files in it, is refused at once (the run takes a minute); a
    non-empty folder is written into with --force only."""
    afile = tmp_path / 'afile.txt'
    afile.write_text('mine')
    assert main(['paper', '--quick', '--no-plots', '-q', '-o', str(afile)]) == 1
    captured = capsys.readouterr()
    assert captured.err == (
        f'ERROR: {afile} exists and is not a folder: choose another folder with -o\n'
    )
    assert captured.out == ''
    folder = tmp_path / 'earlier'
    folder.mkdir()
    (folder / 'results.json').write_text('earlier results')
    assert main(['paper', '--quick', '--no-plots', '-q', '-o', str(folder)]) == 1
    captured = capsys.readouterr()
    assert captured.err == (
        f'ERROR: {folder} exists and is not empty, not overwriting: choose another folder with -o '
        'or pass --force to replace results.json and the figures in it\n'
    )
    assert captured.out == ''
    assert (folder / 'results.json').read_text() == 'earlier results'
