"""NanoBench CSV -> bag of the interface contract (``cloe bag nanobench``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from corpus import FLIGHTS

from cloe_ros.core.kinematics import euler_to_quaternion, euler_to_rotation
from cloe_ros.io import messages
from cloe_ros.io.errors import BagError
from cloe_ros.io.nanobench import COLUMNS, convert_nanobench, parse_stamp
from cloe_ros.io.reader import BagReader


def write_csv(path: Path, rows: list[dict]) -> Path:
    header = [*COLUMNS, 'imu_acc_x']  # another column, as the dataset has 51
    lines = [','.join(header)]
    for row in rows:
        lines.append(','.join(str(row.get(c, '0.0')) for c in header))
    path.write_text('\n'.join(lines) + '\n')
    return path


def read(bag: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with BagReader(bag) as reader:
        for topic, log_ns, raw in reader.messages():
            decode = messages.decode_odometry if topic.endswith('odom') else \
                messages.decode_pose_stamped
            out.setdefault(topic, []).append((log_ns, decode(raw)))
    return out


def test_stamps_are_parsed_to_the_nanosecond():
    assert parse_stamp('1772421915.832047939') == 1_772_421_915_832_047_939
    assert parse_stamp('12.5') == 12_500_000_000
    assert parse_stamp('7') == 7_000_000_000
    with pytest.raises(ValueError):
        parse_stamp('1e9')


def test_a_flight_becomes_odometry_in_the_body_frame_and_references_from_take_off(tmp_path):
    roll, pitch, yaw = 0.1, -0.2, 0.7
    q = euler_to_quaternion(roll, pitch, yaw)
    v_world, w_world = np.array([0.5, -0.3, 0.2]), np.array([0.05, 0.1, -0.4])
    base = dict(zip(('qx', 'qy', 'qz', 'qw'), q), px=1.0, py=2.0, pz=0.05,
                vx=v_world[0], vy=v_world[1], vz=v_world[2],
                wx_vicon=w_world[0], wy_vicon=w_world[1], wz_vicon=w_world[2])  # fmt: skip
    rows = [
        {**base, 't': '100.000000000'},  # on the ground, setpoint all zero: no reference
        {**base, 't': '100.010000001', 'sp_ctrltarget_z': 1.0, 'sp_ctrltarget_yaw': 90.0},
        {**base, 't': '100.020000002', 'px': 'nan'},  # not finite: left out
        {**base, 't': '100.030000003', 'sp_ctrltarget_x': 0.0},  # setpoint zero again: kept
    ]
    bag = tmp_path / 'bag'
    done = convert_nanobench(write_csv(tmp_path / 'flight.csv', rows), bag, namespace='cf1')
    assert (done.odometry, done.references, done.skipped) == (3, 2, 1)
    msgs = read(bag)
    odom = msgs['/cf1/odom']
    assert [s.stamp_ns for _, s in odom] == [100_000_000_000, 100_010_000_001, 100_030_000_003]
    assert [log for log, _ in odom] == [s.stamp_ns for _, s in odom]
    first = odom[0][1]
    assert (first.frame_id, first.child_frame_id) == ('world', 'base_link')
    rotation = euler_to_rotation(roll, pitch, yaw)
    np.testing.assert_allclose(rotation @ first.linear, v_world, atol=1e-12)
    np.testing.assert_allclose(rotation @ first.angular, w_world, atol=1e-12)
    refs = msgs['/cf1/reference']
    assert [s.stamp_ns for _, s in refs] == [100_010_000_001, 100_030_000_003]
    np.testing.assert_allclose(refs[0][1].position, [0.0, 0.0, 1.0])
    z, w = refs[0][1].orientation[2:]
    assert 2 * math.atan2(z, w) == pytest.approx(math.pi / 2)


def test_what_cannot_be_converted_is_refused_by_name(tmp_path):
    bad = tmp_path / 'bad.csv'
    bad.write_text('t,px\n1.0,2.0\n')
    with pytest.raises(BagError, match='not a NanoBench flight CSV: no column'):
        convert_nanobench(bad, tmp_path / 'out')
    with pytest.raises(BagError, match='cannot read'):
        convert_nanobench(tmp_path / 'missing.csv', tmp_path / 'out')
    good = write_csv(tmp_path / 'ok.csv', [{'t': '1.0'}])
    (tmp_path / 'exists').mkdir()
    with pytest.raises(BagError, match='exists already'):
        convert_nanobench(good, tmp_path / 'exists')


def test_a_conversion_that_fails_on_the_way_leaves_no_bag(tmp_path):
    # 30 good rows, then one whose time is not a number: the rows before it were written
    rows = [{'t': f'{0.01 * i:.2f}', 'qw': '1.0'} for i in range(30)] + [{'t': 'garbage'}]
    bad = write_csv(tmp_path / 'bad.csv', rows)
    out = tmp_path / 'out'
    with pytest.raises(BagError, match=r'line 32: .*No bag written \(.*out removed\)'):
        convert_nanobench(bad, out)
    assert not out.exists()
    good = write_csv(tmp_path / 'good.csv', rows[:30])  # (the same rows convert without it)
    assert convert_nanobench(good, out).odometry == 30
    assert len(read(out)['/odom']) == 30


@pytest.mark.parametrize('flight', ['nanobench_B2_circle_medium_rep1',
                                    'nanobench_B3_figure8_medium_rep1'])  # fmt: skip
def test_the_corpus_flights_are_rebuilt_from_their_csv(tmp_path, flight):
    source = FLIGHTS / flight
    if not (source / 'source.csv').is_file():
        pytest.skip(f'{source} not available (set CLOE_FLIGHTS to the corpus folder)')
    convert_nanobench(source / 'source.csv', tmp_path / 'bag')
    ours, theirs = read(tmp_path / 'bag'), read(source)
    assert ours.keys() == theirs.keys()
    for topic in ours:
        a, b = ours[topic], theirs[topic]
        assert len(a) == len(b)
        # the corpus bags were stamped through a float (256 ns resolution); ours are exact
        assert max(abs(x.stamp_ns - y.stamp_ns) for (_, x), (_, y) in zip(a, b)) <= 256
        for (_, x), (_, y) in zip(a, b):
            np.testing.assert_allclose(x.position, y.position, atol=1e-9)
            np.testing.assert_allclose(x.orientation, y.orientation, atol=1e-8)
