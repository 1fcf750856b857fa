"""NanoBench flights (CSV) into bags of the interface contract.

NanoBench (Ullah & Baca, 2026; github syediu/nanobench-iros2026, BSD-3-Clause) logs Crazyflie
2.1 flights under Vicon motion capture as one CSV per flight: time ``t`` (s since the epoch),
the Vicon pose (``px, py, pz``, quaternion ``qx, qy, qz, qw``), the world-frame velocity
(``vx, vy, vz``) and angular velocity (``wx_vicon, wy_vicon, wz_vicon``), IMU, motors, the onboard
estimate and the controller's setpoint (``sp_ctrltarget_x, _y, _z``, m, and ``_yaw``, degrees).

:func:`convert_nanobench` writes, per CSV row, ``<ns>/odom`` (nav_msgs/Odometry: the Vicon pose in
``world``; the velocity and angular velocity rotated into the body frame ``base_link``, REP-105)
and, from the first row with a non-zero setpoint on (take-off), ``<ns>/reference``
(geometry_msgs/PoseStamped: the setpoint's position and yaw). Header stamp and log time are the
row's ``t``, parsed to the nanosecond. Rows whose values are not all finite are left out and
counted. This is how the corpus of real flights the package is evaluated on was made.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cloe_ros.core.kinematics import euler_to_rotation, quaternion_to_euler, yaw_quaternion
from cloe_ros.core.samples import OdometrySample, PoseSample
from cloe_ros.interrupts import uninterrupted
from cloe_ros.io import messages
from cloe_ros.io.errors import BagError, WriterError
from cloe_ros.io.writer import BagWriter

#: Columns the conversion reads.
POSE = ('px', 'py', 'pz', 'qx', 'qy', 'qz', 'qw')
VELOCITY = ('vx', 'vy', 'vz')
RATES = ('wx_vicon', 'wy_vicon', 'wz_vicon')
SETPOINT = ('sp_ctrltarget_x', 'sp_ctrltarget_y', 'sp_ctrltarget_z', 'sp_ctrltarget_yaw')
COLUMNS = ('t', *POSE, *VELOCITY, *RATES, *SETPOINT)


@dataclass
class Conversion:
    """What a conversion wrote: messages per topic, and rows left out (not finite)."""

    odometry: int
    references: int
    skipped: int


def parse_stamp(text: str) -> int:
    """Seconds with a decimal fraction (``1772421915.832047939``) to integer nanoseconds, exactly
    (a float would round to 256 ns)."""
    text = text.strip()
    sign = -1 if text.startswith('-') else 1
    whole, _, frac = text.lstrip('+-').partition('.')
    if not whole.isdigit() or (frac and not frac.isdigit()):
        raise ValueError(f'not a time in seconds: {text!r}')
    frac = (frac + '0' * 9)[:9]
    return sign * (int(whole) * 1_000_000_000 + int(frac))


def convert_nanobench(csv_path: Path, output: Path, namespace: str = '') -> Conversion:
    """Write the bag ``output`` (new) from the NanoBench CSV ``csv_path``."""
    csv_path, output = Path(csv_path), Path(output)
    try:
        handle = csv_path.open(newline='')
    except OSError as err:
        raise BagError(f'cannot read {csv_path}: {err.strerror or err}') from err
    ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
    odom_topic, ref_topic = f'{ns}/odom', f'{ns}/reference'
    with handle:
        rows = csv.DictReader(handle)
        missing = [c for c in COLUMNS if c not in (rows.fieldnames or [])]
        if missing:
            raise BagError(f'{csv_path}: not a NanoBench flight CSV: no column(s) '
                           f'{", ".join(missing)}')  # fmt: skip
        if output.exists():
            raise BagError(f'{output} exists already, not overwriting.')
        writer = BagWriter(output)
        try:
            counts = _write_flight(writer, rows, csv_path, odom_topic, ref_topic)
            writer.close()
        except BaseException as err:
            # a bag cut short looks complete to the next tool: none is left
            with uninterrupted():  # (a second Ctrl-C would leave it half removed)
                writer.discard()
            removed = f'No bag written ({output} removed).'
            if isinstance(err, WriterError):
                msg = f'cannot write {output}: {err.reason or err}. {removed}'
                raise BagError(msg) from err
            if isinstance(err, BagError):
                raise BagError(f'{err} {removed}') from err
            raise
    return counts


def _write_flight(writer: BagWriter, rows: csv.DictReader, csv_path: Path, odom_topic: str,
                  ref_topic: str) -> Conversion:  # fmt: skip
    """The rows of the NanoBench CSV ``rows`` as messages of ``writer``: odometry from every row
    with finite values, references from take-off on."""
    counts = Conversion(0, 0, 0)
    flying = False
    writer.add_topic(odom_topic, messages.ODOMETRY)
    writer.add_topic(ref_topic, messages.POSE_STAMPED)
    for line, row in enumerate(rows, start=2):
        try:
            stamp = parse_stamp(row['t'])
            values = np.array([float(row[c]) for c in COLUMNS[1:]])
        except (TypeError, ValueError) as err:
            raise BagError(f'{csv_path}, line {line}: {err}') from err
        if not np.isfinite(values).all():
            counts.skipped += 1
            continue
        pose, v_world, w_world = values[:7], values[7:10], values[10:13]
        setpoint = values[13:]
        q = pose[3:7] / np.linalg.norm(pose[3:7])
        roll, pitch, yaw = quaternion_to_euler(q)
        rotation = euler_to_rotation(roll, pitch, yaw)  # body -> world
        odom = OdometrySample(
            stamp, 'world', 'base_link', pose[:3], q,
            rotation.T @ v_world, rotation.T @ w_world,
        )  # fmt: skip
        writer.write(odom_topic, stamp, messages.encode_odometry(odom))
        counts.odometry += 1
        flying = flying or bool(np.any(setpoint != 0.0))
        if flying:
            ref = PoseSample(stamp, 'world', setpoint[:3],
                             yaw_quaternion(math.radians(setpoint[3])))  # fmt: skip
            writer.write(ref_topic, stamp, messages.encode_pose_stamped(ref))
            counts.references += 1
    return counts
