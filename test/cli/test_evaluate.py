"""`cloe evaluate sim|bag`: the identification and prediction scores it prints and writes as JSON.

The numbers are checked against what they must satisfy whatever the method's quality (the
per-axis errors add up to the total; the baselines are what their definitions give), plus the
known answers of the simulator: the identified model converges to its true Θ and, given the
future reference, predicts as well as the true model does.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cloe_ros.cli.evaluate import format_prediction
from cloe_ros.cli.main import build_parser, main
from cloe_ros.core.evaluation import PredictionScore
from cloe_ros.io.writer import BagWriter

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / 'bags'
#: A node parameter file that chooses the algorithm and the rate.
CONFIG = 'cloe_inference:\n  ros__parameters:\n    algorithm: cloe_sm\n    rate: 50.0\n'


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
         "no vehicle '/uav9' in " + str(SAMPLES / 'position') + '; found: /'),
        (['evaluate', 'sim', '--duration', '-1'], 'duration'),
        (['evaluate', 'bag', str(SAMPLES / 'position'), '--score-to', '4'],
         '--score-to (4 s) must be after --score-from (5 s)'),
        (['evaluate', 'sim', '--seed', '-1', '--duration', '10', '--score-from', '5', '-q'],
         'ERROR: --seed must be a non-negative integer, got -1'),
        (['evaluate', 'sim', '--segments', '-5', '--duration', '10', '--score-from', '5', '-q'],
         'ERROR: --segments must be >= 0 s (0: no segments), got -5'),
        (['evaluate', 'sim', '--duration', '10', '-q'],
         'ERROR: --score-from 30 s (the default) lies beyond the 10 s run'),
        (['evaluate', 'sim', '--duration', '10', '--score-from', '9.6', '-q'],
         'ERROR: --score-from 9.6 s lies beyond the 10 s run'),
        (['evaluate', 'bag', str(SAMPLES / 'position'), '--score-from', '1000', '-q'],
         'ERROR: --score-from 1000 s lies beyond the recording'),
    ],
)  # fmt: skip
def test_evaluate_refuses_bad_input_with_one_error_line(args, expected, capsys):
    status = main(args)
    err = capsys.readouterr().err
    assert status != 0
    assert 'Traceback' not in err
    assert err.strip().splitlines()[-1].startswith('ERROR: ')
    assert expected in err


def test_evaluate_bag_takes_algorithm_and_rate_from_the_config(tmp_path, capsys):
    """``--config``: its algorithm and rate apply (as in `cloe infer`); ``--vehicle /`` selects
    the un-namespaced vehicle; ``--force`` replaces an existing --json file."""
    config = tmp_path / 'inference.yaml'
    config.write_text(CONFIG)
    out = tmp_path / 'bag.json'
    out.write_text('old')
    status = main(['evaluate', 'bag', str(SAMPLES / 'position'), '--vehicle', '/', '--config',
                   str(config), '--score-to', '20', '-q', '--json', str(out),
                   '--force'])  # fmt: skip
    assert status == 0, capsys.readouterr().err
    result = json.loads(out.read_text())
    assert (result['vehicle'], result['rate_hz'], list(result['algorithms'])) == (
        '/', 50.0, ['cloe_sm'])  # fmt: skip
    # what the duration it prints measures
    header = f'{SAMPLES / "position"} (/): 5001 odometry samples over 50.0 s, from the first '
    assert header + 'reference on' in capsys.readouterr().out


@pytest.mark.parametrize(
    ('args', 'algorithms', 'rate'),
    [
        (['sim'], ['cloe_sm', 'cloe_iv'], 100.0),
        (['bag', 'B'], ['cloe_iv'], 100.0),
        (['sim', '--config', 'C'], ['cloe_sm'], 50.0),
        (['bag', 'B', '--config', 'C'], ['cloe_sm'], 50.0),
        (['bag', 'B', '--config', 'C', '--algorithms', 'cloe_iv', '--rate', '20'], ['cloe_iv'],
         20.0),
    ],
)  # fmt: skip
def test_evaluate_command_line_beats_the_config_file_which_beats_the_defaults(
    args, algorithms, rate, tmp_path
):
    from cloe_ros.cli.evaluate import resolve_settings

    config = tmp_path / 'inference.yaml'
    config.write_text(CONFIG)
    args = [str(config) if a == 'C' else a for a in args]
    parsed = build_parser().parse_args(['evaluate', *args])
    resolve_settings(parsed)
    assert (parsed.algorithms, parsed.rate) == (algorithms, rate)


def test_evaluate_json_is_checked_before_the_run(tmp_path, capsys):
    """An existing --json file is not overwritten without --force, a missing folder is named;
    both before any simulation (which would take seconds)."""
    existing = tmp_path / 'mine.json'
    existing.write_text('mine')
    missing = tmp_path / 'nowhere' / 'x.json'
    for target, expected in (
        (existing, f'ERROR: {existing} exists already, not overwriting: choose another file with '
                   '--json or pass --force to replace it'),
        (missing, f'ERROR: cannot write --json {missing}: the folder {missing.parent} does not '
                  'exist'),
        (tmp_path, f'ERROR: --json {tmp_path} is a folder: give the name of a file'),
    ):  # fmt: skip
        status = main(['evaluate', 'sim', '--duration', '10', '--score-from', '5',
                       '--algorithms', 'cloe_iv', '-q', '--json', str(target)])  # fmt: skip
        captured = capsys.readouterr()
        assert status == 1
        assert captured.err == expected + '\n'
        assert captured.out == ''  # nothing was run
    assert existing.read_text() == 'mine'


def _empty_score(t_from: float, t_to: float) -> PredictionScore:
    nan = np.full(4, np.nan)
    return PredictionScore((0.5, 1.0, 2.0, 5.0), nan, nan, nan, None, np.zeros(4, int), 0,
                           t_from, t_to)  # fmt: skip


def test_an_empty_prediction_table_says_why():
    """Only predictions withheld for an unstable model are blamed on it; an empty window or
    predictions that cannot reach their horizon are said to be that."""
    issued = SimpleNamespace(pred_t=np.arange(0.0, 20.0, 0.2), withheld=0)
    text = format_prediction(_empty_score(30.0, 19.8), 'from t >= 30 s', issued)
    assert 'none scored: no prediction was issued in the scored window' in text
    assert 'the run issued 100 predictions, from 0.0 to 19.8 s' in text
    assert 'unstable' not in text
    text = format_prediction(_empty_score(19.5, 19.8), 'from t >= 19.5 s', issued)
    assert 'none scored: 2 predictions were issued in the scored window, but none reached' in text
    assert 'unstable' not in text
    withheld = SimpleNamespace(pred_t=np.zeros(0), withheld=12)
    text = format_prediction(_empty_score(5.0, 5.0), 'whole run', withheld)
    assert 'every prediction of the run (12) was withheld: the identified model had an ' in text


def test_evaluate_corpus_scores_every_flight_beside_the_baselines(tmp_path, capsys):
    """Two simulated flights in a folder (one bag holding two vehicles), and a bag without a
    vehicle: each flight gets its row, the medians and the pooled coverage are printed and
    written, and the bag that cannot be scored is named (exit status 1)."""
    from bag_fixtures import simulate, write_sim_bag

    corpus = tmp_path / 'corpus'
    corpus.mkdir()
    result = simulate(duration=15.0)
    write_sim_bag(corpus / 'one', result)
    write_sim_bag(corpus / 'nested' / 'two', result, namespaces=('/uav1', '/uav2'))
    (corpus / 'notes.txt').write_text('not a bag')
    out = tmp_path / 'corpus.json'
    status = main(['evaluate', 'corpus', str(corpus), '--jobs', '2', '-q', '--json', str(out)])
    printed = capsys.readouterr()
    assert status == 0, printed.err
    data = json.loads(out.read_text())
    names = [f['name'] for f in data['flights']]
    assert names == ['two/uav1', 'two/uav2', 'one']  # bags in path order: nested/two, one
    for flight in data['flights']:
        rmse = flight['rmse_m']
        assert set(rmse) == {'model', 'constant_velocity', 'hold_position', 'reference_held',
                             'reference_lag'}  # fmt: skip
        assert all(np.all(np.isfinite(v)) and len(v) == 4 for v in rmse.values())
        best = np.minimum(rmse['constant_velocity'], rmse['hold_position'])
        assert flight['worst_ratio'] == pytest.approx(np.max(np.array(rmse['model']) / best))
        assert all(0.0 <= c <= 1.0 for c in flight['coverage'])
    # the same vehicle data three times: the same scores (whichever bag or process)
    assert data['flights'][0]['rmse_m'] == data['flights'][1]['rmse_m'] == \
        data['flights'][2]['rmse_m']
    median = np.median([f['rmse_m']['model'] for f in data['flights']], axis=0)
    np.testing.assert_allclose(data['median_rmse_m']['model'], median)
    for name in names:
        assert name in printed.out
    assert 'median over 3 flights' in printed.out and 'pooled' in printed.out
    # a folder holding a bag without any vehicle: that bag is named, the others still scored
    empty = corpus / 'empty'
    with BagWriter(empty) as writer:
        writer.add_topic('/chatter', 'std_msgs/msg/String')
    out.unlink()
    status = main(['evaluate', 'corpus', str(corpus), '-q', '--jobs', '1', '--json', str(out)])
    printed = capsys.readouterr()
    assert status == 1
    (error,) = printed.err.splitlines()
    assert error.startswith(f'ERROR: {empty}')
    assert 'median over 3 flights' in printed.out
    # ... and it has a row, and its entry in the JSON (before: neither, so that the JSON of a
    # corpus that lost a bag read as whole)
    rows = [line.split(None, 1) for line in printed.out.splitlines()]
    assert ['empty', 'not read (see its ERROR line)'] in rows
    data = json.loads(out.read_text())
    assert data['unread'] == [{'bag': str(empty), 'error': error.removeprefix('ERROR: ')}]
    assert len(data['flights']) == data['flights_scored'] == 3


def test_evaluate_corpus_refuses_paths_without_bags(tmp_path, capsys):
    assert main(['evaluate', 'corpus', str(tmp_path)]) == 1
    assert 'no bag' in capsys.readouterr().err
    assert main(['evaluate', 'corpus', str(tmp_path / 'missing')]) == 1
    assert 'does not exist' in capsys.readouterr().err


def test_a_horizon_no_flight_reaches_is_nan_not_zero(tmp_path, capsys):
    """Flights too short for the 5 s horizon: its pooled coverage is printed as nan (before:
    0.000, as if every position had been outside its radius) and written as null, with the
    other numbers no flight has (the JSON is strict: no NaN)."""
    from bag_fixtures import simulate, write_sim_bag

    write_sim_bag(tmp_path / 'corpus' / 'short', simulate(duration=4.0))
    out = tmp_path / 'corpus.json'
    status = main(['evaluate', 'corpus', str(tmp_path / 'corpus'), '--score-from', '1', '-q',
                   '--jobs', '1', '--json', str(out)])  # fmt: skip
    printed = capsys.readouterr()
    assert status == 0, printed.err
    pooled = next(line for line in printed.out.splitlines() if 'pooled over the flights' in line)
    assert pooled.split(': ')[1].split()[-1] == 'nan', pooled
    text = out.read_text()
    assert 'NaN' not in text and 'Infinity' not in text
    data = json.loads(text)
    assert data['pooled_coverage'][-1] is None
    assert all(0.0 <= c <= 1.0 for c in data['pooled_coverage'][:-1])


def test_evaluate_corpus_splits_the_vehicles_of_a_bag_over_the_workers(tmp_path, capsys):
    """One bag of two vehicles and two workers: each vehicle a job of its own, with the scores
    and names of a run in one process."""
    from bag_fixtures import simulate, write_sim_bag

    from cloe_ros.cli.corpus import _jobs

    corpus = tmp_path / 'corpus'
    write_sim_bag(corpus / 'two', simulate(duration=15.0), namespaces=('/uav1', '/uav2'))
    assert [job[3] for job in _jobs([corpus / 'two'], {}, 5.0, 2)] == [['/uav1'], ['/uav2']]
    assert [job[3] for job in _jobs([corpus / 'two'], {}, 5.0, 1)] == [None]
    data = []
    for jobs in ('1', '2'):
        out = tmp_path / f'corpus{jobs}.json'
        status = main(['evaluate', 'corpus', str(corpus), '--jobs', jobs, '-q', '--json',
                       str(out)])  # fmt: skip
        printed = capsys.readouterr()
        assert status == 0, printed.err
        data.append(json.loads(out.read_text()))
    assert [f['name'] for f in data[1]['flights']] == ['two/uav1', 'two/uav2']
    assert data[1]['flights'] == data[0]['flights']


@pytest.mark.filterwarnings('error::RuntimeWarning')
def test_a_flight_with_nothing_to_score_is_named_and_left_out(tmp_path, capsys):
    """A bag whose odometry positions are all NaN, sorted before two good flights: it is an
    ``ERROR:`` line naming it and why (exit status 1, as a bag that cannot be read), its row and
    its JSON entry say it has nothing to score, and the medians, the pooled coverage and the
    worst ratio are those of the two others (before: a row of nan, status 0, and a worst ratio of
    nan because the NaN flight came first). ``--score-from`` beyond every flight: every flight is
    named and it is an error; numpy's warning of an all-NaN median does not leak (filterwarnings
    turns it into a failure)."""
    from bag_fixtures import simulate, write_sim_bag

    corpus = tmp_path / 'corpus'
    result = simulate(duration=15.0)
    measured = result.measured.copy()
    measured[..., [0, 4, 10]] = np.nan
    write_sim_bag(corpus / 'a_blind', dataclasses.replace(result, measured=measured))
    write_sim_bag(corpus / 'b_good', result)
    write_sim_bag(corpus / 'c_good', result)
    out = tmp_path / 'corpus.json'
    status = main(['evaluate', 'corpus', str(corpus), '-q', '--jobs', '1', '--json', str(out)])
    printed = capsys.readouterr()
    assert status == 1
    blind_why = 'no odometry message was accepted (each was rejected or malformed)'
    assert printed.err == f'ERROR: {corpus / "a_blind"}: nothing to score: {blind_why}\n'
    rows = printed.out.splitlines()
    assert rows[2] == 'a_blind  nothing to score: ' + blind_why
    assert 'median over 2 flights (1 flight(s) with nothing to score left out)' in printed.out
    data = json.loads(out.read_text())
    blind, good, _ = data['flights']
    assert (blind['scored'], good['scored'], data['flights_scored']) == (False, True, 2)
    assert blind['nothing_to_score'] == blind_why
    assert data['worst_ratio'] == good['worst_ratio'] and data['worst_ratio_flight'] == 'b_good'
    assert f'(any horizon): {good["worst_ratio"]:.2f} (b_good);' in printed.out
    np.testing.assert_allclose(data['median_rmse_m']['model'], good['rmse_m']['model'])
    assert all(0.0 <= c <= 1.0 for c in data['pooled_coverage'])
    # nothing issued from --score-from on: every flight named, and no table
    status = main(['evaluate', 'corpus', str(corpus / 'b_good'), str(corpus / 'c_good'), '-q',
                   '--jobs', '1', '--score-from', '100'])  # fmt: skip
    printed = capsys.readouterr()
    assert status == 1 and printed.out == ''
    assert printed.err.splitlines() == [
        f'ERROR: {corpus / name}: nothing to score: no prediction was issued from --score-from '
        '100 s on (the last at 15.0 s after the first odometry)'
        for name in ('b_good', 'c_good')
    ] + ['ERROR: no flight could be scored']


def test_a_vehicle_with_nothing_to_score_is_named_by_bag_and_vehicle(tmp_path, capsys):
    """Among the vehicles of one bag, the one without a usable position is named with its bag."""
    from bag_fixtures import simulate, write_sim_bag

    result = simulate(duration=15.0)
    measured = result.measured.copy()
    measured[:, :, [0, 4, 10]] = np.nan
    two = dataclasses.replace(
        result,
        measured=np.concatenate([result.measured, measured], axis=1),
        zeta=np.concatenate([result.zeta, result.zeta], axis=1),
        reference=np.concatenate([result.reference, result.reference], axis=1),
    )
    bag = write_sim_bag(tmp_path / 'two', two, namespaces=('/uav1', '/uav2'))
    status = main(['evaluate', 'corpus', str(bag), '-q', '--jobs', '2'])
    printed = capsys.readouterr()
    assert status == 1
    assert printed.err.startswith(f'ERROR: {bag} (two/uav2): nothing to score: ')
    assert 'median over 1 flights (1 flight(s) with nothing to score left out)' in printed.out


def test_find_bags_follows_symbolic_links_once(tmp_path):
    """A folder of links to bags finds them, a linked bag among real ones is kept, and a link to a
    folder above (a loop) ends the search instead of repeating it; sorted, each bag once."""
    from cloe_ros.cli.corpus import find_bags

    for name in ('real/a', 'elsewhere/b', 'elsewhere/c'):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / 'metadata.yaml').write_text('')
    (tmp_path / 'elsewhere' / 'd.mcap').write_bytes(b'')
    links = tmp_path / 'links'
    links.mkdir()
    (links / 'b').symlink_to(tmp_path / 'elsewhere' / 'b')
    (links / 'c').symlink_to(tmp_path / 'elsewhere' / 'c')
    (links / 'd.mcap').symlink_to(tmp_path / 'elsewhere' / 'd.mcap')
    (tmp_path / 'real' / 'b_link').symlink_to(tmp_path / 'elsewhere' / 'b')
    (tmp_path / 'real' / 'loop').symlink_to(tmp_path / 'real')
    elsewhere, real = (tmp_path / 'elsewhere').resolve(), (tmp_path / 'real').resolve()
    assert find_bags([links]) == [elsewhere / 'b', elsewhere / 'c', elsewhere / 'd.mcap']
    assert find_bags([tmp_path / 'real']) == [elsewhere / 'b', real / 'a']
    assert find_bags([links, tmp_path / 'real', links / 'b']) == sorted(
        [elsewhere / 'b', elsewhere / 'c', elsewhere / 'd.mcap', real / 'a']
    )
