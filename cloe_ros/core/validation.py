"""Input validation: whether one input's values are usable, and whether it is in the vehicle's
world frame. The first stage of a vehicle's engine (:class:`~cloe_ros.core.engine.VehicleEngine`),
before the timeline (:mod:`cloe_ros.core.timeline`) orders the inputs in time.

* :func:`check_odometry`, :func:`check_reference` and :func:`check_plan` are pure: one message's
  values in, its state or reference (in the estimator's units) or why it is unusable out. They
  know nothing of the vehicle's other inputs.
* :class:`WorldFrame` holds the vehicle's world frame: configured, or learnt from the first input
  and learnt again when that one turns out to have been an outlier.

Rejected, never fed to the estimator: non-finite values, a quaternion far from unit norm, values
no quadrotor in a local world frame reaches (beyond ``MAX_POSITION``, ``MAX_SPEED``,
``MAX_RATE``), a roll or pitch beyond ``MAX_TILT`` (outside the near-hover model, whose Euler rates
are singular at 90 deg), a frame other than the vehicle's world frame.
"""

from __future__ import annotations

import math

import numpy as np

from cloe_ros.core import kernels
from cloe_ros.core.kinematics import quaternion_yaw, quaternion_yaw_one
from cloe_ros.core.model import QUADROTOR_MAX_RATE, QUADROTOR_MAX_SPEED
from cloe_ros.core.samples import NS, OdometrySample, PathSample, PoseSample

#: Bounds of plausible inputs, generous for any quadrotor in a local world frame; beyond them an
#: input is rejected (such values overflow the estimator's statistics, or leave its model).
MAX_POSITION = 1e5  # m, each coordinate (odometry, reference, plan)
MAX_SPEED = QUADROTOR_MAX_SPEED  # m/s, each body velocity component
MAX_RATE = QUADROTOR_MAX_RATE  # rad/s, each body rate
MAX_TILT = math.radians(80.0)  # roll and pitch: the model linearises about hover in Euler angles
#: Longest accepted plan, poses (a minute at 100 Hz, and more).
MAX_PLAN_POSES = 10_000
#: Inputs in one other frame, in a row, after which a frame learnt from the first input is taken
#: to have been an outlier and is learnt again.
FRAME_RELEARN = 20
#: Reference and plan quaternions are normalised before their yaw is taken, but for those of unit
#: norm to round-off: dividing by 1 - 1e-16 would only add round-off to the yaw.
ROUNDOFF = 1e-12


class Rejection(str):
    """Why an input was rejected: the reason (the counter's key, categorical) as the string,
    ``detail``, the offending value, for the logs, and ``later``: decided after its input
    arrived, by a later one (a held input found an outlier), not on the input's arrival."""

    detail: str
    later: bool

    def __new__(cls, reason: str, detail: str = '', later: bool = False) -> Rejection:
        obj = super().__new__(cls, reason)
        obj.detail, obj.later = detail, later
        return obj

    def describe(self) -> str:
        """``reason: detail``."""
        return f'{self}: {self.detail}' if self.detail else str(self)


def check_odometry(
    sample: OdometrySample, quaternion_tolerance: float
) -> tuple[np.ndarray, None] | tuple[None, Rejection]:
    """The state ``zeta`` (12,) of an odometry sample and None, or None and why its values are
    unusable, in one compiled call (:func:`~cloe_ros.core.kernels.odometry_state`). Yaw in
    (-pi, pi], not yet unwrapped; the frame is not checked."""
    fields = (sample.position, sample.orientation, sample.linear, sample.angular)
    arrays = [np.asarray(a, dtype=float) for a in fields]
    zeta, detail = np.empty(12), np.empty(2)
    verdict = kernels.odometry_state(*arrays, quaternion_tolerance, MAX_POSITION, MAX_SPEED,
                                     MAX_RATE, MAX_TILT, zeta, detail)  # fmt: skip
    if verdict == kernels.ODOMETRY_OK:
        return zeta, None
    if verdict == kernels.NON_FINITE:
        fields = zip(('position', 'orientation', 'linear', 'angular'), arrays)
        bad = ', '.join(n for n, a in fields if not np.isfinite(a).all())
        return None, Rejection('non-finite odometry', f'in {bad}')
    if verdict == kernels.BAD_QUATERNION:
        return None, Rejection('invalid quaternion', f'norm {detail[0]:.6g}')
    bounds = {kernels.BAD_POSITION: ('position', MAX_POSITION, 'm'),
              kernels.BAD_VELOCITY: ('velocity', MAX_SPEED, 'm/s'),
              kernels.BAD_RATE: ('angular rate', MAX_RATE, 'rad/s')}  # fmt: skip
    if verdict in bounds:
        name, bound, unit = bounds[verdict]
        return None, Rejection(f'{name} beyond {bound:g} {unit}', f'{detail[0]:.6g} {unit}')
    roll, pitch = detail.tolist()  # (kernels.BAD_TILT)
    return None, Rejection(
        f'tilt beyond {math.degrees(MAX_TILT):g} deg, outside the model',
        f'roll {math.degrees(roll):.1f} deg, pitch {math.degrees(pitch):.1f} deg',
    )


