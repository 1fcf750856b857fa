"""The ``cloe`` command: the demo, and the package's offline tools.

``cloe demo`` starts the nodes on a private, localhost-only DDS domain and ``cloe live`` relays a
DDS domain; every other subcommand works offline on files and needs no DDS domain.

Each subcommand's arguments are declared in :mod:`cloe_ros.cli.commands`, which imports nothing
that does the work; the subcommand itself lives in its own module, ``cloe_ros.cli.<command>``
with ``run(args) -> int``, imported only when it runs. ``cloe --help`` and ``cloe COMMAND --help``
therefore start in about the time Python takes to import numpy (no scipy, matplotlib, rosbags or
rclpy; a test checks it).
Errors a user can act on derive from :class:`cloe_ros.errors.CloeError` and are printed as
``ERROR: ...`` with exit status 1, never as a traceback. The exit statuses (:data:`EXIT_STATUS`,
shown by ``cloe --help``) are those a shell expects: 2 for a command line that does not parse
(argparse), 130 after Ctrl-C, and a reader that goes away while output is still to come
(``head``) ends the command quietly with 141, the status of a tool killed by SIGPIPE (128 + 13),
which is what ``cat`` or ``grep`` give in the same pipeline.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence

from cloe_ros import __version__
from cloe_ros.cli.commands import COMMANDS
from cloe_ros.errors import CloeError
from cloe_ros.threads import limit_blas_threads

#: Exit status of an error the command reports as ``ERROR: ...``.
EXIT_ERROR = 1
#: Exit status of a command line that does not parse (argparse's own).
EXIT_USAGE = 2
#: Exit status after Ctrl-C (SIGINT): 128 + 2, as the shell reports a process SIGINT ended.
EXIT_INTERRUPTED = 128 + signal.SIGINT
#: Exit status when standard output was closed by its reader: 128 + SIGPIPE, as standard tools.
EXIT_PIPE_CLOSED = 128 + signal.SIGPIPE

EXIT_STATUS = f"""\
exit status:
  0    success
  {EXIT_ERROR}    an error: one line "ERROR: ..." on stderr says what is wrong (bad input, a
       damaged bag, an output that exists, a full disk, ...) and nothing is left half-written
  {EXIT_USAGE}    the command line does not parse (unknown option, missing argument)
  {EXIT_INTERRUPTED}  interrupted by Ctrl-C (SIGINT); `cloe live`, which runs until Ctrl-C,
       ends with 0
  {EXIT_PIPE_CLOSED}  standard output was closed by its reader (e.g. `| head`) while output was
       still to come: the command stops quietly, as a tool ended by SIGPIPE
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cloe',
        description=(
            'Trajectory inference of quadrotors with CLOE, CLOE-SM and cloe_iv. `cloe demo` runs '
            'the nodes on a private, localhost-only DDS domain and `cloe live` relays a DDS '
            'domain; the other commands work offline on files and need no DDS.'
        ),
        epilog=EXIT_STATUS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for add_command in COMMANDS:
        add_command(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # exits with EXIT_USAGE (2) on a bad command line
    limit_blas_threads()
    try:
        status = int(args.run(args) or 0)
        sys.stdout.flush()  # what is still buffered goes now, while a closed pipe can be handled
    except BrokenPipeError:
        return _stdout_closed()
    except (CloeError, OSError) as err:
        print(f'ERROR: {err}', file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return EXIT_INTERRUPTED
    return status


def _stdout_closed() -> int:
    """The reader of standard output went away: stop quietly. Python's documented way (library
    reference, signal, "Note on SIGPIPE"): point standard output at devnull, so that the flush at
    interpreter exit does not fail a second time."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real file behind sys.stdout (tests)
        pass
    return EXIT_PIPE_CLOSED


if __name__ == '__main__':
    sys.exit(main())
