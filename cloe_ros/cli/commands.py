"""The command line of ``cloe``: every subcommand's arguments, and nothing that does the work.

``cloe --help`` and ``cloe COMMAND --help`` build these parsers and print, so this module imports
only what the parsers show (the algorithm and scenario names, numpy underneath); the module that
runs a command (``cloe_ros.cli.<command>``, with its scipy, rosbags, matplotlib) is imported when
that command runs (:func:`later`). A test checks that ``--help`` imports none of them.

Each ``add_<command>(subparsers)`` declares one subcommand and sets ``args.run``, the function
``run(args) -> int`` that carries it out.
"""

from __future__ import annotations

import argparse
import importlib
import math
from collections.abc import Callable
from pathlib import Path

from cloe_ros.core.algorithms import ALGORITHMS
from cloe_ros.core.simulator import SCENARIOS

#: ``cloe evaluate``: estimators and rate when neither the command line nor a --config file gives
#: them, and where ``evaluate sim`` starts scoring.
DEFAULT_ALGORITHMS = {'sim': ['cloe_sm', 'cloe_iv'], 'bag': ['cloe_iv']}
DEFAULT_RATE = 100.0
DEFAULT_SCORE_FROM_SIM = 30.0

EVALUATE_DESCRIPTION = """\
cloe evaluate sim scores a simulated scenario, where the truth is known: the parameter error per
block over time, and the prediction RMSE at 0.5 / 1 / 2 / 5 s beside the true-model,
constant-velocity and hold-position predictors. cloe evaluate bag BAG scores the predictions of a
recording against what the vehicle did next (no parameter truth), optionally with the recorded
future references as the plan. cloe evaluate corpus PATH... replays every flight of many bags as
cloe infer runs them and scores them per flight and as the median over flights, beside four
baselines, with the coverage of the 95 % radius.
"""

#: Help of ``--node``, which every command with ``--config`` takes.
NODE_HELP = (
    'read the --config file as rclpy gives it to the node NAME: every section that applies to '
    "that name ('/**', NAME's, nested namespaces, '/*' and '/**' patterns), in the file's "
    'order, the later values winning (default: %(default)s; e.g. cloe_shard1 for a node renamed '
    'so, /fleet/cloe_shard1 in a namespace)'
)


def add_node_option(p: argparse.ArgumentParser) -> None:
    """``--node NAME``: the node whose sections of a ``--config`` file are read
    (``cloe_ros.io.config.load_settings``)."""
    p.add_argument('--node', default='cloe_inference', metavar='NAME', help=NODE_HELP)


def later(command: str, name: str = 'run') -> Callable[[argparse.Namespace], int]:
    """``cloe_ros.cli.<command>.<name>``, imported when the command runs, not when it is parsed."""

    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(f'cloe_ros.cli.{command}'), name)(args)

    run.__qualname__ = f'{command}.{name}'
    return run


def add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'demo',
        help='run simulator, CLOE / CLOE-SM / CLOE-IV inference and the recorder as processes',
        description=(
            "On a private DDS domain, start bag_recorder, three cloe_inference nodes (the paper's "
            'CLOE and CLOE-SM side by side, and cloe_iv) and quadrotor_sim as separate processes, '
            'fly a scenario, stop them cleanly, then print the comparison table computed from the '
            'recorded bag and write the plots.'
        ),
    )
    p.add_argument(
        '-o',
        '--output',
        type=Path,
        default=Path('demo_results'),
        help='folder for the bag, plots and logs (default: %(default)s)',
    )
    p.add_argument(
        '--scenario',
        default='position',
        choices=sorted(SCENARIOS),
        help='simulated scenario (default: %(default)s)',
    )
    p.add_argument(
        '--duration',
        type=float,
        default=None,
        help="simulated seconds (default: the scenario's; position: 50)",
    )
    p.add_argument(
        '--speed',
        type=float,
        default=2.0,
        help='real-time factor of the simulation (default: %(default)s)',
    )
    p.add_argument(
        '--rate',
        type=float,
        default=100.0,
        help='inference rate, Hz of message time (default: %(default)s)',
    )
    p.add_argument('--no-plots', action='store_true', help='table only')
    p.set_defaults(run=later('demo'))


