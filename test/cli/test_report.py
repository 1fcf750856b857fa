"""`cloe report`: a bag in, tables on stdout, a folder with index.html, summary.md, report.json and
figures out. Simulated bags are built in tmp directories (test/bag_fixtures.py)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ORIGIN_NS,
    copy_bag,
    oracle_predictions,
    read_topics,
    simulate,
    write_sim_bag,
)

from cloe_ros.cli.infer import infer_bag
from cloe_ros.cli.main import main
from cloe_ros.cli.plots import model_columns
from cloe_ros.cli.report import prediction_rmse
from cloe_ros.core.kinematics import odometry_to_state
from cloe_ros.core.model import PARAMETER_NAMES
from cloe_ros.core.samples import OdometrySample
from cloe_ros.core.simulator import (
    SCENARIOS,
    TYPICAL_NOISE,
    PaperDisturbance,
    QuadrotorSimulator,
)
from cloe_ros.io import messages
from cloe_ros.io.dataset import Predictions, Series, load_flight
from cloe_ros.io.reader import BagReader
from cloe_ros.io.writer import BagWriter

NS = 1_000_000_000
from corpus import B2  # noqa: E402

PNG = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def flight():
    """12 s of the position scenario (take-off and the start of the move), disturbed, noisy."""
    return simulate(12.0)


@pytest.fixture(scope='module')
def input_bag(flight, tmp_path_factory):
    return write_sim_bag(tmp_path_factory.mktemp('bags') / 'sim', flight)


@pytest.fixture(scope='module')
def output_bag(input_bag, tmp_path_factory):
    """`cloe infer`'s output for the simulated bag: cloe_sm into /cloe, without predictions (the
    tests add their own oracle predictions)."""
    folder = tmp_path_factory.mktemp('bags')
    infer_bag(input_bag, folder / 'inferred', {'algorithm': 'cloe_sm', 'prediction_horizon': 0.0})
    return folder / 'inferred'


def run_report(capsys, *args) -> tuple[int, str, str]:
    status = main(['report', *map(str, args)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def odometry_states(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns) and model states straight from the Odometry messages of ``topic``."""
    with BagReader(bag) as reader:
        samples = [messages.decode_odometry(raw) for _, _, raw in reader.messages([topic])]
    t = np.array([s.stamp_ns for s in samples])
    zeta = odometry_to_state(
        np.array([s.position for s in samples]),
        np.array([s.orientation for s in samples]),
        np.array([s.linear for s in samples]),
        np.array([s.angular for s in samples]),
    )
    return t, zeta


def check_folder(folder: Path, figures: set[str]) -> dict:
    """The files every report has; returns report.json."""
    pngs = {p.name for p in folder.glob('*.png')}
    assert figures <= pngs, pngs
    for png in pngs:
        assert (folder / png).read_bytes()[:8] == PNG, png
    page = (folder / 'index.html').read_text()
    assert page.startswith('<!DOCTYPE html>') and page.rstrip().endswith('</html>')
    # self-contained: every figure embedded, nothing fetched
    assert page.count('src="data:image/png;base64,') == len(pngs)
    assert 'src="http' not in page and 'href="http' not in page
    assert '<link' not in page and '<script' not in page
    assert '<table>' in page and '<figcaption>' in page
    summary = (folder / 'summary.md').read_text()
    for png in pngs:
        assert f']({png})' in summary
    return json.loads((folder / 'report.json').read_text())


def table_header(out: str, title: str) -> list[str]:
    lines = out.splitlines()
    i = next(i for i, line in enumerate(lines) if line.startswith(title))
    return lines[i + 1].split()


# -- prediction scoring ------------------------------------------------------------------------


