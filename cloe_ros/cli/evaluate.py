"""``cloe evaluate``: how well the identification and the anticipation work, with numbers.

What each target (``sim``, ``bag``, ``corpus``) does is the command's description,
:data:`cloe_ros.cli.commands.EVALUATE_DESCRIPTION` (``cloe evaluate --help``), and its options are
declared there too; this module runs them.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from cloe_ros.cli.commands import DEFAULT_ALGORITHMS, DEFAULT_RATE, DEFAULT_SCORE_FROM_SIM
from cloe_ros.cli.errors import CliError
from cloe_ros.cli.outputs import check_new_file, json_safe
from cloe_ros.cli.progress import ProgressBar
from cloe_ros.core.engine import NS
from cloe_ros.core.evaluation import (
    GAUSSIAN_2SIGMA,
    HORIZONS,
    PredictionScore,
    Run,
    covariance_coverage,
    parameter_error_over_time,
    run_engine,
    score_predictions,
    status_calibration,
)
from cloe_ros.core.identifier import ROW_NAMES, STATUS_NAMES
from cloe_ros.core.model import BLOCKS, PAPER_COUPLING, unstable_blocks
from cloe_ros.core.simulator import (
    SCENARIOS,
    TYPICAL_NOISE,
    MeasurementNoise,
    NoDisturbance,
    PaperDisturbance,
    QuadrotorSimulator,
    true_parameters,
)
from cloe_ros.io.config import build_configs, command_settings

BLOCK_NAMES = [b.name for b in BLOCKS]
#: Why the engine withholds a prediction.
WITHHELD_BECAUSE = (
    'the identified model had an unstable block, and unstable dynamics are never extrapolated'
)


def resolve_settings(args: argparse.Namespace) -> dict:
    """The --config file's settings; sets ``args.algorithms`` and ``args.rate`` from it where the
    command line does not give them (else the defaults). Refuses bad values before any work."""
    settings = command_settings(args.config, args.node)
    if args.algorithms is None:
        args.algorithms = (
            [settings['algorithm']] if 'algorithm' in settings else DEFAULT_ALGORITHMS[args.target]
        )
    if args.rate is None:
        args.rate = float(settings.get('rate', DEFAULT_RATE))
    for algorithm in args.algorithms:
        build_configs(_settings(settings, algorithm, args.rate))
    return settings


def _settings(settings: dict, algorithm: str, rate: float) -> dict:
    return {**settings, 'algorithm': algorithm, 'rate': rate}


def _why_none(score: PredictionScore, run: Run) -> str:
    """Why a prediction table is empty, in words."""
    withheld = f'{run.withheld} withheld because {WITHHELD_BECAUSE}'
    if not len(run.pred_t):
        if run.withheld:
            return f'every prediction of the run ({run.withheld}) was withheld: {WITHHELD_BECAUSE}'
        return 'the run issued no prediction'
    issued = int(np.count_nonzero((run.pred_t >= score.t_from) & (run.pred_t <= score.t_to)))
    span = (
        f'the run issued {len(run.pred_t)} predictions, from {run.pred_t[0]:.1f} to '
        f'{run.pred_t[-1]:.1f} s' + (f', and {withheld}' if run.withheld else '')
    )
    if not issued:
        return f'no prediction was issued in the scored window ({span})'
    return (
        f'{issued} predictions were issued in the scored window, but none reached a horizon '
        'inside the scored data (past the end of the data or of the window, or out of flight)'
    )


def format_prediction(score: PredictionScore, label: str, run: Run) -> str:
    if not score.count.any():
        return f'  prediction, {label}: none scored: {_why_none(score, run)}'
    lines = [
        f'  prediction RMSE [m], {label} ({int(score.count[0])} predictions issued in '
        f'[{score.t_from:.0f}, {score.t_to:.0f}] s; {score.withheld} withheld)',
        f'    {"horizon":>8} {"model":>9}'
        + (f' {"true model":>11}' if score.true_model is not None else '')
        + f' {"const. vel.":>11} {"hold pos.":>10} {"vs CV":>7} {"vs hold":>8}'
        + '   model along x / y / z',
    ]
    for j, h in enumerate(score.horizons):
        row = f'    {h:>7g}s {score.model[j]:>9.4f}'
        if score.true_model is not None:
            row += f' {score.true_model[j]:>11.4f}'
        row += f' {score.constant_velocity[j]:>11.4f} {score.hold_position[j]:>10.4f}'
        row += f' {score.constant_velocity[j] / score.model[j]:>6.1f}x'
        row += f' {score.hold_position[j] / score.model[j]:>7.1f}x'
        if score.model_per_axis is not None:
            row += '   ' + ' / '.join(f'{v:.3f}' for v in score.model_per_axis[j])
        lines.append(row)
    return '\n'.join(lines)


def _score_dict(score: PredictionScore) -> dict:
    return {
        'horizons_s': list(score.horizons),
        'model': score.model.tolist(),
        'model_per_axis_xyz': None
        if score.model_per_axis is None
        else (score.model_per_axis.tolist()),
        'true_model': None if score.true_model is None else score.true_model.tolist(),
        'constant_velocity': score.constant_velocity.tolist(),
        'hold_position': score.hold_position.tolist(),
        'count': score.count.tolist(),
        'withheld': score.withheld,
        'window_s': [score.t_from, score.t_to],
    }


#: Units of the covariance blocks' errors.
BLOCK_UNITS = {'position': 'm', 'attitude': 'rad', 'velocity': 'm/s', 'rates': 'rad/s'}


def format_coverage(coverage: dict[str, dict[str, float]]) -> list[str]:
    """Lines of the ``cloe/state`` covariance calibration (:func:`covariance_coverage`)."""
    lines = [f'  cloe/state covariance: true errors inside 2 sigma (Gaussian: '
             f'{100 * GAUSSIAN_2SIGMA[1]:.1f} % per axis, {100 * GAUSSIAN_2SIGMA[3]:.1f} % in the '
             f'3-D ellipsoid)']  # fmt: skip
    for name, c in coverage.items():
        unit = BLOCK_UNITS[name]
        lines.append(
            f'    {name:>8}: per axis {100 * c["interval_1d"]:5.1f} % (lowest '
            f'{100 * c["interval_1d_lowest"]:5.1f} %), 3-D {100 * c["ellipsoid_3d"]:5.1f} %; '
            f'RMS error {c["rms_error"]:.2g} {unit}, median sigma {c["median_sigma"]:.2g} {unit}'
        )
    return lines


def _identification_summary(run: Run) -> list[str]:
    lines = []
    if run.status is not None:
        st, ex = run.status[-1], run.excitation[-1]
        lines.append(
            '  identifier status at the end: '
            + ', '.join(
                f'{n} {STATUS_NAMES[int(s)]} (exc. {e:.2f})' for n, s, e in zip(ROW_NAMES, st, ex)
            )
        )
    theta, coupling = run.theta_hat[-1], run.coupling[-1]
    unstable = unstable_blocks(theta, coupling)
    lines.append(f'  couplings: c_x = {coupling[0]:.3f}, c_y = {coupling[1]:.3f} m/s^2 per rad '
                 f'(paper: +-{PAPER_COUPLING[0]:.2f}); unstable blocks of the final estimate: '
                 f'{", ".join(unstable) or "none"}')  # fmt: skip
    lines.append(f'  L: max {np.max(run.gain_l):.3g} /s over the run, {np.max(run.gain_l[-1]):.3g}'
                 ' at the end')  # fmt: skip
    return lines


def _check_sim_args(args) -> None:
    """Refuse, before any work, options that cannot give a run or a score."""
    if not 10.0 <= args.duration <= 20000.0:
        raise CliError(f'--duration must be within [10, 20000] s, got {args.duration:g}')
    if args.seed < 0:
        raise CliError(f'--seed must be a non-negative integer, got {args.seed}')
    if not args.segments >= 0.0:
        raise CliError(f'--segments must be >= 0 s (0: no segments), got {args.segments:g}')
    given = args.score_from is not None
    if not given:
        args.score_from = DEFAULT_SCORE_FROM_SIM
    last = args.duration - HORIZONS[0]  # the last issue time that reaches a horizon in the run
    if not args.score_from <= last:
        raise CliError(
            f'--score-from {args.score_from:g} s{"" if given else " (the default)"} lies beyond '
            f'the {args.duration:g} s run: no prediction issued from then on reaches even the '
            f'{HORIZONS[0]:g} s horizon before the end; give --score-from {last:g} or less, or a '
            'longer --duration'
        )


def run_sim(args) -> int:
    _check_sim_args(args)
    base = resolve_settings(args)
    if args.json:
        check_new_file(args.json, args.force, '--json')
    scenario = SCENARIOS[args.scenario]
    sim_rate = 500.0
    if (
        not 10.0 <= args.rate <= sim_rate
        or abs(sim_rate / args.rate - round(sim_rate / args.rate)) > 1e-9
    ):
        raise CliError(f'--rate must divide {sim_rate:g} Hz and be >= 10 Hz, got {args.rate:g}')
    noise = TYPICAL_NOISE if args.noise else MeasurementNoise()
    bar = ProgressBar(enabled=not args.quiet)
    sim = QuadrotorSimulator(
        scenario, disturbance=NoDisturbance() if args.no_disturbance else PaperDisturbance(),
        noise=noise, dt=1.0 / sim_rate, rng=np.random.default_rng(args.seed),
    )  # fmt: skip
    start = time.monotonic()
    res = sim.run(args.duration, progress=lambda f: bar('simulate', f))
    every = round(sim_rate / args.rate)
    t, measured, ref = res.t[::every], res.measured[::every, 0], res.reference[::every, 0]
    truth_t, truth = res.t, res.zeta[:, 0]
    theta_true = true_parameters(sim.quad, sim.gains)
    print(f'{args.scenario} scenario, {args.duration:g} s, '
          f'{"no disturbance" if args.no_disturbance else "§6.1 disturbances"}, '
          f'{"noise 2 mm / 1 cm/s / 2 mrad / 0.01 rad/s" if args.noise else "no noise"}, '
          f'probing on; odometry and estimator at {args.rate:g} Hz')  # fmt: skip
    out = {'scenario': args.scenario, 'duration_s': args.duration, 'noise': args.noise,
           'rate_hz': args.rate, 'algorithms': {}}  # fmt: skip
    checkpoints = [c for c in (10, 20, 30, 45, 60, 90, 120, 200, 500, 1000) if c <= args.duration]
    for algorithm in args.algorithms:
        engine_config, _ = build_configs(_settings(base, algorithm, args.rate))
        horizon = engine_config.prediction.horizon

        def known_future(now, horizon=horizon):
            """The simulator's own future reference (desired + probing), as reference_plan."""
            times = now + np.arange(0.0, horizon + 0.2 + 1e-9, 0.02)
            return times, sim.reference(times)[:, 0]

        run = run_engine(engine_config, t, measured, ref,
                         progress=lambda f, a=algorithm: bar(f'estimate {a}', f))  # fmt: skip
        run_plan = run_engine(
            engine_config,
            t,
            measured,
            ref,
            known_future,
            progress=lambda f, a=algorithm: bar(f'estimate {a} + plan', f),
        )
        bar.close()
        step = engine_config.prediction.step
        print(f'\n{algorithm}:')
        perr = parameter_error_over_time(run, theta_true, [*checkpoints, args.duration])
        print('  parameter error ||Theta_hat_b - Theta_b|| / ||Theta_b|| [%]')
        print('    ' + f'{"t [s]":>7}' + ''.join(f'{b:>9}' for b in [*BLOCK_NAMES, 'all']))
        for tq, errs in perr.items():
            print('    ' + f'{tq:>7g}' + ''.join(f'{100 * errs[b]:>9.2f}'
                                               for b in [*BLOCK_NAMES, 'all']))  # fmt: skip
        for line in _identification_summary(run):
            print(line)
        coverage = covariance_coverage(run, truth_t, truth)
        for line in format_coverage(coverage):
            print(line)
        calibration = None if run.status is None else status_calibration(run, theta_true)
        if calibration is not None:
            print('  time reported identified / of it more than 10 % off / largest error while '
                  'reported identified:')  # fmt: skip
            print('    ' + ', '.join(
                f"{b} {100 * c['identified']:.0f} % / {100 * c['identified_but_wrong']:.0f} % / "
                + ('-' if np.isnan(c['max_error_identified'])
                   else f"{100 * c['max_error_identified']:.1f} %")
                for b, c in calibration.items()))  # fmt: skip
        score = score_predictions(run, truth_t, truth, step, HORIZONS, t_from=args.score_from,
                                  true_model=(theta_true, PAPER_COUPLING))  # fmt: skip
        print(format_prediction(score, f'reference held, from t >= {args.score_from:g} s', run))
        score_all = score_predictions(run, truth_t, truth, step, HORIZONS, t_from=0.0,
                                      true_model=(theta_true, PAPER_COUPLING))  # fmt: skip
        print(format_prediction(score_all, 'reference held, whole run', run))
        score_plan = score_predictions(run_plan, truth_t, truth, step, HORIZONS,
                                       t_from=args.score_from,
                                       true_model=(theta_true, PAPER_COUPLING),
                                       plans=known_future)  # fmt: skip
        label = f'known future reference as reference_plan, from t >= {args.score_from:g} s'
        print(format_prediction(score_plan, label, run_plan))
        entry = {
            'parameter_error': {str(k): v for k, v in perr.items()},
            'prediction': _score_dict(score),
            'prediction_whole_run': _score_dict(score_all),
            'prediction_with_plan': _score_dict(score_plan),
            'coupling_final': run.coupling[-1].tolist(),
            'L_max': float(np.max(run.gain_l)),
            'theta_hat_abs_max': float(np.max(np.abs(run.theta_hat))),
            'covariance_coverage': coverage,
        }
        if calibration is not None:
            entry['status_calibration'] = calibration
        if args.segments > 0:
            print(f'  per {args.segments:g} s segment (RMSE model / const. vel. / hold at 2 s and '
                  '5 s; L max; |Theta_hat| max):')  # fmt: skip
            segs = []
            for s0 in np.arange(0.0, args.duration, args.segments):
                sc = score_predictions(run, truth_t, truth, step, (2.0, 5.0), t_from=s0,
                                       t_to=s0 + args.segments)  # fmt: skip
                m = (run.t >= s0) & (run.t < s0 + args.segments)
                lmax = float(np.max(run.gain_l[m])) if np.any(m) else float('nan')
                tmax = float(np.max(np.abs(run.theta_hat[m]))) if np.any(m) else float('nan')
                print(f'    [{s0:6.0f}, {s0 + args.segments:6.0f}) s: '
                      f'2 s {sc.model[0]:.4f} / {sc.constant_velocity[0]:.4f} / '
                      f'{sc.hold_position[0]:.4f}; 5 s {sc.model[1]:.4f} / '
                      f'{sc.constant_velocity[1]:.4f} / {sc.hold_position[1]:.4f}; '
                      f'L {lmax:.3g}; |Theta| {tmax:.4g}')  # fmt: skip
                segs.append({'start_s': float(s0), **_score_dict(sc), 'L_max': lmax,
                             'theta_abs_max': tmax})  # fmt: skip
            entry['segments'] = segs
        out['algorithms'][algorithm] = entry
    print(f'\n({time.monotonic() - start:.0f} s)')
    if args.json:
        args.json.write_text(json.dumps(json_safe(out), indent=2))
    return 0


