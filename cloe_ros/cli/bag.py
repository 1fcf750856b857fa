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