def add_paper(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'paper',
        help="reproduce the paper's experiments: tables and Figures 6-8, 10-12",
        description=(
            'Simulate the position-control (50 s, extended to 200 s for the parameter figures) '
            'and trajectory-control (140 s) scenarios with and without the disturbances of §6.1, '
            'run CLOE and CLOE-SM at 1 kHz, print the RMSE / ITAE / parameter-error tables beside '
            "the paper's values and write the figures."
        ),
    )
    p.add_argument(
        '-o',
        '--output',
        type=Path,
        default=Path('paper_results'),
        help='folder for the figures and results.json, new or empty (default: %(default)s)',
    )
    p.add_argument(
        '--force',
        action='store_true',
        help='write into the folder even if it is not empty (replaces results.json and figures)',
    )
    p.add_argument(
        '--rate',
        type=float,
        default=1000.0,
        help='simulation and estimation rate, Hz (default: %(default)s, as the paper)',
    )
    p.add_argument(
        '--parameter-duration',
        type=float,
        default=200.0,
        help='length of the position run for the parameter figures, s (default: 200)',
    )
    p.add_argument(
        '--quick',
        action='store_true',
        help='a smoke test: 200 Hz instead of --rate, and a 50 s position run for the parameter '
        'figures instead of --parameter-duration (the tables cover 50 s and 140 s as always)',
    )
    p.add_argument('--no-plots', action='store_true', help='tables only')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar')
    p.set_defaults(run=later('paper'))


def add_infer(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'infer',
        help='run the inference engine over a recorded bag and write its outputs to a new bag',
        description=(
            'Runs the same engine as the cloe_inference node over a rosbag2/MCAP bag: every '
            'vehicle with <ns>/odom (nav_msgs/Odometry) and <ns>/reference '
            '(geometry_msgs/PoseStamped) topics is inferred (with <ns>/reference_plan, '
            'nav_msgs/Path, when present); other topics are not inferred. Writes, under '
            '<ns>/<output_ns>/ (default output_ns: cloe), state, parameters, parameters_named, '
            'parameter_labels and, with predictions on, prediction, prediction_radius and '
            'prediction_markers into the bag OUTPUT, and /diagnostics (each vehicle\'s status as '
            'the node reports it, every diagnostics_period of message time), with copies of the '
            'inputs (and of <ns>/ground_truth and <ns>/true_parameters, when present) so the '
            'output bag is self-contained. The first input rejected for each reason is a '
            'warning.'
        ),
    )
    p.add_argument(
        'bag', type=Path, nargs='+', metavar='BAG',
        help='input bag: a rosbag2 directory or a single .mcap file; several: each is inferred '
        'into OUTPUT/<its name>',
    )  # fmt: skip
    p.add_argument(
        '-o', '--output', type=Path, required=True, metavar='OUTPUT',
        help='output bag directory (new); with several bags, a folder (new, or empty) for them',
    )  # fmt: skip
    p.add_argument(
        '--jobs', '-j', type=int, default=0,
        help='processes at once (default 0: one per core): several bags, one per process; one '
        'bag of several vehicles, its vehicles split into that many groups, the outputs written '
        'into the one output bag',
    )  # fmt: skip
    p.add_argument('--algorithm', choices=ALGORITHMS, help='estimator (default: cloe_iv)')
    p.add_argument('--rate', type=float, help='estimator rate, Hz of message time (default 100)')
    p.add_argument(
        '--config',
        type=Path,
        help="YAML with the node's parameters (cloe_inference: ros__parameters: ...)",
    )
    add_node_option(p)
    p.add_argument(
        '--vehicles',
        nargs='+',
        metavar='NS',
        help='only these vehicle namespaces (default: every one found)',
    )
    p.add_argument(
        '--no-inputs',
        action='store_true',
        help='do not copy the input topics (`cloe report` then has nothing to score against)',
    )
    p.add_argument(
        '--compression',
        choices=('zstd', 'none'),
        default='zstd',
        help='chunk compression of the output bag (default: %(default)s)',
    )
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar')
    p.set_defaults(run=later('infer'))


def add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'report',
        help='tables, figures and an HTML page about a recorded flight (inferring it if needed)',
        description=(
            'Report on a rosbag2/MCAP bag: an input bag (<ns>/odom, <ns>/reference) is first '
            'inferred into FOLDER/inferred_bag (as `cloe infer` does); an output bag of `cloe '
            'infer` is reported on as it is. Writes FOLDER/index.html (self-contained), '
            'FOLDER/summary.md, FOLDER/report.json and the figures; prints the main table.'
        ),
    )
    p.add_argument('bag', type=Path, help='bag directory (rosbag2, MCAP) or .mcap file')
    p.add_argument(
        '-o',
        '--output',
        type=Path,
        metavar='FOLDER',
        help='report folder (default: ./<bag name>_report)',
    )
    p.add_argument(
        '--force',
        action='store_true',
        help='write into FOLDER even if it is not empty (replaces the report files)',
    )
    p.add_argument(
        '--algorithm', choices=ALGORITHMS, help='estimator for an input bag (default: cloe_iv)'
    )
    p.add_argument('--rate', type=float, help='estimator rate for an input bag, Hz (default 100)')
    p.add_argument(
        '--config',
        type=Path,
        help="YAML with the node's parameters, for an input bag (like `cloe infer`)",
    )
    add_node_option(p)
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar')
    p.set_defaults(run=later('report'))


