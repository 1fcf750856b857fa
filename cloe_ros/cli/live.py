"""``cloe live``: relay the package's topics to the Foxglove app, live, over its WebSocket
protocol (``foxglove-sdk``). Like ``cloe demo`` it needs a DDS domain (``ROS_DOMAIN_ID``); the
relay itself is :mod:`cloe_ros.ros.live_relay`."""

from __future__ import annotations

import argparse
import sys

from cloe_ros.cli.errors import CliError


def run(args: argparse.Namespace) -> int:
    if not 0 <= args.port <= 65535:
        raise CliError(f'--port must be within [0, 65535], got {args.port}')
    try:
        from cloe_ros.ros import live_relay
    except ImportError as err:
        if 'foxglove' not in str(err):
            raise
        raise CliError(
            'cloe live needs the foxglove-sdk package: `make install` installs it, or '
            "`pip install 'cloe_ros[live]'`"
        ) from err
    return live_relay.serve(
        args.host, args.port, args.topics, print_line=lambda text: print(text, flush=True)
    )


if __name__ == '__main__':
    sys.exit(run(argparse.Namespace(host='127.0.0.1', port=8765, topics=None)))
