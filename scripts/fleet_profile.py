"""The engine path of the inference node in one process, for profiling: N vehicles fed raw CDR
(the simulated position flight, each vehicle its copy), one ``Fleet.advance`` per odometry tick
of all of them (``--batch 0``: each vehicle at each of its messages), every output encoded.

    .venv/bin/python scripts/fleet_profile.py --vehicles 10
    pip install pyinstrument; python -m pyinstrument scripts/fleet_profile.py --vehicles 10

Prints the CPU time per odometry message (no DDS: what the node adds to the receiving), with
one BLAS thread, as the nodes run (cloe_ros/threads.py: OpenBLAS's spinning threads would count
in the process's CPU time, about doubling it at one vehicle).

``--kernels`` also times every call Python makes into the compiled kernels (``cloe_ros.core.
kernels*``: the arithmetic, with the LAPACK and BLAS calls they make) and prints their time per
odometry message, kernel by kernel: what the same arithmetic costs however the Python around it
is written. (The timing wrappers add about a microsecond per message to the total.)
"""

from __future__ import annotations

import argparse
import collections
import importlib
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
    parser.add_argument('--inputs', type=int, default=3000,
                        help='inputs per vehicle (odometry and references; the simulated flight '
                             'holds 3002)')  # fmt: skip
    parser.add_argument('--kernels', action='store_true',
                        help='also the time of the compiled kernels per odometry message')
    args = parser.parse_args()
    limit_blas_threads()  # as the nodes do
    spent = time_kernels() if args.kernels else None
    engine_config, output_config = build_configs(dict(DEFAULTS))
    odoms, refs = flight_messages(simulated_flight())
    inputs = in_time_order(odoms, refs)
    if args.inputs > len(inputs):
        parser.error(f'--inputs: the simulated flight holds {len(inputs)} inputs per vehicle, '
                     f'not {args.inputs}')  # fmt: skip
    raws = [(kind, cdr.encode_odometry(m) if kind == 'odom' else cdr.encode_pose_stamped(m))
            for kind, m in inputs[: args.inputs]]  # fmt: skip
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
    if spent is not None:
        total = sum(seconds for seconds, _ in spent.values())
        print(f'of which in compiled kernels: {1e6 * total / count:.1f} us per odometry message')
        for name, (seconds, calls) in sorted(spent.items(), key=lambda kv: -kv[1][0]):
            print(f'  {1e6 * seconds / count:6.2f} us per message  {calls:8d} calls '
                  f'{1e6 * seconds / calls:8.1f} us per call  {name}')
    return 0


KERNEL_MODULES = ('kernels', 'kernels_combine', 'kernels_covariance', 'kernels_ensemble',
                  'kernels_identifier', 'kernels_models')  # fmt: skip


def time_kernels() -> dict[str, list]:
    """Wrap every compiled kernel of ``KERNEL_MODULES`` in a timer wherever the package's
    modules (all imported by now, the kernels loaded) hold it; returns the table the timers fill:
    name -> [seconds, calls] (wall time, one thread)."""
    from cloe_ros.core import ahead

    if ahead.MODULE is not None:  # the kernels built ahead: the module's functions
        built = {id(getattr(ahead.MODULE, name)) for name in dir(ahead.MODULE)
                 if not name.startswith('_')}  # (its kernels: 'kernels__iv_step_filter', ...)

        def is_kernel(value):
            return id(value) in built

    else:
        from numba.core.registry import CPUDispatcher

        def is_kernel(value):
            return isinstance(value, CPUDispatcher)

    spent: dict[str, list] = collections.defaultdict(lambda: [0.0, 0])
    clock = time.perf_counter

    def timed(name, kernel):
        def call(*args):
            start = clock()
            try:
                return kernel(*args)
            finally:
                entry = spent[name]
                entry[0] += clock() - start
                entry[1] += 1

        return call

    ours = [m for name, m in sys.modules.items() if name.startswith('cloe_ros')]
    for short in KERNEL_MODULES:
        module = importlib.import_module(f'cloe_ros.core.{short}')
        for attr, kernel in list(vars(module).items()):
            if is_kernel(kernel):
                wrapper = timed(f'{short}.{attr}', kernel)
                for holder in ours:
                    if getattr(holder, attr, None) is kernel:
                        setattr(holder, attr, wrapper)
    return spent


if __name__ == '__main__':
    sys.exit(main())