def test_prediction_rmse_against_closed_form():
    """Straight flight at constant velocity: constant velocity predicts it exactly, hold position
    is off by |v| h, and paths offset by d are off by |d|."""
    v = np.array([0.5, -0.2, 0.1])
    t_ns = ORIGIN_NS + np.arange(0, 20 * NS + 1, NS // 100)
    t = (t_ns - ORIGIN_NS) / NS
    position = t[:, None] * v
    zeta = np.zeros((len(t), 12))
    zeta[:, [0, 4, 10]] = position
    zeta[:, [1, 5, 11]] = v
    measured = Series(t_ns, zeta)
    issue = t_ns[::50][:30]  # every 0.5 s over the first 15 s
    lead_ns = np.arange(0, 5 * NS + 1, NS // 10)  # poses every 0.1 s up to 5 s
    stamps = issue[:, None] + lead_ns
    offset = np.array([0.03, 0.0, -0.04])  # |d| = 0.05 m
    positions = ((stamps - ORIGIN_NS) / NS)[..., None] * v + offset
    # the last path is short: 1 s of poses, padded as the reader pads
    stamps[-1, 11:] = -1
    positions[-1, 11:] = np.nan
    score = prediction_rmse(Predictions(issue, stamps, positions), measured)
    assert score.horizons == (0.5, 1.0, 2.0, 5.0)
    assert score.count.tolist() == [30, 30, 29, 29]
    np.testing.assert_allclose(score.model, 0.05, rtol=1e-9)
    np.testing.assert_allclose(score.constant_velocity, 0.0, atol=1e-12)
    np.testing.assert_allclose(score.hold_position, np.linalg.norm(v) * np.array(score.horizons),
                               rtol=1e-9)  # fmt: skip


def test_prediction_rmse_skips_poses_far_from_the_horizon():
    """Poses every 2 s: none is within 20 % of 0.5 s or 1 s, so those horizons score nothing."""
    t_ns = ORIGIN_NS + np.arange(0, 20 * NS + 1, NS // 100)
    measured = Series(t_ns, np.zeros((len(t_ns), 12)))
    issue = t_ns[:1]
    stamps = issue[:, None] + np.arange(0, 6 * NS + 1, 2 * NS)
    positions = np.zeros((1, stamps.shape[1], 3))
    score = prediction_rmse(Predictions(issue, stamps, positions), measured)
    assert score.count.tolist() == [0, 0, 1, 1]
    assert math.isnan(score.model[0]) and score.model[2] == 0.0


# -- reports on simulated bags -----------------------------------------------------------------


@pytest.mark.slow
def test_report_on_an_input_bag_infers_it_first(input_bag, tmp_path, capsys):
    folder = tmp_path / 'report'
    status, out, err = run_report(capsys, input_bag, '-o', folder, '-q')
    assert status == 0, err
    assert (folder / 'inferred_bag' / 'metadata.yaml').is_file()
    data = check_folder(folder, {
        'vehicle_errors.png', 'vehicle_states.png', 'vehicle_parameters.png',
        'vehicle_parameter_error.png', 'vehicle_path.png',
    })  # fmt: skip
    # the main table on stdout: one column per output, the raw measurement beside it (simulation)
    # (the output namespace, and the algorithm `cloe infer` recorded in the bag)
    assert table_header(out, '/: estimation error against the ground truth') == [
        'metric', 'cloe', '(cloe_iv)', 'odom', '(raw', 'measurement)',
    ]  # fmt: skip
    assert data['vehicles']['/']['outputs']['cloe']['algorithm'] == 'cloe_iv'
    for row in (
        'RMSE 12-state norm (vs ground truth)',
        'RMSE angles',
        'ITAE position',
        'ITAE rates',
        'parameter error x_theta [%]',
        'parameter error all [%]',
    ):
        assert f'  {row}  ' in out, row  # fmt: skip
    assert 'cloe_iv at 100 Hz by `cloe report`' in out
    assert f'report: {(folder / "index.html").resolve()}' in out

    # RMSE of the 12-state error norm, computed here from the bag's messages alone
    t_est, est = odometry_states(folder / 'inferred_bag', '/cloe/state')
    t_true, true = odometry_states(folder / 'inferred_bag', '/ground_truth')
    inside = (t_est >= t_true[0]) & (t_est <= t_true[-1])
    truth_at = np.column_stack([np.interp(t_est[inside], t_true, true[:, j]) for j in range(12)])
    err = truth_at - est[inside]
    err[:, 8] = (err[:, 8] + np.pi) % (2 * np.pi) - np.pi
    vehicle = data['vehicles']['/']
    score = vehicle['outputs']['cloe']['score']
    assert score['against'] == 'truth'
    assert score['steps'] == inside.sum()
    assert score['rmse'] == pytest.approx(np.sqrt(np.mean(np.sum(err**2, axis=1))), rel=1e-9)
    assert score['rmse_sub']['position'] == pytest.approx(
        np.sqrt(np.mean(np.sum(err[:, [0, 4, 10]] ** 2, axis=1))), rel=1e-9
    )
    # the parameter error against the true parameters, from the last parameters message
    params = read_topics(folder / 'inferred_bag', ['/cloe/parameters', '/true_parameters'])
    theta_hat = messages.decode_float64_multi_array(params[0][2][-1][1])[1][:16]
    labels, theta = messages.decode_float64_multi_array(params[1][2][0][1])
    assert labels[0] == 'theta.x_theta.a_x'
    expected = np.linalg.norm(theta_hat - theta) / np.linalg.norm(theta)
    assert score['param_error']['all'] == pytest.approx(expected, rel=1e-9)
    assert vehicle['outputs']['cloe']['final_parameters']['z.b_z_d'] == pytest.approx(
        theta_hat[15]
    )
    assert vehicle['true_parameters']['z.b_z_d'] == pytest.approx(theta[15])
    assert data['inference']['settings']['algorithm'] == 'cloe_iv'  # the default
    assert data['inference']['malformed'] == {'': 0}
    # the parameter table shows truth and error beside the estimate
    summary = (folder / 'summary.md').read_text()
    assert '| parameter | cloe (cloe_iv) Θ̂ | true Θ | cloe (cloe_iv) error [%] |' in summary
    assert 'scored against' in summary and 'simulator ground truth' in summary
    # the pole table says whose poles: cloe_iv's raw Θ̂ and the usable model it predicts with
    assert '| block | cloe (cloe_iv) Θ̂ | cloe (cloe_iv) usable model | true |' in summary
    assert 'cloe_iv predicts with its usable model (model.theta.*' in summary
    assert 'predictions diverge' not in summary
    poles = vehicle['outputs']['cloe']['model_max_real_pole']
    assert all(p < 0 for p in poles.values()), poles  # the usable model is stable
    # a noisy simulation: the errors figure draws the measurement's own error in grey
    assert "grey: the measurement's own error" in summary


def test_report_on_a_noise_free_simulation_says_the_measurement_is_the_truth(tmp_path, capsys):
    """No odom column and no grey line when the measurements equal the truth, and the captions
    say so rather than promising them."""
    result = QuadrotorSimulator(SCENARIOS['position'], dt=2e-3).run(3.0)
    bag = write_sim_bag(tmp_path / 'clean', result)
    status, out, err = run_report(capsys, bag, '-o', tmp_path / 'report', '-q')
    assert status == 0, err
    assert table_header(out, '/: estimation error against the ground truth') == [
        'metric', 'cloe', '(cloe_iv)',
    ]  # fmt: skip
    summary = (tmp_path / 'report' / 'summary.md').read_text()
    assert 'the measurements equal the truth (a noise-free simulation)' in summary
    assert "the measurement's own error" not in summary
    assert 'the measurements equal the truth (a noise-free simulation): no line' in summary


@pytest.mark.slow
def test_report_on_an_output_bag_with_predictions(flight, output_bag, tmp_path, capsys,
                                                  monkeypatch):  # fmt: skip
    """An output bag is reported on as it is (no inference); predictions are scored."""
    status = messages.Status(
        messages.WARN,
        'cloe_inference: /',
        'running; 4 input(s) rejected',
        '/',
        (
            ('algorithm', 'cloe_sm'),
            ('steps', '1201'),
            ('odom_received', '1205'),
            ('odom_accepted', '1202'),
            ('rejected', '4'),
            ('malformed', '1'),
            ('time_jumps', '0'),
        ),
    )
    diagnostics = [(ORIGIN_NS + NS, messages.encode_diagnostics(ORIGIN_NS + NS, [status]))]
    bag = copy_bag(output_bag, tmp_path / 'with_prediction', [
        ('/cloe/prediction', messages.PATH, oracle_predictions(flight)),
        ('/diagnostics', messages.DIAGNOSTIC_ARRAY, diagnostics),
    ])  # fmt: skip
    monkeypatch.chdir(tmp_path)
    status, out, err = run_report(capsys, bag)  # default folder: ./<bag name>_report
    assert status == 0, err
    folder = tmp_path / 'with_prediction_report'
    assert not (folder / 'inferred_bag').exists()
    data = check_folder(folder, {'vehicle_prediction.png', 'vehicle_path.png'})
    assert 'outputs found in the bag: /cloe' in out
    assert table_header(out, '/: prediction RMSE against the measured position [m]') == [
        'horizon', '[s]', 'cloe', '(cloe_sm)', 'model', 'cloe', '(cloe_sm)', 'const.', 'velocity',
        'cloe', '(cloe_sm)', 'hold', 'cloe', '(cloe_sm)', 'paths',
    ]  # fmt: skip
    pred = data['vehicles']['/']['outputs']['cloe']['prediction']
    assert pred['horizons_s'] == [0.5, 1.0, 2.0, 5.0]
    # the oracle predicts the true position: its error against the measurement is the noise
    noise = math.sqrt(3) * TYPICAL_NOISE.position
    np.testing.assert_allclose(pred['model'], noise, rtol=0.3)
    assert all(cv > 3 * noise for cv in pred['constant_velocity'])
    assert pred['paths'][0] == 24 and pred['paths'][-1] < pred['paths'][0]  # paths cut at the end
    # what the node's /diagnostics last said about its inputs
    assert data['diagnostics']['cloe_inference: / (cloe_sm)']['malformed'] == '1'
    assert (
        '| cloe_inference: / (cloe_sm) | 1201 | 1205 | 1202 | 4 | 1 | 0 |'
        in (folder / 'summary.md').read_text()
    )

    # a second report into the same folder is refused, unless forced
    status, _, err = run_report(capsys, bag, '-o', folder)
    assert status == 1
    assert err == (
        f'ERROR: {folder} exists and is not empty, not overwriting: choose another folder with '
        '-o or pass --force to replace the report in it\n'
    )
    (folder / 'index.html').write_text('stale')
    status, _, err = run_report(capsys, bag, '-o', folder, '--force')
    assert status == 0, err
    assert (folder / 'index.html').read_text().startswith('<!DOCTYPE html>')


@pytest.mark.slow
def test_report_on_two_vehicles_and_two_outputs(tmp_path, capsys):
    sim = QuadrotorSimulator(
        SCENARIOS['position'], n_vehicles=2, offsets=np.array([[0.0, 0, 0], [1.0, 0, 0]]),
        disturbance=PaperDisturbance(), noise=TYPICAL_NOISE, dt=2e-3,
        rng=np.random.default_rng(1),
    )  # fmt: skip
    bag = write_sim_bag(tmp_path / 'in', sim.run(6.0), namespaces=('/uav1', '/uav2'))
    infer_bag(bag, tmp_path / 'a', {'algorithm': 'cloe', 'output_ns': 'cloe'})
    infer_bag(bag, tmp_path / 'b', {'algorithm': 'cloe_sm', 'output_ns': 'cloe_sm'},
              copy_inputs=False)  # fmt: skip
    extra = read_topics(tmp_path / 'b', [f'/uav{i}/cloe_sm/{kind}' for i in (1, 2)
                                         for kind in ('state', 'parameters')])  # fmt: skip
    merged = copy_bag(tmp_path / 'a', tmp_path / 'merged', extra)
    status, out, err = run_report(capsys, merged, '-o', tmp_path / 'report')
    assert status == 0, err
    for v in ('uav1', 'uav2'):
        assert table_header(out, f'/{v}: estimation error against the ground truth') == [
            'metric', 'cloe', 'cloe_sm', 'odom', '(raw', 'measurement)',
        ]  # fmt: skip
    data = check_folder(tmp_path / 'report', {
        f'{v}_{kind}.png' for v in ('uav1', 'uav2') for kind in ('errors', 'parameters', 'path')
    })  # fmt: skip
    assert set(data['vehicles']) == {'/uav1', '/uav2'}
    assert set(data['vehicles']['/uav2']['outputs']) == {'cloe', 'cloe_sm'}


# -- a real flight -----------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(not B2.is_dir(), reason='the NanoBench flights are not available')
def test_report_on_a_real_flight(tmp_path, capsys):
    folder = tmp_path / 'b2'
    start = time.monotonic()
    status, out, err = run_report(capsys, B2, '-o', folder, '-q', '--algorithm', 'cloe')
    elapsed = time.monotonic() - start
    assert status == 0, err
    assert table_header(out, '/: estimation error against the measurements') == ['metric', 'cloe']
    assert 'RMSE 12-state norm (vs measurements)' in out
    assert 'parameter error' not in out  # no truth for a real flight
    assert 'cloe at 100 Hz' in out
    data = check_folder(folder, {
        'vehicle_errors.png', 'vehicle_states.png', 'vehicle_parameters.png', 'vehicle_path.png',
    })  # fmt: skip
    assert not (folder / 'vehicle_parameter_error.png').exists()
    vehicle = data['vehicles']['/']
    assert vehicle['scored_against'] == 'measurement'
    assert vehicle['true_parameters'] is None
    assert vehicle['odom_messages'] == 2725 and vehicle['reference_messages'] == 2527
    assert vehicle['odom_rate_hz'] == pytest.approx(100.0, rel=0.02)
    score = vehicle['outputs']['cloe']['score']
    assert score['param_error'] is None
    # a Vicon-tracked flight: the inferred position stays within a few cm of the measured one
    assert 0.0 < score['rmse_sub']['position'] < 0.1
    assert data['topics']['/odom'] == {'type': 'nav_msgs/msg/Odometry', 'messages': 2725}
    summary = (folder / 'summary.md').read_text()
    assert 'no true parameters in the bag' in summary
    assert '| /odom | nav_msgs/msg/Odometry | 2725 |' in summary
    print(f'report on B2 in {elapsed:.1f} s')  # shown with -s; a benchmark, not an assertion


# -- errors ------------------------------------------------------------------------------------


def test_missing_bag(tmp_path, capsys):
    status, _, err = run_report(capsys, tmp_path / 'nope', '-o', tmp_path / 'r')
    assert status == 1
    assert err == f'ERROR: {tmp_path / "nope"} does not exist\n'
    assert not (tmp_path / 'r').exists()


def _bag_with(path: Path, topics: dict[str, str]) -> Path:
    with BagWriter(path) as writer:
        for name, msgtype in topics.items():
            writer.add_topic(name, msgtype)
            if msgtype == messages.ODOMETRY:
                writer.write(name, ORIGIN_NS, messages.encode_odometry(
                    OdometrySample(ORIGIN_NS, 'world', 'base_link', np.zeros(3),
                                            np.array([0.0, 0, 0, 1]), np.zeros(3), np.zeros(3))
                ))  # fmt: skip
    return path


def test_bag_without_reference(tmp_path, capsys):
    bag = _bag_with(tmp_path / 'odom_only', {'/odom': messages.ODOMETRY})
    status, _, err = run_report(capsys, bag, '-o', tmp_path / 'r')
    assert status == 1
    assert err == (
        f'ERROR: {bag}: no vehicle to infer: each needs <ns>/odom (nav_msgs/msg/Odometry) and '
        '<ns>/reference (geometry_msgs/msg/PoseStamped); vehicle / has /odom but no /reference '
        'topic\n'
    )
    assert not (tmp_path / 'r').exists()


def test_bag_without_odom_or_reference(tmp_path, capsys):
    bag = _bag_with(tmp_path / 'other', {'/chatter': messages.ODOMETRY})
    status, _, err = run_report(capsys, bag, '-o', tmp_path / 'r')
    assert status == 1
    assert err.startswith(f'ERROR: {bag}: no vehicle to infer: ')
    assert err.endswith('the bag has /chatter (nav_msgs/msg/Odometry)\n')


def test_a_bag_of_outputs_alone_is_refused_as_such(tmp_path, capsys):
    """`cloe infer --no-inputs` writes outputs without odom/reference: the report says that,
    not that there is no vehicle to infer."""
    outputs = {'/cloe/state': messages.ODOMETRY, '/cloe/parameters': messages.FLOAT64_MULTI_ARRAY}
    bag = _bag_with(tmp_path / 'outputs', outputs)
    status, _, err = run_report(capsys, bag, '-o', tmp_path / 'r')
    assert status == 1
    assert err == (
        f'ERROR: {bag} holds only inference outputs (/cloe/parameters, /cloe/state), no '
        '<ns>/odom and <ns>/reference to compare them with (written by `cloe infer '
        '--no-inputs`?): report the input bag instead, or infer it again without --no-inputs\n'
    )
    assert not (tmp_path / 'r').exists()


def test_existing_folder_is_refused_before_any_work(input_bag, tmp_path, capsys):
    folder = tmp_path / 'r'
    folder.mkdir()
    (folder / 'notes.txt').write_text('mine')
    status, _, err = run_report(capsys, input_bag, '-o', folder)
    assert status == 1
    assert 'exists and is not empty, not overwriting' in err and '--force' in err
    assert sorted(p.name for p in folder.iterdir()) == ['notes.txt']


def test_inference_options_on_an_output_bag_are_refused(output_bag, tmp_path, capsys):
    status, _, err = run_report(capsys, output_bag, '-o', tmp_path / 'r', '--rate', '50')
    assert status == 1
    expected = (
        f'ERROR: {output_bag} already holds inference outputs (/cloe/parameters, /cloe/state): '
        '--algorithm, --rate and --config only apply to input bags'
    )
    assert err.startswith(expected)


def test_bad_rate_is_refused(input_bag, tmp_path, capsys):
    status, _, err = run_report(capsys, input_bag, '-o', tmp_path / 'r', '--rate', '-3')
    assert status == 1
    assert err.startswith('ERROR: ') and 'rate' in err
    assert not (tmp_path / 'r').exists()


def test_the_parameters_figure_shows_the_model_in_use_only_where_it_differs(
    input_bag, output_bag, tmp_path
):
    """cloe_iv publishes a usable model that differs from its raw estimate early on; cloe_sm runs
    on its own estimate, so there is nothing more to draw."""
    infer_bag(input_bag, tmp_path / 'iv', {'algorithm': 'cloe_iv', 'prediction_horizon': 0.0})
    iv = load_flight(tmp_path / 'iv')[''].outputs['cloe']
    columns = model_columns(iv)
    assert [iv.labels[c] for c in columns] == [f'model.theta.{n}' for n in PARAMETER_NAMES]
    assert not np.array_equal(iv.parameters.values[:, columns], iv.parameters.values[:, :16])
    assert model_columns(load_flight(output_bag)[''].outputs['cloe']) is None


# -- progress and failure ------------------------------------------------------------------------


def malformed_odometry_bag(source: Path, target: Path) -> Path:
    """``source`` with every odometry message cut to 20 bytes (undecodable)."""
    with BagReader(source) as reader, BagWriter(target) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for topic, t, raw in reader.messages():
            writer.write(topic, t, bytes(raw[:20]) if topic == '/odom' else bytes(raw))
    return target


def test_every_phase_shows_progress(input_bag, tmp_path, capsys):
    """Without -q: the inference, reading the bag, scoring and the figures of each vehicle and
    writing the report each show their progress on stderr (a line per 10 % off a terminal)."""
    status, _, err = run_report(capsys, input_bag, '-o', tmp_path / 'r')
    assert status == 0, err
    stages = [line.split(':')[0] for line in err.splitlines() if line.endswith(' s)')]
    for stage in ('infer', 'read the bag', 'score /', 'figures /', 'write the report'):
        assert stage in stages, err
        assert f'{stage}: 100%' in err, err
    figures = [line for line in err.splitlines() if line.startswith('figures /:')]
    assert len(figures) >= 4  # one line per figure drawn (a decile each)


def test_a_failed_inference_leaves_nothing_behind(input_bag, tmp_path, capsys):
    """Every odometry message malformed: one ERROR line naming the bag and the topic, exit 1,
    and neither the report folder nor its inferred_bag/ is left."""
    bag = malformed_odometry_bag(input_bag, tmp_path / 'malformed')
    folder = tmp_path / 'new' / 'report'
    status, _out, err = run_report(capsys, bag, '-o', folder, '-q')
    assert status == 1
    errors = [line for line in err.splitlines() if 'ERROR' in line]
    assert len(errors) == 1 and errors[0].startswith(f'ERROR: {bag}'), err
    assert '/odom' in errors[0], err
    assert 'Traceback' not in err
    assert not folder.exists() and not (tmp_path / 'new').exists()


def test_a_failed_report_with_force_keeps_only_what_was_there(input_bag, tmp_path, capsys):
    """Into an existing folder (--force): the user's files stay, the report's own go."""
    folder = tmp_path / 'r'
    folder.mkdir()
    (folder / 'notes.txt').write_text('mine')
    (folder / 'index.html').write_text('an earlier report')
    bag = malformed_odometry_bag(input_bag, tmp_path / 'malformed')
    status, _, err = run_report(capsys, bag, '-o', folder, '-q', '--force')
    assert status == 1 and err.startswith(f'ERROR: {bag}'), err
    assert sorted(p.name for p in folder.iterdir()) == ['notes.txt']