def check_reference(
    sample: PoseSample, quaternion_tolerance: float
) -> tuple[np.ndarray, None] | tuple[None, Rejection]:
    """The reference ``r = (x, y, psi, z)`` (4,) of a reference pose and None, or None and why
    its values are unusable. Yaw in (-pi, pi], not yet unwrapped; the frame is not checked.
    (Scalar math: it runs for every reference.)"""
    q = sample.orientation
    p, qs = sample.position.tolist(), q.tolist()
    if not all(map(math.isfinite, (*p, *qs))):
        bad = 'position' if not all(map(math.isfinite, p)) else 'orientation'
        return None, Rejection('non-finite reference', f'in {bad}')
    norm = math.sqrt(float(q @ q))
    if abs(norm - 1.0) > quaternion_tolerance:
        return None, Rejection('invalid reference quaternion', f'norm {norm:.6g}')
    largest = max(map(abs, p))
    if largest > MAX_POSITION:
        return None, Rejection(f'reference position beyond {MAX_POSITION:g} m', f'{largest:.6g} m')
    x, y, z, w = (c / (norm if abs(norm - 1.0) > ROUNDOFF else 1.0) for c in qs)
    yaw = quaternion_yaw_one((x, y, z, w))
    return np.array([p[0], p[1], yaw, p[2]]), None


def check_plan(
    sample: PathSample, quaternion_tolerance: float
) -> tuple[np.ndarray, None] | tuple[None, Rejection]:
    """The references ``(x, y, psi, z)`` (K, 4) of a plan's poses and None, or None and why its
    values are unusable. Yaw unwrapped along the plan; neither the frame nor the stamps against
    the vehicle's other inputs are checked."""
    stamps, p, q = sample.stamps_ns, sample.positions, sample.orientations
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return None, Rejection('non-finite plan')
    if len(stamps) == 0:
        return None, Rejection('empty plan')
    if len(stamps) > MAX_PLAN_POSES:
        return None, long_plan(len(stamps))
    largest = float(np.max(np.abs(p)))
    if largest > MAX_POSITION:
        return None, Rejection(f'plan position beyond {MAX_POSITION:g} m', f'{largest:.6g} m')
    norms = np.sqrt(np.sum(q * q, axis=1))
    worst = int(np.argmax(np.abs(norms - 1.0)))
    if abs(norms[worst] - 1.0) > quaternion_tolerance:
        return None, Rejection('invalid plan quaternion', f'pose {worst}: norm {norms[worst]:.6g}')
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        return None, Rejection(
            'plan stamps not increasing',
            f'pose {k} at {seconds(stamps[k])} after {seconds(stamps[k - 1])}',
        )
    yaw = quaternion_yaw(q / np.where(np.abs(norms - 1.0) > ROUNDOFF, norms, 1.0)[:, None])
    return np.column_stack([p[:, 0], p[:, 1], np.unwrap(yaw), p[:, 2]]), None


def long_plan(poses: int) -> Rejection:
    """Why a plan of ``poses`` poses, more than ``MAX_PLAN_POSES``, is refused."""
    return Rejection(f'plan longer than {MAX_PLAN_POSES} poses', f'{poses} poses')


def seconds(stamp_ns: int) -> str:
    """A stamp in seconds, every nanosecond shown (``1700000001.230000000 s``)."""
    sec, nsec = divmod(int(stamp_ns), NS)
    return f'{sec}.{nsec:09d} s'


#: :meth:`WorldFrame.check`'s verdicts: the input is in the frame (or set it); it set a reopened
#: frame anew to another one (the inputs kept are in the old one); the frame was learnt again
#: (the first input was an outlier: everything accepted in the old frame is void); the input is
#: in another frame and is rejected.
FRAME_SAME, FRAME_MOVED, FRAME_RELEARNT, FRAME_OTHER = range(4)


class WorldFrame:
    """The world frame of one vehicle's inputs: ``configured``, else learnt from the first input.

    A frame learnt from the first input is learnt again when the next ``FRAME_RELEARN`` inputs
    all come in one other frame: the first input was the outlier. After :meth:`reopen` (a reset)
    a learnt frame stays until the next input sets it, in whatever frame that one is."""

    def __init__(self, configured: str = '') -> None:
        #: The frame (None until the first input, when none is configured).
        self.name: str | None = configured or None
        #: The frame before the last one learnt again (for the logs).
        self.previous: str | None = None
        self._learnt = False  # learnt from an input (not configured)
        self._open = False  # the next input sets it anew (after a reopen)
        self._others: list[str] = []  # frames of the inputs refused in a row since

    def check(self, frame_id: str) -> int:
        """The verdict (``FRAME_*``) on an input in ``frame_id``, which may set or learn the
        frame anew."""
        if self.name is None:
            self.name, self._learnt = frame_id, True
            self._others.clear()
            return FRAME_SAME
        if self._open:
            self._open = False
            if frame_id != self.name:
                self.name = frame_id
                return FRAME_MOVED
            return FRAME_SAME
        if frame_id == self.name:
            self._others.clear()
            return FRAME_SAME
        if self._learnt:
            others = self._others
            if others and others[-1] != frame_id:
                others.clear()
            others.append(frame_id)
            if len(others) >= FRAME_RELEARN:
                self.previous, self.name = self.name, frame_id
                others.clear()
                return FRAME_RELEARNT
        return FRAME_OTHER

    def mismatch(self, frame_id: str) -> str:
        """An input in ``frame_id`` (refused), in words."""
        return f'received {frame_id!r}, expected {self.name!r}'

    def reopen(self) -> None:
        """A learnt frame is set by the next input (a configured one stays)."""
        if self._learnt:
            self._open = True
            self._others.clear()