def add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'evaluate',
        help='score identification and prediction (a simulation, a bag or a corpus of bags) '
        'against baselines',
        description=EVALUATE_DESCRIPTION,
    )
    ev = p.add_subparsers(dest='target', metavar='TARGET', required=True)
    s = ev.add_parser('sim', help='a simulated scenario, truth known')
    s.add_argument(
        '--scenario',
        default='position',
        choices=sorted(SCENARIOS),
        help='the simulated scenario (default: %(default)s)',
    )
    s.add_argument('--duration', type=float, default=90.0, help='simulated s (default: 90)')
    _evaluate_algorithms(s, 'odometry and estimator rate, Hz', 'sim')
    s.add_argument(
        '--noise', action='store_true', help='measurement noise: 2 mm, 1 cm/s, 2 mrad, 0.01 rad/s'
    )
    s.add_argument('--no-disturbance', action='store_true', help='without the §6.1 disturbances')
    s.add_argument('--seed', type=int, default=0, help='noise seed (>= 0; default: 0)')
    s.add_argument(
        '--score-from',
        type=float,
        default=None,
        help='score predictions issued after this time, s; it must lie within the run '
        f'(default: {DEFAULT_SCORE_FROM_SIM:g})',
    )
    s.add_argument(
        '--segments',
        type=float,
        default=0.0,
        help='also score the predictions per segment of this many s (long runs; default 0: no '
        'segments)',
    )
    _evaluate_common(s)
    b = ev.add_parser('bag', help='a recorded flight: predictions against what happened next')
    b.add_argument('bag', type=Path, help='bag directory (rosbag2, MCAP) or .mcap file')
    b.add_argument(
        '--vehicle',
        default=None,
        help="vehicle namespace, '/' for the un-namespaced one (default: the first)",
    )
    _evaluate_algorithms(b, 'estimator rate, Hz', 'bag')
    b.add_argument(
        '--plan-from-reference',
        action='store_true',
        help='give the estimator the recorded future references as reference_plan',
    )
    b.add_argument(
        '--score-from',
        type=float,
        default=5.0,
        help='score predictions issued this many s after the start (default: 5)',
    )
    b.add_argument(
        '--score-to',
        type=float,
        default=math.inf,
        help='score only predictions issued and reaching their horizon by this many s after the '
        'start (default: the end), e.g. to leave out a landing',
    )
    _evaluate_common(b)
    c = ev.add_parser(
        'corpus',
        help='many recorded flights: predictions against what happened next, per flight and '
        'as the median over flights, beside the baselines',
    )
    c.add_argument(
        'paths', type=Path, nargs='+', metavar='PATH',
        help='bag directories or .mcap files, or folders holding them (searched recursively)',
    )  # fmt: skip
    c.add_argument(
        '--jobs', '-j', type=int, default=0,
        help='flights evaluated at once, in separate processes (default 0: one per core; with '
        'more processes than bags, each vehicle of a bag of several is a job of its own)',
    )  # fmt: skip
    c.add_argument(
        '--score-from', type=float, default=5.0,
        help='score predictions issued this many s after the first odometry (default: 5)',
    )  # fmt: skip
    c.add_argument(
        '--config', type=Path,
        help="YAML with the node's parameters (as for `cloe infer`), the same for every flight",
    )  # fmt: skip
    add_node_option(c)
    c.add_argument('--json', type=Path, help='also write the numbers to this JSON file (new)')
    c.add_argument('--force', action='store_true', help='replace the --json file if it exists')
    c.add_argument('-q', '--quiet', action='store_true', help='no progress line')
    p.set_defaults(run=later('evaluate'))


def _evaluate_algorithms(p: argparse.ArgumentParser, rate: str, target: str) -> None:
    p.add_argument(
        '--algorithms',
        nargs='+',
        choices=ALGORITHMS,
        help="estimators to run (default: the --config file's algorithm, else "
        f'{" ".join(DEFAULT_ALGORITHMS[target])})',
    )
    p.add_argument(
        '--rate',
        type=float,
        help=f"{rate} (default: the --config file's rate, else {DEFAULT_RATE:g})",
    )


def _evaluate_common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        '--config',
        type=Path,
        help="YAML with the node's parameters (as for `cloe infer`); its algorithm and rate apply "
        'unless --algorithms / --rate are given',
    )
    add_node_option(p)
    p.add_argument('--json', type=Path, help='also write the numbers to this JSON file (new)')
    p.add_argument('--force', action='store_true', help='replace the --json file if it exists')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar')


