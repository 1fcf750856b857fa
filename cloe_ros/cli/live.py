"""``cloe live``: relay the package's topics to the Foxglove app, live, over its WebSocket
protocol (``foxglove-sdk``). Like ``cloe demo`` it needs a DDS domain (``ROS_DOMAIN_ID``); the
relay itself is :mod:`cloe_ros.ros.live_relay`."""

from __future__ import annotations

import argparse
import sys

from cloe_ros.cli.errors import CliError


def add_parser(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(run=run)


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
