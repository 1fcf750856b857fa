"""The engine path of the inference node in one process, for profiling: N vehicles fed raw CDR
(the simulated position flight, each vehicle its copy), one ``Fleet.advance`` per odometry tick
of all of them (``--batch 0``: each vehicle at each of its messages), every output encoded.

    .venv/bin/python scripts/fleet_profile.py --vehicles 10
    pip install pyinstrument; python -m pyinstrument scripts/fleet_profile.py --vehicles 10

Prints the CPU time per odometry message (no DDS: what the node adds to the receiving), with
one BLAS thread, as the nodes run (cloe_ros/threads.py: OpenBLAS's spinning threads would count
in the process's CPU time, about doubling it at one vehicle).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cloe_ros.core.engine import VehicleEngine
from cloe_ros.core.fleet import Fleet
from cloe_ros.io import cdr, messages
from cloe_ros.io.config import DEFAULTS, build_configs
from cloe_ros.io.outputs import OutputEncoder
from cloe_ros.threads import limit_blas_threads
from test.core.test_engine import in_time_order, simulated_flight
from test.core.test_engine import messages as flight_messages


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--vehicles', type=int, default=10)
    parser.add_argument('--batch', type=int, choices=(0, 1), default=1,
                        help='1: one batch per odometry tick; 0: each vehicle alone')
    parser.add_argument('--inputs', type=int, default=3000, help='inputs per vehicle')
    args = parser.parse_args()
    limit_blas_threads()  # as the nodes do
    engine_config, output_config = build_configs(dict(DEFAULTS))
    odoms, refs = flight_messages(simulated_flight())
    raws = [(kind, cdr.encode_odometry(m) if kind == 'odom' else cdr.encode_pose_stamped(m))
            for kind, m in in_time_order(odoms, refs)[: args.inputs]]  # fmt: skip
    names = [f'/uav{i}' for i in range(args.vehicles)]
    fleet = Fleet(pooled=bool(args.batch))
    encoders = {}
    for name in names:
        fleet.add(VehicleEngine(engine_config, name=name))
        encoders[name] = OutputEncoder(output_config, name, engine_config.prediction.enabled)

    def publish(estimates):
        for v, of_vehicle in estimates.items():
            for est in of_vehicle:
                for _ in encoders[v].encode(est, 'world', 'base_link'):
                    pass

    start, count = time.process_time(), 0
    for kind, raw in raws:
        for name in names:
            engine = fleet.engines[name]
            if kind == 'odom':
                engine.add_odometry(messages.decode_odometry(raw))
                count += 1
            else:
                engine.add_reference(messages.decode_pose_stamped(raw))
            if not args.batch:
                publish(fleet.advance([name]))
        if args.batch and kind == 'odom':
            publish(fleet.advance(names))
    per = 1e6 * (time.process_time() - start) / count
    print(f'{args.vehicles} vehicles, batch {args.batch}: {per:.0f} us of CPU per odometry '
          'message')
    return 0


if __name__ == '__main__':
    sys.exit(main())
