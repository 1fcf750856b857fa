"""``cloe demo``: the main job. Simulator, three inference nodes (CLOE, CLOE-SM, cloe_iv) and the
recorder as separate processes on a private DDS domain; then the comparison table from the
recorded bag, and plots. It needs DDS, as ``cloe live`` does; the other subcommands do not."""

from __future__ import annotations

import argparse
import re
import signal
import time
from datetime import datetime
from pathlib import Path

from cloe_ros.cli.analysis import format_scores, score_output
from cloe_ros.cli.errors import CliError
from cloe_ros.cli.processes import NodeProcess, reserve_domain_id, ros_env
from cloe_ros.core.experiments import PAPER_TABLES
from cloe_ros.core.simulator import SCENARIOS
from cloe_ros.io.dataset import load_flight

#: As quadrotor_sim: behind when it achieves less than this fraction of the factor asked for.
RTF_TOLERANCE = 0.9
#: The slowest simulation the demo waits for, wall seconds per simulated second.
SLOWEST = 20.0
#: How long a node may take to start (import rclpy, discover) on a busy machine, s.
START_TIMEOUT = 120.0

#: The paper's two algorithms side by side, and the package's identifier that converges.
ALGORITHMS = (('cloe', 'CLOE'), ('cloe_sm', 'CLOE-SM'), ('cloe_iv', 'CLOE-IV'))


def _start(name, params, env, logs: Path, node_name=None) -> NodeProcess:
    return NodeProcess(name, params, env, logs / f'{node_name or name}.log', node_name)


#: quadrotor_sim's last line: ``done: 50 s simulated in 26.10 s of wall time (real-time factor
#: 1.92, asked 2)``.
_DONE = re.compile(r'done: \S+ s simulated in (\S+) s of wall time \(real-time factor (\S+),')


def achieved_factor(sim_log: str, asked: float) -> str:
    """What the simulator says it achieved, in words (from its ``done:`` line)."""
    found = _DONE.search(sim_log)
    if found is None:
        return 'the simulator did not report its real-time factor'
    wall, factor = found.groups()
    text = f'real-time factor achieved {factor} (asked {asked:g}, {wall} s of wall time)'
    try:
        behind = float(factor) < RTF_TOLERANCE * asked
    except ValueError:
        behind = False
    if behind:
        text += (
            f'\n  the simulator could not hold {asked:g}x real time (a busy machine?). The '
            'results do not depend on it: the nodes work on message stamps, not on the wall '
            'clock'
        )
    return text


def run(args: argparse.Namespace) -> int:
    scenario = SCENARIOS[args.scenario]
    duration = scenario.duration if args.duration is None else args.duration
    if not 1.0 <= duration <= 3600.0:
        raise CliError(f'--duration must be within [1, 3600] s, got {duration:g}')
    if not 0.1 <= args.speed <= 20.0:
        raise CliError(f'--speed must be within [0.1, 20], got {args.speed:g}')
    out = args.output
    stamp = datetime.now().strftime('%Y%m%d_%H%M%S')
    run_dir = out / f'{args.scenario}_{stamp}'
    bag = run_dir / 'bag'
    logs = run_dir / 'logs'
    logs.mkdir(parents=True, exist_ok=False)
    domain = reserve_domain_id()
    env = ros_env(domain, logs / 'ros')
    print(f'ROS_DOMAIN_ID={domain} (private, localhost only); logs in {logs}')

    outputs = [f'/{alg}/{kind}' for alg, _ in ALGORITHMS
               for kind in ('state', 'parameters', 'prediction')]  # fmt: skip
    recorded = ['/odom', '/reference', '/ground_truth', '/true_parameters', '/diagnostics',
                *outputs]  # fmt: skip
    procs: list[NodeProcess] = []
    try:
        recorder = _start('bag_recorder', {'output': str(bag), 'topics': recorded}, env, logs)
        procs.append(recorder)
        for alg, _ in ALGORITHMS:
            procs.append(_start(
                'cloe_inference', {'algorithm': alg, 'output_ns': alg, 'rate': args.rate},
                env, logs, node_name=f'cloe_inference_{alg}',
            ))  # fmt: skip
        for p in procs:
            ready = 'recording to' if p.name == 'bag_recorder' else 'ready:'
            if not p.wait_for(ready, timeout=START_TIMEOUT):
                raise CliError(f'{p.name} did not start; its log:\n{p.output()}')
        # the recorder subscribes to a topic once discovery shows its publisher, which can take
        # seconds: start the simulation only when every output is being recorded, or their first
        # seconds are lost
        for topic in outputs:
            if not recorder.wait_for(f'recording {topic} (', timeout=START_TIMEOUT):
                raise CliError(f'bag_recorder did not subscribe to {topic}; its log:\n'
                               f'{recorder.output()}')  # fmt: skip
        print(f'recording to {bag}; ' + ', '.join(label for _, label in ALGORITHMS)
              + f' inference at {args.rate:g} Hz')  # fmt: skip
        sim = _start('quadrotor_sim', {
            'scenario': args.scenario, 'duration': duration, 'real_time_factor': args.speed,
            'shutdown_when_done': True, 'wait_for_subscribers': 1 + len(ALGORITHMS),
        }, env, logs)  # fmt: skip
        procs.append(sim)
        print(
            f'simulating the {args.scenario} scenario ({duration:g} s, disturbances and probing) '
            f'at {args.speed:g}x real time ...'
        )
        start = time.monotonic()
        # a busy machine holds less than the real-time factor asked (the simulator says so and
        # goes on): wait for it down to 1/20 of real time, a bound against a hung process only
        bound = 60.0 + SLOWEST * duration
        try:
            status = sim.proc.wait(timeout=bound)
        except Exception as err:
            raise CliError(
                f'the simulator did not finish within {bound:.0f} s (below 1/{SLOWEST:g} of real '
                f'time); its log:\n{sim.output()}'
            ) from err
        if status != 0:
            raise CliError(f'the simulator failed (status {status}):\n{sim.output()}')
        print(
            f'simulation done in {time.monotonic() - start:.1f} s; '
            + achieved_factor(sim.output(), args.speed)
        )
        print('stopping the nodes')
        time.sleep(1.0)  # let the last messages reach the recorder
    finally:
        for p in reversed(procs):
            p.stop(signal.SIGINT)
    for p in procs:
        if p.proc.returncode not in (0, -signal.SIGINT):
            print(f'warning: {p.name} exited with status {p.proc.returncode}; see {p.log_path}')

    vehicles = load_flight(bag)
    vehicle = vehicles['']
    scores = [score_output(vehicle, alg) for alg, _ in ALGORITHMS]
    if any(s is None for s in scores):
        raise CliError(f'the bag {bag} holds no inference output; see the logs in {logs}')
    for s, (_, label) in zip(scores, ALGORITHMS):
        s.name = label
    print()
    print(f'Recorded bag: {bag}  ({len(vehicle.odom)} odom, {len(vehicle.reference)} reference)')
    print(
        f'Online inference of the {args.scenario} scenario, {duration:g} s with disturbances, '
        f'{args.rate:g} Hz, errors against the simulator truth:'
    )
    paper = PAPER_TABLES.get(args.scenario)
    print(format_scores(scores, paper))
    print(
        "(the paper's values come from CoppeliaSim at 1 kHz: compare orderings, not values; "
        '`cloe paper` reproduces its tables offline)'
    )
    if not args.no_plots:
        from cloe_ros.cli.plots import flight_figures

        paths = flight_figures(vehicle, run_dir, {alg: label for alg, label in ALGORITHMS})
        print('Figures: ' + ', '.join(str(p) for p in paths))
    return 0
