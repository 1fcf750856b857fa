"""Run a command while busy loops occupy every core: the test suite as a busy machine runs it.

    .venv/bin/python scripts/under_load.py [--workers N] -- COMMAND [ARG ...]

Starts N (default: the number of cores, ``os.cpu_count()``) Python processes that each spin
``while True: pass``, runs COMMAND, then kills the loops whatever COMMAND's outcome (also on
Ctrl-C or SIGTERM) and exits with COMMAND's status. ``make test-under-load`` runs the suite so.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

BUSY_LOOP = 'while True: pass'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument(
        '--workers', type=int, default=os.cpu_count() or 1,
        help='busy loops to start (default: one per core, %(default)s here)',
    )  # fmt: skip
    parser.add_argument('command', nargs=argparse.REMAINDER, help='the command (after --)')
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ['--'] else args.command
    if not command:
        parser.error('no command given (after --)')
    if args.workers < 0:
        parser.error(f'--workers must be >= 0, got {args.workers}')

    # SIGTERM ends this process through the same `finally` as Ctrl-C does
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    loops: list[subprocess.Popen] = []
    started = time.monotonic()
    try:
        for _ in range(args.workers):
            loops.append(subprocess.Popen([sys.executable, '-c', BUSY_LOOP]))
        print(
            f'under_load: {len(loops)} busy loop(s) running (pids '
            f'{", ".join(str(p.pid) for p in loops)}); running: {" ".join(command)}',
            flush=True,
        )
        status = subprocess.call(command)
    except KeyboardInterrupt:
        status = 130
    finally:
        for proc in loops:
            proc.kill()
        for proc in loops:
            proc.wait()
    print(
        f'under_load: {" ".join(command)} exited with status {status} after '
        f'{time.monotonic() - started:.0f} s; {len(loops)} busy loop(s) stopped',
        flush=True,
    )
    return status


if __name__ == '__main__':
    sys.exit(main())
