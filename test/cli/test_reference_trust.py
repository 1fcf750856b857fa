"""Reference trust end to end (``cloe infer``): a flight whose reference runs away, made from the
sample bag, and the same flight with its reference left as it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloe_ros.cli.infer import infer_bag
from cloe_ros.core.samples import PoseSample
from cloe_ros.io import messages
from cloe_ros.io.dataset import load_flight
from cloe_ros.io.reader import BagReader
from cloe_ros.io.writer import BagWriter

REPO = Path(__file__).resolve().parents[2]
POSITION = REPO / 'bags' / 'position'
NS = 1_000_000_000
#: From this many s after the first reference, the logged y setpoint runs away at 1 m/s while the
#: vehicle keeps flying the scenario (as a velocity-mode setpoint or a logging fault would).
RUNAWAY_AFTER = 25.0

pytestmark = pytest.mark.slow


def runaway_bag(target: Path) -> Path:
    """The position sample bag with its /reference's y running away after ``RUNAWAY_AFTER``."""
    with BagReader(POSITION) as reader, BagWriter(target) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        start = None
        for topic, log_ns, raw in reader.messages():
            if topic == '/reference':
                sample = messages.decode_pose_stamped(raw)
                start = sample.stamp_ns if start is None else start
                late = (sample.stamp_ns - start) / NS - RUNAWAY_AFTER
                if late > 0:
                    position = sample.position + np.array([0.0, late, 0.0])
                    raw = messages.encode_pose_stamped(
                        PoseSample(sample.stamp_ns, sample.frame_id, position,
                                            sample.orientation))  # fmt: skip
            writer.write(topic, log_ns, raw)
    return target


def outputs(bag: Path) -> dict:
    """The inferred outputs of the root vehicle, and its truth, by topic."""
    vehicle = load_flight(bag)['']
    (out,) = vehicle.outputs.values()
    return {'vehicle': vehicle, 'out': out}


def tracked_y(out) -> tuple[np.ndarray, np.ndarray]:
    """Times (s from the first parameters message) and reference.tracked.y."""
    labels = out.labels
    t = (out.parameters.t_ns - out.parameters.t_ns[0]) / NS
    return t, out.parameters.values[:, labels.index('reference.tracked.y')]


def prediction_miss(vehicle, out) -> tuple[np.ndarray, np.ndarray]:
    """Per prediction, the largest distance of a predicted pose from where the vehicle was, and
    the issue times (s from the first parameters message)."""
    truth = vehicle.ground_truth
    miss = []
    for stamps, positions in zip(out.prediction.stamps_ns, out.prediction.positions):
        ok = np.isfinite(positions).all(axis=1) & (stamps <= truth.t_ns[-1])
        actual = np.column_stack([np.interp(stamps[ok], truth.t_ns, truth.values[:, i])
                                  for i in (0, 4, 10)])  # fmt: skip
        miss.append(np.max(np.linalg.norm(positions[ok] - actual, axis=1)) if ok.any() else 0.0)
    issued = (out.prediction.t_ns - out.parameters.t_ns[0]) / NS
    return np.array(miss), issued


@pytest.fixture(scope='module')
def runaway(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp('runaway')
    bag = runaway_bag(base / 'runaway')
    runs = {}
    for trust in (True, False):
        out = base / f'inferred_{trust}'
        # the control: neither the trust check nor the guard, the closed loop alone
        infer_bag(bag, out, {} if trust else {'reference_trust': False, 'prediction_guard': False})
        runs[trust] = outputs(out)
    return runs


def test_a_runaway_reference_is_reported_not_tracked_and_nothing_follows_it(runaway):
    vehicle, out = runaway[True]['vehicle'], runaway[True]['out']
    t, tracked = tracked_y(out)
    first_ref = (vehicle.reference.t_ns[0] - out.parameters.t_ns[0]) / NS
    after = t - first_ref - RUNAWAY_AFTER
    # tracked before the runaway (once in flight), not tracked within 5 s of its start, to the end
    assert np.all(tracked[(t > 6.0) & (after < 0)] == 1.0)
    assert np.all(tracked[after > 5.0] == 0.0)
    # once it is found not tracked, the predictions never draw the vehicle far from where it flew
    # (the reference ends 25 m off)
    miss, issued = prediction_miss(vehicle, out)
    late = issued > first_ref + RUNAWAY_AFTER + 5.0
    assert np.max(miss[late]) < 1.0, np.max(miss[late])
    # identification of the y block pauses: its estimate does not move while not tracked
    labels = out.labels
    cols = [i for i, name in enumerate(labels) if name.startswith('theta_hat.y_phi.')]
    frozen = out.parameters.values[after > 6.0][:, cols]
    np.testing.assert_array_equal(frozen, np.broadcast_to(frozen[0], frozen.shape))
    # the published state stays on the vehicle
    state, truth = out.state, vehicle.ground_truth
    late = (state.t_ns - state.t_ns[0]) / NS > RUNAWAY_AFTER + 5.0
    y_true = np.interp(state.t_ns[late], truth.t_ns, truth.values[:, 4])
    assert np.max(np.abs(state.values[late, 4] - y_true)) < 0.05


def test_the_closed_loop_alone_follows_the_runaway_reference(runaway):
    """The same flight with reference_trust and prediction_guard off: the test above can fail."""
    vehicle, out = runaway[False]['vehicle'], runaway[False]['out']
    _, tracked = tracked_y(out)
    assert np.all(tracked == 1.0)
    miss, issued = prediction_miss(vehicle, out)
    first_ref = (vehicle.reference.t_ns[0] - out.parameters.t_ns[0]) / NS
    assert np.max(miss[issued > first_ref + RUNAWAY_AFTER + 5.0]) > 2.0


def test_a_reference_that_is_tracked_changes_nothing(tmp_path):
    """On the sample bag as recorded, no channel is ever found not tracked in flight, and the
    estimates and parameters equal those with the check off, to the bit."""
    runs = {}
    for trust in (True, False):
        out = tmp_path / f'inferred_{trust}'
        infer_bag(POSITION, out, {'reference_trust': trust})
        runs[trust] = outputs(out)['out']
    on, off = runs[True], runs[False]
    labels = on.labels
    tracked = on.parameters.values[:, [labels.index(f'reference.tracked.{c}')
                                       for c in ('x', 'y', 'psi', 'z')]]  # fmt: skip
    commanded_up = on.parameters.t_ns > on.parameters.t_ns[0] + 3 * NS  # after the take-off
    assert np.all(tracked[commanded_up] == 1.0)
    np.testing.assert_array_equal(on.state.values, off.state.values)
    keep = [i for i, name in enumerate(labels) if not name.startswith('reference.tracked.')]
    np.testing.assert_array_equal(on.parameters.values[:, keep], off.parameters.values[:, keep])
