"""A bag of many vehicles from a bag of one: its odom and reference under ``/uav0``, ``/uav1``,
..., each vehicle's positions (odometry and reference) shifted by ``--spacing`` m in x.

    .venv/bin/python scripts/make_swarm_bag.py bags/position /tmp/swarm24 --vehicles 24

For measuring ``cloe infer`` on many vehicles (EVALUATION.md, section 4).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cloe_ros.io import cdr, messages
from cloe_ros.io.reader import BagReader
from cloe_ros.io.writer import BagWriter


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='a bag with /odom and /reference')
    parser.add_argument('output', type=Path, help='the new bag (a folder that does not exist)')
    parser.add_argument('--vehicles', type=int, default=24)
    parser.add_argument('--spacing', type=float, default=2.0, help='m between vehicles in x')
    args = parser.parse_args()
    codecs = {'/odom': (messages.decode_odometry, cdr.encode_odometry),
              '/reference': (messages.decode_pose_stamped, cdr.encode_pose_stamped)}  # fmt: skip
    names = [f'/uav{k}' for k in range(args.vehicles)]
    with BagReader(args.bag) as reader, BagWriter(args.output) as writer:
        for ns in names:
            for topic in codecs:
                writer.add_topic(ns + topic, reader.topics[topic].msgtype)
        for topic, log_ns, raw in reader.messages(list(codecs)):
            decode, encode = codecs[topic]
            sample = decode(raw)
            for k, ns in enumerate(names):
                shift = np.array([args.spacing * k, 0.0, 0.0])
                moved = dataclasses.replace(sample, position=sample.position + shift)
                writer.write(ns + topic, log_ns, encode(moved))
    print(f'wrote {args.output}: {len(names)} vehicles')
    return 0


if __name__ == '__main__':
    sys.exit(main())
