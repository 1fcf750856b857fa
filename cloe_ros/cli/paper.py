"""``cloe paper``: reproduce the paper's experiments (§6) and print its tables beside ours."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from cloe_ros.cli.errors import CliError
from cloe_ros.cli.outputs import check_folder, make_folder
from cloe_ros.cli.progress import ProgressBar
from cloe_ros.core.experiments import PAPER_TABLES, PaperCase, run_paper_case
from cloe_ros.core.model import BLOCKS
from cloe_ros.core.simulator import ProbingSignal, closed_loop_poles

SUBSYSTEM_LABELS = {
    'position': 'Position (x, y, z)',
    'velocity': 'Velocity (x_dot, y_dot, z_dot)',
    'angles': 'Euler angles (theta, phi, psi)',
    'rates': 'Angular rates (theta_dot, phi_dot, psi_dot)',
}


def _fmt(x: float) -> str:
    return f'{x:.4g}'


def format_tables(position: PaperCase, trajectory: PaperCase) -> str:
    """The paper's Tables 2-5 with our values beside the paper's, plus the parameter error."""
    lines: list[str] = []
    for case, title in ((position, 'Position control'), (trajectory, 'Trajectory control')):
        tab = case.table()
        paper = PAPER_TABLES[case.scenario]
        lines.append(f'{title} ({case.table_duration:.0f} s): RMSE of the 12-state error norm')
        lines.append(f'  {"algorithm":<10} {"no disturbance":>15} {"disturbance":>12} '
                     f'{"paper (dist.)":>14}')  # fmt: skip
        for alg, name in (('cloe', 'CLOE'), ('cloe_sm', 'CLOE-SM')):
            lines.append(
                f'  {name:<10} {_fmt(tab[(False, alg)]["rmse"]):>15} '
                f'{_fmt(tab[(True, alg)]["rmse"]):>12} {_fmt(paper["rmse"][alg]):>14}'
            )
        lines.append('')
        lines.append(f'{title}: ITAE per subsystem, with disturbances (paper beside)')
        lines.append(f'  {"subsystem":<44} {"CLOE":>9} {"CLOE-SM":>9} {"paper CLOE":>11} '
                     f'{"paper SM":>9}')  # fmt: skip
        for sub, label in SUBSYSTEM_LABELS.items():
            ours = [tab[(True, alg)]['itae'][sub] for alg in ('cloe', 'cloe_sm')]
            theirs = [paper['itae'][sub][alg] for alg in ('cloe', 'cloe_sm')]
            lines.append(f'  {label:<44} {_fmt(ours[0]):>9} {_fmt(ours[1]):>9} '
                         f'{_fmt(theirs[0]):>11} {_fmt(theirs[1]):>9}')  # fmt: skip
        lines.append('')
        t_end = tab[(True, 'cloe')]['param_time']
        lines.append(
            f'{title}: parameter error ||Theta_hat - Theta|| / ||Theta|| at t = {t_end:.0f} s '
            '(with disturbances; the paper reports no value)'
        )
        lines.append(f'  {"block":<10} {"CLOE":>9} {"CLOE-SM":>9}')
        for key in [b.name for b in BLOCKS] + ['all']:
            vals = [tab[(True, alg)]['param_error'][key] for alg in ('cloe', 'cloe_sm')]
            lines.append(f'  {key:<10} {100 * vals[0]:>8.1f}% {100 * vals[1]:>8.1f}%')
        lines.append('')
    return '\n'.join(lines)


def _header(rate: float) -> str:
    poles = closed_loop_poles()
    probing = ProbingSignal()
    lines = [
        'Simulator: nonlinear quadrotor (paper eqs 4-9), m = 0.52 kg, Jx = Jy = 0.01, Jz = 0.02 '
        f'kg m^2, RK4 at {rate:g} Hz.',
        'Controller: hierarchical PD of §3; attitude gains read as torques / J and k_vx = k_vy = '
        '0.12 (the printed 0.05 is unstable). Closed-loop poles of the hover linearization:',
    ]
    for name, p in poles.items():
        lines.append(f'  {name:<8} ' + ', '.join(f'{z.real:.2f}{z.imag:+.2f}j' for z in p))
    lines.append('Probing signal (rad/s, amplitudes m or rad):')
    for ch, amps, freqs in zip(('x_d', 'y_d', 'psi_d', 'z_d'), probing.amplitudes,
                               probing.frequencies):  # fmt: skip
        lines.append(
            '  ' + ch + ': ' + ' + '.join(f'{a:g} sin({w:g} t)' for a, w in zip(amps, freqs))
        )
    lines.append(
        'Estimators: Gamma = 400 I_28, Theta_hat(0) = 0, L(0) = 0, Table 1 sliding-mode gains.'
    )
    lines.append('The paper ran CoppeliaSim: absolute values differ, orderings are comparable.')
    return '\n'.join(lines) + '\n'


def run(args: argparse.Namespace) -> int:
    if not 20.0 <= args.rate <= 10000.0:
        raise CliError(f'--rate must be within [20, 10000] Hz, got {args.rate:g}')
    rate = 200.0 if args.quick else args.rate
    param_duration = 50.0 if args.quick else args.parameter_duration
    if param_duration < 50.0:
        raise CliError(f'--parameter-duration must be >= 50 s, got {param_duration:g}')
    check_folder(args.output, args.force, 'results.json and the figures')
    make_folder(args.output)
    dt = 1.0 / rate
    bar = ProgressBar(enabled=not args.quiet)
    start = time.monotonic()
    position = run_paper_case(
        'position', duration=param_duration, table_duration=50.0, dt=dt, progress=bar
    )
    trajectory = run_paper_case('trajectory', dt=dt, progress=bar)
    bar.close()
    print(_header(rate))
    print(format_tables(position, trajectory))

    results = {
        case.scenario: {
            f'{"disturbance" if dist else "no_disturbance"}/{alg}': value
            for (dist, alg), value in case.table().items()
        }
        for case in (position, trajectory)
    }
    results['settings'] = {'rate_hz': rate, 'parameter_duration_s': param_duration}
    (args.output / 'results.json').write_text(json.dumps(results, indent=2))
    if not args.no_plots:
        from cloe_ros.cli.plots import paper_figures, trajectory_figure

        paths = paper_figures(position, args.output)
        paths.append(trajectory_figure(trajectory, args.output / 'fig12_trajectory_control.png'))
        print('Figures: ' + ', '.join(str(p) for p in paths))
    print(f'Results: {args.output / "results.json"}  ({time.monotonic() - start:.0f} s)')
    final = np.max([v['param_error']['all'] for v in position.table().values()])
    if not np.isfinite(final):
        raise CliError('an estimator diverged (non-finite parameters); see the figures')
    return 0