def run_bag(args) -> int:
    from cloe_ros.io.dataset import load_flight
    from cloe_ros.io.reader import BagError

    if not args.score_to > args.score_from:
        raise CliError(f'--score-to ({args.score_to:g} s) must be after --score-from '
                       f'({args.score_from:g} s)')  # fmt: skip
    base = resolve_settings(args)
    if args.json:
        check_new_file(args.json, args.force, '--json')
    try:
        vehicles = load_flight(args.bag)
    except BagError as err:
        raise CliError(str(err)) from err
    # '/' (or '') is the un-namespaced vehicle, stored as '' (as `cloe infer --vehicles /`)
    ns = args.vehicle.rstrip('/') if args.vehicle is not None else sorted(vehicles)[0]
    if ns not in vehicles:
        raise CliError(f'no vehicle {args.vehicle!r} in {args.bag}; found: '
                       + ', '.join(v or '/' for v in sorted(vehicles)))  # fmt: skip
    data = vehicles[ns]
    if not len(data.odom) or not len(data.reference):
        raise CliError(f'{args.bag} ({ns or "/"}): no messages on its odom or reference topic')
    t0 = int(min(data.odom.t_ns[0], data.reference.t_ns[0]))
    t_odom = (data.odom.t_ns - t0) / NS
    t_ref = (data.reference.t_ns - t0) / NS
    # one merged stream on the odometry's stamps (the engine holds the latest reference)
    idx = np.searchsorted(t_ref, t_odom, side='right') - 1
    keep = idx >= 0
    t, zeta, ref = t_odom[keep], data.odom.values[keep], data.reference.values[idx[keep]]
    if not len(t):
        raise CliError(f'{args.bag} ({ns or "/"}): no odometry after the first reference')
    if not args.score_from <= t[-1] - HORIZONS[0]:
        raise CliError(
            f'--score-from {args.score_from:g} s lies beyond the recording: its odometry ends '
            f'{t[-1]:.1f} s after the start, and a prediction needs {HORIZONS[0]:g} s to reach '
            f'its first horizon; give --score-from {t[-1] - HORIZONS[0]:.1f} or less'
        )
    bar = ProgressBar(enabled=not args.quiet)
    out = {'bag': str(args.bag), 'vehicle': ns or '/', 'rate_hz': args.rate,
           'plan_from_reference': args.plan_from_reference,
           'score_from': args.score_from,
           'score_to': args.score_to if np.isfinite(args.score_to) else None,
           'algorithms': {}}  # fmt: skip
    print(f'{args.bag} ({ns or "/"}): {len(t)} odometry samples over {t[-1] - t[0]:.1f} s, '
          'from the first reference on'
          + (', recorded future references given as the plan' if args.plan_from_reference
             else ''))  # fmt: skip
    for algorithm in args.algorithms:
        engine_config, _ = build_configs(_settings(base, algorithm, args.rate))
        horizon = engine_config.prediction.horizon
        plans = None
        if args.plan_from_reference:
            values = data.reference.values

            def plans(now, horizon=horizon, values=values):
                m = (t_ref > now) & (t_ref <= now + horizon + 0.1)
                return (t_ref[m], values[m]) if np.any(m) else None

        run = run_engine(engine_config, t, zeta, ref, plans,
                         progress=lambda f, a=algorithm: bar(f'estimate {a}', f),
                         namespace=ns or '/')  # fmt: skip
        bar.close()
        # in flight: measured altitude above 0.2 m and the setpoint above the ground altitude;
        # a landed vehicle (motors off, often under a zero setpoint) follows no closed loop
        ground = engine_config.estimator.ground_altitude

        def in_window(times):
            return times <= args.score_to

        def in_flight(times, ground=ground):
            z = np.interp(times, t, zeta[:, 10], left=np.nan, right=np.nan)
            zd = np.interp(times, t, ref[:, 3], left=np.nan, right=np.nan)
            return (z > 0.2) & (zd > ground) & in_window(times)

        step = engine_config.prediction.step
        window = {'t_from': args.score_from, 't_to': args.score_to}
        score = score_predictions(run, t, zeta, step, HORIZONS, **window, valid=in_flight)
        score_all = score_predictions(run, t, zeta, step, HORIZONS, **window, valid=in_window)
        print(f'\n{algorithm}:')
        for line in _identification_summary(run):
            print(line)
        print(format_prediction(score, 'against the measured positions, issued and landing in '
                                       'flight', run))  # fmt: skip
        until = f' to {args.score_to:g} s' if np.isfinite(args.score_to) else ''
        label = (f'against the measured positions, every prediction from t >= '
                 f'{args.score_from:g} s{until}')  # fmt: skip
        print(format_prediction(score_all, label, run))
        out['algorithms'][algorithm] = {'prediction_in_flight': _score_dict(score),
                                        'prediction_all': _score_dict(score_all),
                                        'coupling_final': run.coupling[-1].tolist()}  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(json_safe(out), indent=2))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.target == 'corpus':
        from cloe_ros.cli.corpus import run_corpus

        return run_corpus(args)
    return run_sim(args) if args.target == 'sim' else run_bag(args)