def add_bag(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'bag',
        help='inspect bags; recover a bag whose recorder was killed; make a bag of a NanoBench '
        'flight',
        description='Inspect rosbag2 bags (MCAP storage), recover incomplete ones, and make a bag '
        'of the interface contract from a NanoBench flight CSV.',
    )
    bag_sub = p.add_subparsers(dest='bag_command', metavar='ACTION', required=True)

    info = bag_sub.add_parser(
        'info',
        help='topics, types, message counts and time span of a bag',
        description=(
            'Print the topics, types, message counts, duration, start and end of a bag, as its '
            'files hold them (a "warning:" line where metadata.yaml says otherwise), and check '
            'its data: every record is read, chunks are checked against their CRCs or message '
            'indexes. A damaged bag ends with status 1.'
        ),
    )
    info.add_argument(
        'bag', type=Path, metavar='BAG', help='rosbag2 directory (or one .mcap file)'
    )
    info.set_defaults(run=later('bag', 'run_info'))

    rec = bag_sub.add_parser(
        'recover',
        help='rebuild a complete bag from an incomplete .mcap (recorder killed)',
        description=(
            'Read the .mcap file(s) of BAG record by record, step over damaged records where '
            'readable records follow (stop where none do: a cut, zero-filled or garbage end), '
            'and write every message that was fully on disk and intact into a new, complete '
            'bag (metadata.yaml, MCAP summary). BAG is never modified.'
        ),
    )
    rec.add_argument('bag', type=Path, metavar='BAG', help='rosbag2 directory (or one .mcap file)')
    rec.add_argument(
        '-o',
        '--output',
        type=Path,
        default=None,
        metavar='OUT',
        help='bag directory to create (default: <BAG>_recovered; never overwritten)',
    )
    rec.add_argument(
        '--compression',
        choices=('zstd', 'none'),
        default='zstd',
        help='chunk compression of the new bag (default: %(default)s)',
    )
    rec.set_defaults(run=later('bag', 'run_recover'))

    nano = bag_sub.add_parser(
        'nanobench',
        help='a bag of the interface contract from a NanoBench flight CSV',
        description=(
            'Convert one flight of the NanoBench dataset (Crazyflie 2.1 under Vicon; '
            'github syediu/nanobench-iros2026, BSD-3-Clause) from its CSV into a rosbag2/MCAP '
            'bag: <ns>/odom (nav_msgs/Odometry: Vicon pose in world, twist in the body frame) '
            'at every row, and <ns>/reference (geometry_msgs/PoseStamped: the controller\'s '
            'setpoint, sp_ctrltarget_*) from the first non-zero setpoint on. The corpus of real '
            'flights the package is evaluated on was made this way.'
        ),
    )
    nano.add_argument('csv', type=Path, metavar='CSV', help='the flight CSV of NanoBench')
    nano.add_argument('-o', '--output', type=Path, required=True, metavar='OUT',
                      help='bag directory to create (never overwritten)')  # fmt: skip
    nano.add_argument('--namespace', default='', metavar='NS',
                      help='vehicle namespace of the topics (default: none)')  # fmt: skip
    nano.set_defaults(run=later('bag', 'run_nanobench'))


def add_live(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'live',
        help='relay the ROS 2 topics of the domain to the Foxglove app (WebSocket), live',
        description=(
            'Subscribe to every topic of the DDS domain (ROS_DOMAIN_ID) that has a publisher, or '
            'to --topics, and serve them to the Foxglove app over its WebSocket protocol: in the '
            'app, Open connection, Foxglove WebSocket, ws://HOST:PORT; then import the layout '
            'share/cloe_ros/foxglove/cloe_lab.json (or cloe_demo.json). Topics appearing later '
            'are relayed as they appear. Needs the foxglove-sdk package (`make install` installs '
            "it; else `pip install 'cloe_ros[live]'`). Ctrl-C stops."
        ),
    )
    p.add_argument(
        '--host',
        default='127.0.0.1',
        help='address to serve on (default: %(default)s; 0.0.0.0: every interface)',
    )
    p.add_argument('--port', type=int, default=8765, help='port (default: %(default)s)')
    p.add_argument('--topics', nargs='+', metavar='TOPIC',
                   help='relay only these topics (default: every topic except /rosout and '
                   '/parameter_events)')  # fmt: skip
    p.set_defaults(run=later('live'))


#: Every subcommand, in the order ``cloe --help`` lists them.
COMMANDS = (add_demo, add_paper, add_infer, add_report, add_evaluate, add_bag, add_live)
