"""The ``cloe`` command: the demo, and the package's offline tools.

``cloe demo`` starts the nodes on a private, localhost-only DDS domain; every other subcommand
works offline on files and needs no DDS domain.

Each subcommand lives in its own module with ``add_parser(subparsers)`` and ``run(args) -> int``.
Errors a user can act on derive from :class:`cloe_ros.errors.CloeError` and are printed as
``ERROR: ...`` with exit status 1, never as a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from cloe_ros import __version__
from cloe_ros.cli import bag, demo, evaluate, infer, live, paper, report
from cloe_ros.errors import CloeError

SUBCOMMANDS = (demo, paper, infer, report, evaluate, bag, live)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cloe',
        description=(
            'Trajectory inference of quadrotors with CLOE, CLOE-SM and cloe_iv. `cloe demo` runs '
            'the nodes on a private, localhost-only DDS domain; the other commands work offline '
            'on files and need no DDS.'
        ),
    )
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (CloeError, OSError) as err:
        print(f'ERROR: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
