"""``cloe bag``: look into bags and recover the ones whose recorder died.

* ``cloe bag info BAG`` — topics, types, message counts, duration, start and end (log time),
  from the files; where metadata.yaml disagrees, a ``warning:`` line (status 0). The data are
  read through to check them (CRCs, message indexes, counts), and a damaged bag ends with
  status 1.
* ``cloe bag recover BAG [-o OUT]`` — a complete bag from an ``.mcap`` without summary/footer
  (recorder killed, power lost) or with damaged records: every message fully on disk and intact,
  written to ``<BAG>_recovered``.
* ``cloe bag nanobench CSV -o OUT`` — a bag of the interface contract from a flight of the
  public NanoBench dataset (:mod:`cloe_ros.io.nanobench`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cloe_ros.cli.errors import CliError
from cloe_ros.io.bag_info import bag_info
from cloe_ros.io.recover import recover_bag


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'bag',
        help='inspect bags; recover a bag whose recorder was killed',
        description='Inspect rosbag2 bags (MCAP storage) and recover incomplete ones.',
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
    info.set_defaults(run=run_info)

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
    rec.set_defaults(run=run_recover)

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
    nano.set_defaults(run=run_nanobench)


def run_info(args: argparse.Namespace) -> int:
    bag: Path = args.bag
    info = bag_info(bag)
    for line in info.lines():
        print(line)
    if info.damage:
        raise CliError(
            f'{bag} is damaged (see "damaged:" above): `cloe bag recover {bag}` writes a bag with '
            'every message that can still be read'
        )
    return 0


def run_recover(args: argparse.Namespace) -> int:
    report = recover_bag(args.bag, args.output, compression=args.compression)
    for line in report.lines():
        print(line)
    return 0


def run_nanobench(args: argparse.Namespace) -> int:
    from cloe_ros.io.nanobench import convert_nanobench

    done = convert_nanobench(args.csv, args.output, args.namespace)
    print(f'wrote {args.output}: {done.odometry} odometry and {done.references} reference '
          f'messages' + (f'; {done.skipped} row(s) with non-finite values left out'
                         if done.skipped else ''))  # fmt: skip
    return 0
