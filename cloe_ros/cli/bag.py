"""``cloe bag``: look into bags and recover the ones whose recorder died.

* ``cloe bag info BAG`` — topics, types, message counts, duration, start and end (log time).
* ``cloe bag recover BAG [-o OUT]`` — a complete bag from an ``.mcap`` without summary/footer
  (recorder killed, power lost): every message fully on disk, written to ``<BAG>_recovered``.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from cloe_ros.cli.errors import CliError
from cloe_ros.io.reader import BagError, BagReader
from cloe_ros.io.recover import BagInfo, RecoveryReport, TopicSummary, bag_info, recover_bag


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
        description='Print the topics, types, message counts, duration, start and end of a bag.',
    )
    info.add_argument(
        'bag', type=Path, metavar='BAG', help='rosbag2 directory (or one .mcap file)'
    )
    info.set_defaults(run=run_info)

    rec = bag_sub.add_parser(
        'recover',
        help='rebuild a complete bag from an incomplete .mcap (recorder killed)',
        description=(
            'Read the .mcap file(s) of BAG record by record, stop at the first truncated or '
            'corrupt record, and write every message that was fully on disk into a new, complete '
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


def mcap_file_info(path: Path) -> BagInfo:
    """What ``cloe bag info`` shows, for a single ``.mcap`` file (from its own summary)."""
    try:
        with BagReader(path) as reader:
            topics = tuple(
                TopicSummary(name, info.msgtype, info.count)
                for name, info in reader.topics.items()
            )
            storage = 'mcap, a single file without metadata.yaml'
            return BagInfo(path, (path.name,), storage, topics, reader.message_count,
                           reader.start_ns, reader.end_ns)  # fmt: skip
    except BagError as err:
        raise CliError(str(err)) from err


def run_info(args: argparse.Namespace) -> int:
    bag: Path = args.bag
    if not bag.exists():
        raise CliError(f'{bag} does not exist')
    if bag.is_file() and bag.suffix == '.mcap':
        info = mcap_file_info(bag)
    elif bag.is_file():
        raise CliError(
            f'{bag} is a file, not a bag: expected a rosbag2 directory (or a single .mcap file)'
        )
    else:
        info = bag_info(bag)
    for line in info.lines():
        print(line)
    return 0


def recovery_lines(report: RecoveryReport) -> list[str]:
    """``report.lines()``, except for a file whose last chunk is cut off: the messages taken from
    that chunk lie past ``end`` (where the last complete record ends), so ``end`` is not the
    number of usable bytes there."""
    lines = report.lines()
    for i, f in enumerate(report.files):
        if f.complete or not f.partial_chunk_messages:
            continue
        reason = re.sub(r' \(offset \d+ of \d+ bytes\)$', '', f.reason)
        lines[i] = (
            f'{f.path}: incomplete ({f.size} bytes), complete records up to byte {f.end}, then a '
            f'chunk cut off by the end of the file: {reason}; {f.messages} messages read'
        )
    return lines


def run_recover(args: argparse.Namespace) -> int:
    report = recover_bag(args.bag, args.output, compression=args.compression)
    for line in recovery_lines(report):
        print(line)
    return 0
