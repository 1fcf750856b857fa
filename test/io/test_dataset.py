"""cloe_ros.io.dataset on bags whose log times are not the message times (recordings)."""

from __future__ import annotations

import numpy as np
from bag_fixtures import simulate, write_sim_bag

from cloe_ros.cli.infer import infer_bag
from cloe_ros.io import messages
from cloe_ros.io.dataset import load_flight
from cloe_ros.io.reader import BagReader
from cloe_ros.io.writer import BagWriter


def test_parameters_are_placed_at_message_time_in_a_recording(tmp_path):
    """A recorder logs reception times. A simulation at 2x real time is recorded in half its
    duration, and ``parameters`` (Float64MultiArray, no header) must still line up with the
    stamped outputs rather than with the wall clock."""
    inferred = tmp_path / 'inferred'
    infer_bag(write_sim_bag(tmp_path / 'sim', simulate(6.0)), inferred,
              {'algorithm': 'cloe_sm', 'prediction_horizon': 0.0})  # fmt: skip
    recorded = tmp_path / 'recorded'
    origin = None
    with BagReader(inferred) as reader, BagWriter(recorded) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for topic, log_ns, raw in reader.messages():
            origin = log_ns if origin is None else origin
            # received at half the pace, 3 ms late, 10 s of wall clock after the stamps' origin
            writer.write(topic, origin + 10**10 + (log_ns - origin) // 2 + 3_000_000, raw)
    original = load_flight(inferred)[''].outputs['cloe'].parameters
    loaded = load_flight(recorded)[''].outputs['cloe'].parameters
    np.testing.assert_array_equal(loaded.values, original.values)
    # back on the estimates' time line (state and parameters share the delay), far from the log
    # times the recorder wrote
    assert np.abs(loaded.t_ns - original.t_ns).max() <= 1
    with BagReader(recorded) as reader:
        logged = np.array([t for _, t, _ in reader.messages(['/cloe/parameters'])])
    assert np.abs(logged - original.t_ns).min() > 10**9


def test_a_recording_names_the_algorithm_from_the_nodes_diagnostics(tmp_path):
    """A recording of running nodes has no custom data; the inference nodes' ``/diagnostics``
    (recorded beside the outputs) say which algorithm produced which output namespace. A
    malformed diagnostics message is skipped, not fatal."""
    inferred = tmp_path / 'inferred'
    infer_bag(write_sim_bag(tmp_path / 'sim', simulate(3.0)), inferred,
              {'algorithm': 'cloe_sm', 'prediction_horizon': 0.0})  # fmt: skip
    recorded = tmp_path / 'recorded'

    def report(algorithm):
        values = (('algorithm', algorithm), ('output_ns', 'cloe'), ('rate_hz', '100'))
        statuses = [
            messages.Status(messages.OK, 'recorder', 'ok', 'bag', (('recorded', '3'),)),
            messages.Status(messages.OK, 'cloe_inference: /', 'running', '/', values),
        ]
        return messages.encode_diagnostics(0, statuses)

    with BagReader(inferred) as reader, BagWriter(recorded) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        writer.add_topic('/diagnostics', messages.DIAGNOSTIC_ARRAY)
        last = 0
        for topic, log_ns, raw in reader.messages():
            writer.write(topic, log_ns, raw)
            last = log_ns
        # the algorithm was changed at runtime: the last report counts
        writer.write('/diagnostics', last + 1, report('cloe'))
        writer.write('/diagnostics', last + 2, b'\x00\x01\x00\x00garbage')
        writer.write('/diagnostics', last + 3, report('cloe_sm'))
    assert load_flight(inferred)[''].outputs['cloe'].algorithm == 'cloe_sm'  # custom data
    with BagReader(recorded) as reader:
        assert not reader.custom_data
    assert load_flight(recorded)[''].outputs['cloe'].algorithm == 'cloe_sm'
