"""Nonlinear quadrotor under the hierarchical PD controller (paper eqs 4-9 and §3).

Plant state, per vehicle:
``s = [x, y, z, vx, vy, vz, phi, theta, psi, phi_dot, theta_dot, psi_dot]`` (world position m,
world velocity m/s, ZYX Euler angles rad, Euler-angle rates rad/s)::

    m x_ddot = u (s_phi s_psi + c_phi c_psi s_theta) + m d_x
    m y_ddot = u (c_phi s_theta s_psi - c_psi s_phi) + m d_y
    m z_ddot = u c_theta c_phi - m g + m d_z
    psi_ddot   = tau_psi   + a theta_dot phi_dot + d_psi
    theta_ddot = tau_theta + b psi_dot phi_dot   + d_theta
    phi_ddot   = tau_phi   + c theta_dot psi_dot + d_phi

with the inertia couplings of Euler's rigid-body equations, ``a = (Jx - Jy)/Jz``,
``b = (Jz - Jx)/Jy``, ``c = (Jy - Jz)/Jx``. The controller (§3)::

    u = (r1 + m g) / (c_theta c_phi),  r1 = -k_vz z_dot - k_pz (z - z_d)    (so z_ddot = r1/m)
    tau_psi   = -k_dpsi psi_dot - k_ppsi (psi - psi_d)
    tau_theta = (-k_dtheta theta_dot - k_ptheta (theta - theta_ref)) / J_y,
        theta_ref = -k_vx x_dot - k_px (x - x_d)
    tau_phi   = (-k_dphi phi_dot - k_pphi (phi - phi_ref)) / J_x,
        phi_ref = +k_vy y_dot + k_py (y - y_d)

The paper's printed x/y gains (k_vx = 0.05 with the attitude gains used as normalised torques) give
an unstable x-theta loop (poles +0.47 +- 0.98j). This simulator reads the attitude gains as torques
(N m / rad) divided by J_x = J_y = 0.01 kg m^2 and uses k_vx = k_vy = 0.12; the z and psi gains
are as printed. :func:`closed_loop_poles` shows the resulting poles, :func:`true_parameters` the
hover linearization Theta that the identifiers are scored against.

Integration is classical RK4 at ``dt`` (default 1 ms); the controller samples the reference once
per step, disturbances are evaluated at every stage.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from cloe_ros.core.model import (
    BLOCKS,
    GRAVITY,
    N_REFERENCES,
    N_STATES,
    check_shape,
)


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters: mass (kg), inertia about body x, y, z (kg m^2), gravity (m/s^2)."""

    mass: float = 0.52
    inertia: tuple[float, float, float] = (0.01, 0.01, 0.02)
    gravity: float = GRAVITY


@dataclass(frozen=True)
class ControllerGains:
    """Hierarchical PD gains (§3, §6.1), with the stable reading of the x/y loops (see module doc).

    Position loops: ``k_px, k_vx, k_py, k_vy`` (rad per m, rad per m/s). Attitude loops:
    ``k_ptheta, k_dtheta, k_pphi, k_dphi`` (N m per rad, N m per rad/s; divided by the inertia).
    Yaw: ``k_ppsi, k_dpsi`` (normalised, rad/s^2 per rad and per rad/s). Altitude: ``k_pz, k_vz``
    (N per m and N per m/s; divided by the mass).
    """

    k_px: float = 0.1
    k_vx: float = 0.12
    k_ptheta: float = 1.0
    k_dtheta: float = 0.15
    k_py: float = 0.1
    k_vy: float = 0.12
    k_pphi: float = 1.0
    k_dphi: float = 0.15
    k_pz: float = 150.0
    k_vz: float = 8.0
    k_ppsi: float = 140.0
    k_dpsi: float = 12.01


#: The gains exactly as the paper prints them (x-theta / y-phi unstable with attitude gains read
#: as normalised torques; kept to document the instability).
PAPER_PRINTED_GAINS = ControllerGains(k_vx=0.05, k_vy=0.05)


def true_parameters(
    quad: QuadrotorParams = QuadrotorParams(), gains: ControllerGains = ControllerGains()
) -> np.ndarray:
    """Theta (16,) of the closed loop linearized at hover (psi = 0), block by block."""
    jx, jy, _ = quad.inertia
    kt, dt = gains.k_ptheta / jy, gains.k_dtheta / jy
    kp, dp = gains.k_pphi / jx, gains.k_dphi / jx
    kz, vz = gains.k_pz / quad.mass, gains.k_vz / quad.mass
    return np.array(
        [
            # theta_ddot = -kt (theta + k_vx x_dot + k_px (x - x_d)) - dt theta_dot
            -kt * gains.k_px, -kt * gains.k_vx, -kt, -dt, kt * gains.k_px,
            # phi_ddot = -kp (phi - k_vy y_dot - k_py (y - y_d)) - dp phi_dot
            kp * gains.k_py, kp * gains.k_vy, -kp, -dp, -kp * gains.k_py,
            # psi_ddot = -k_ppsi (psi - psi_d) - k_dpsi psi_dot
            -gains.k_ppsi, -gains.k_dpsi, gains.k_ppsi,
            # z_ddot = (-k_pz (z - z_d) - k_vz z_dot) / m
            -kz, -vz, kz,
        ]
    )  # fmt: skip


def closed_loop_poles(
    quad: QuadrotorParams = QuadrotorParams(), gains: ControllerGains = ControllerGains()
) -> dict[str, np.ndarray]:
    """Eigenvalues of each block of the hover linearization, by block name."""
    from cloe_ros.core.model import BLOCK_SLICES, block_matrices

    theta = true_parameters(quad, gains)
    return {
        b.name: np.linalg.eigvals(block_matrices(theta[sl], b)[0])
        for b, sl in zip(BLOCKS, BLOCK_SLICES)
    }


class Disturbance(Protocol):
    """Additive disturbance accelerations.

    ``__call__(t)`` returns ``[d_x, d_y, d_z, d_phi, d_theta, d_psi]`` (..., 6) at times ``t`` (s,
    scalar or array): m/s^2 on the translational rows, rad/s^2 on the rotational rows.
    """

    def __call__(self, t: float | np.ndarray) -> np.ndarray: ...


class NoDisturbance:
    """The disturbance-free case."""

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        return np.zeros((*np.shape(t), 6))


class PaperDisturbance:
    """The deterministic sinusoids of the paper's §6.1 (as printed)::

    d_x = 0.02 sin(1.2 t) + 0.01 cos(0.2 t)      d_theta = 0.01 sin(0.2 t)
    d_y = 0.02 sin(0.2 t)                        d_phi   = 0.01 sin(1.04 t) + 0.01 cos(0.03 t)
    d_z = 0.3 sin(1.2 t) + 0.01 cos(0.2 t)       d_psi   = 0.01 cos(0.001 t)
    """

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = scale

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        s12, c02, s02 = np.sin(1.2 * t), np.cos(0.2 * t), np.sin(0.2 * t)
        return self.scale * np.stack(
            [
                0.02 * s12 + 0.01 * c02,
                0.02 * s02,
                0.3 * s12 + 0.01 * c02,
                0.01 * np.sin(1.04 * t) + 0.01 * np.cos(0.03 * t),
                0.01 * s02,
                0.01 * np.cos(0.001 * t),
            ],
            axis=-1,
        )


@dataclass(frozen=True)
class ProbingSignal:
    """Excitation added to the reference: per channel a sum of sinusoids.

    ``tau_c(t) = sum_k A_ck sin(w_ck t + phase_ck)`` for the channels ``[x_d, y_d, psi_d, z_d]``.
    Amplitudes in m (rad for psi_d), frequencies in rad/s. The default uses three frequencies on
    the 4th-order chains (each sinusoid adds two directions of excitation, the 5-parameter rows
    need at least three) and two on the 2nd-order chains; no two frequencies in a small-integer
    ratio; all but the lowest x/y ones above the §6.1 disturbances (<= 1.2 rad/s), and none within
    0.5 rad/s of them, so an identifier can tell the reference's effect from the disturbances'.
    A few centimetres and a few hundredths of a radian: the flight is barely changed.
    """

    amplitudes: tuple[tuple[float, ...], ...] = (
        (0.05, 0.04, 0.03),
        (0.05, 0.04, 0.03),
        (0.03, 0.02),
        (0.05, 0.03),
    )
    frequencies: tuple[tuple[float, ...], ...] = (
        (0.6, 2.3, 5.3),
        (0.7, 2.9, 5.9),
        (2.3, 4.7),
        (2.7, 5.1),
    )
    phases: tuple[tuple[float, ...], ...] = (
        (0.0, 1.0, 2.0),
        (0.5, 1.5, 2.5),
        (0.0, 1.0),
        (0.0, 1.0),
    )

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        out = np.zeros((*t.shape, N_REFERENCES))
        for c in range(N_REFERENCES):
            for a, w, ph in zip(self.amplitudes[c], self.frequencies[c], self.phases[c]):
                out[..., c] += a * np.sin(w * t + ph)
        return out

    def scaled(self, factor: float) -> ProbingSignal:
        amps = tuple(tuple(factor * a for a in ch) for ch in self.amplitudes)
        return ProbingSignal(amps, self.frequencies, self.phases)


NO_PROBING = ProbingSignal(((), (), (), ()), ((), (), (), ()), ((), (), (), ()))


def _smoothstep(t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Quintic 0 -> 1 on [t0, t1] with zero velocity and acceleration at both ends."""
    s = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


@dataclass(frozen=True)
class Scenario:
    """A desired trajectory ``zeta_d(t) = [x_d, y_d, psi_d, z_d]`` with its length and start.

    Attributes:
        name: Name used on the command line and in parameters.
        duration: Default length, s.
        reference: ``t (s) -> (..., 4)`` desired trajectory (without probing).
        initial_position: Start position (x, y, z), m; the vehicle starts at rest.
        initial_yaw: Start yaw, rad.
        description: One line for help texts.

    """

    name: str
    duration: float
    reference: Callable[[np.ndarray], np.ndarray]
    initial_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    initial_yaw: float = 0.0
    description: str = ''


def _position_reference(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    out = np.zeros((*t.shape, N_REFERENCES))
    out[..., 0] = 0.6 * _smoothstep(t, 4.0, 13.4)
    out[..., 1] = 1.0 * _smoothstep(t, 4.0, 13.4)
    out[..., 3] = 0.05 + 0.95 * _smoothstep(t, 1.0, 3.0)
    return out


TRAJECTORY_OMEGA = 0.03


def _trajectory_reference(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    w = TRAJECTORY_OMEGA
    out = np.zeros((*t.shape, N_REFERENCES))
    out[..., 0] = 1.6 * np.sin(w * t)
    out[..., 1] = 3.0 * np.sin(w * t) * np.cos(w * t)
    out[..., 2] = np.pi / 16.0
    out[..., 3] = 1.0
    return out


def _hover_reference(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    out = np.zeros((*t.shape, N_REFERENCES))
    out[..., 3] = 1.0
    return out


SCENARIOS: dict[str, Scenario] = {
    'position': Scenario(
        'position',
        50.0,
        _position_reference,
        description='paper §6.1: x_d 0->0.6 m, y_d 0->1 m on [4, 13.4] s, z_d 0.05->1 m on [1, 3]',
    ),
    'trajectory': Scenario(
        'trajectory',
        140.0,
        _trajectory_reference,
        initial_position=(0.0, 0.0, 1.0),
        initial_yaw=np.pi / 16.0,
        description='paper §6.2: x_d = 1.6 sin(wt), y_d = 3 sin(wt) cos(wt), z_d = 1 m',
    ),
    'hover': Scenario(
        'hover',
        60.0,
        _hover_reference,
        initial_position=(0.0, 0.0, 1.0),
        description='hold (0, 0, 1 m), psi_d = 0',
    ),
}


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name``; ``ValueError`` listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        msg = f'unknown scenario {name!r}; known: {", ".join(SCENARIOS)}'
        raise ValueError(msg) from None


@dataclass(frozen=True)
class MeasurementNoise:
    """White Gaussian noise on the measured state (standard deviations).

    ``position`` m, ``velocity`` m/s, ``angle`` rad, ``rate`` rad/s; isotropic, so the same in the
    world and the body frame.
    """

    position: float = 0.0
    velocity: float = 0.0
    angle: float = 0.0
    rate: float = 0.0

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviation per entry of ``zeta`` (12,)."""
        s = np.empty(N_STATES)
        s[[0, 4, 10]] = self.position
        s[[1, 5, 11]] = self.velocity
        s[[2, 6, 8]] = self.angle
        s[[3, 7, 9]] = self.rate
        return s

    @property
    def enabled(self) -> bool:
        return bool(np.any(self.sigma > 0))


#: The noise level the evaluation uses (Vicon-like): 2 mm, 1 cm/s, 2 mrad, 0.01 rad/s.
TYPICAL_NOISE = MeasurementNoise(position=0.002, velocity=0.01, angle=0.002, rate=0.01)


def plant_to_model(s: np.ndarray) -> np.ndarray:
    """Model state ``zeta`` (..., 12) of plant states ``s`` (..., 12): reordered."""
    zeta = np.empty_like(s)
    zeta[..., [0, 1, 2, 3]] = s[..., [0, 3, 7, 10]]
    zeta[..., [4, 5, 6, 7]] = s[..., [1, 4, 6, 9]]
    zeta[..., [8, 9, 10, 11]] = s[..., [8, 11, 2, 5]]
    return zeta


def model_to_plant(zeta: np.ndarray) -> np.ndarray:
    """Inverse of :func:`plant_to_model`."""
    s = np.empty_like(zeta)
    s[..., [0, 3, 7, 10]] = zeta[..., [0, 1, 2, 3]]
    s[..., [1, 4, 6, 9]] = zeta[..., [4, 5, 6, 7]]
    s[..., [8, 11, 2, 5]] = zeta[..., [8, 9, 10, 11]]
    return s


def controller_matrix(quad: QuadrotorParams, gains: ControllerGains) -> np.ndarray:
    """The linear part of the controller, ``K`` (4, 16) with ``[r1, tau_phi, tau_theta, tau_psi]
    = K [s ; ref]`` (plant state order, then ``[x_d, y_d, psi_d, z_d]``).

    ``r1`` is in N; the torques are angular accelerations (already divided by the inertia).
    """
    jx, jy, _ = quad.inertia
    k = np.zeros((4, N_STATES + N_REFERENCES))
    x, y, z, vx, vy, vz, phi, theta, psi, dphi, dtheta, dpsi = range(12)
    xd, yd, psid, zd = range(12, 16)
    # r1 = -k_vz z_dot - k_pz (z - z_d)
    k[0, [vz, z, zd]] = -gains.k_vz, -gains.k_pz, gains.k_pz
    # tau_phi = (-k_dphi phi_dot - k_pphi (phi - phi_ref)) / Jx,
    # phi_ref = k_vy y_dot + k_py (y - y_d)
    kp = gains.k_pphi / jx
    k[1, [dphi, phi]] = -gains.k_dphi / jx, -kp
    k[1, [vy, y, yd]] = kp * gains.k_vy, kp * gains.k_py, -kp * gains.k_py
    # tau_theta = (-k_dtheta theta_dot - k_ptheta (theta - theta_ref)) / Jy,
    # theta_ref = -k_vx x_dot - k_px (x - x_d)
    kt = gains.k_ptheta / jy
    k[2, [dtheta, theta]] = -gains.k_dtheta / jy, -kt
    k[2, [vx, x, xd]] = -kt * gains.k_vx, -kt * gains.k_px, kt * gains.k_px
    # tau_psi = -k_dpsi psi_dot - k_ppsi (psi - psi_d)
    k[3, [dpsi, psi, psid]] = -gains.k_dpsi, -gains.k_ppsi, gains.k_ppsi
    return k


def inertia_couplings(quad: QuadrotorParams) -> np.ndarray:
    """Coefficients of ``[theta_dot psi_dot, psi_dot phi_dot, theta_dot phi_dot]`` in the roll,
    pitch and yaw accelerations (Euler's rigid-body equations): ``(Jy - Jz)/Jx``, ``(Jz - Jx)/Jy``,
    ``(Jx - Jy)/Jz``."""
    jx, jy, jz = quad.inertia
    return np.array([(jy - jz) / jx, (jz - jx) / jy, (jx - jy) / jz])


def closed_loop_derivative(
    s: np.ndarray,
    ref: np.ndarray,
    dist: np.ndarray,
    quad: QuadrotorParams,
    gains: ControllerGains,
    k_matrix: np.ndarray | None = None,
) -> np.ndarray:
    """``s'`` (N, 12) of the controlled plant at states ``s`` (N, 12).

    Args:
        s: Plant states (N, 12).
        ref: Commanded references ``[x_d, y_d, psi_d, z_d]`` (N, 4), probing included.
        dist: Disturbances ``[d_x, d_y, d_z, d_phi, d_theta, d_psi]`` (N, 6) or (6,).
        quad: Physical parameters.
        gains: Controller gains.
        k_matrix: :func:`controller_matrix` of ``quad`` and ``gains``, if already computed.

    """
    if k_matrix is None:
        k_matrix = controller_matrix(quad, gains)
    m, g = quad.mass, quad.gravity
    lin = np.concatenate([s, ref], axis=1) @ k_matrix.T  # [r1, tau_phi, tau_theta, tau_psi]
    sin, cos = np.sin(s[:, 6:9]).T, np.cos(s[:, 6:9]).T
    sphi, sth, spsi = sin
    cphi, cth, cpsi = cos
    tilt = np.empty((s.shape[0], 3))
    tilt[:, 0] = sphi * spsi + cphi * cpsi * sth
    tilt[:, 1] = cphi * sth * spsi - cpsi * sphi
    tilt[:, 2] = cth * cphi
    # u = (r1 + m g) / (c_theta c_phi): thrust per unit mass times the body z axis
    tilt *= ((lin[:, 0] + m * g) / (m * tilt[:, 2]))[:, None]
    tilt[:, 2] -= g
    rates = s[:, 9:12]
    coupled = np.empty((s.shape[0], 3))
    coupled[:, 0] = rates[:, 1] * rates[:, 2]
    coupled[:, 1] = rates[:, 2] * rates[:, 0]
    coupled[:, 2] = rates[:, 1] * rates[:, 0]
    coupled *= inertia_couplings(quad)
    out = np.empty_like(s)
    out[:, 0:3] = s[:, 3:6]
    out[:, 6:9] = rates
    np.add(tilt, dist[..., 0:3], out=out[:, 3:6])
    np.add(lin[:, 1:4], coupled, out=out[:, 9:12])
    out[:, 9:12] += dist[..., 3:6]
    return out


@dataclass
class SimulationResult:
    """Samples of a simulated flight.

    Attributes:
        t: Times (T,), s.
        zeta: True model states (T, N, 12).
        measured: Measured states (T, N, 12) (``zeta`` plus measurement noise).
        reference: Commanded references (T, N, 4), probing included.
        theta_true: Hover-linearization parameters (16,).

    """

    t: np.ndarray
    zeta: np.ndarray
    measured: np.ndarray
    reference: np.ndarray
    theta_true: np.ndarray


@dataclass
class QuadrotorSimulator:
    """N quadrotors flying a scenario under the PD controller, integrated with RK4.

    Attributes:
        scenario: The desired trajectory.
        n_vehicles: Number of vehicles (leading axis of every array).
        quad: Physical parameters.
        gains: Controller gains.
        disturbance: Disturbance model, or one per vehicle (a list).
        probing: Probing signal added to the reference.
        noise: Measurement noise.
        dt: Integration step, s (<= 1 ms for the paper's 1 kHz).
        offsets: Per-vehicle offset (N, 3) of the reference position, m.
        rng: Random generator for the measurement noise.

    """

    scenario: Scenario
    n_vehicles: int = 1
    quad: QuadrotorParams = field(default_factory=QuadrotorParams)
    gains: ControllerGains = field(default_factory=ControllerGains)
    disturbance: Disturbance | list[Disturbance] = field(default_factory=NoDisturbance)
    probing: ProbingSignal = field(default_factory=ProbingSignal)
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    dt: float = 1e-3
    offsets: np.ndarray | None = None
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def __post_init__(self) -> None:
        if not (0 < self.dt <= 0.01):
            msg = f'dt must be in (0, 0.01] s, got {self.dt}'
            raise ValueError(msg)
        if self.n_vehicles < 1:
            msg = f'n_vehicles must be >= 1, got {self.n_vehicles}'
            raise ValueError(msg)
        n = self.n_vehicles
        if self.offsets is None:
            self.offsets = np.zeros((n, 3))
        self.offsets = np.asarray(self.offsets, dtype=float)
        check_shape('offsets', self.offsets, (3,))
        if isinstance(self.disturbance, list) and len(self.disturbance) != n:
            msg = f'{len(self.disturbance)} disturbances for {n} vehicles'
            raise ValueError(msg)
        self._k_matrix = controller_matrix(self.quad, self.gains)
        self.reset()

    def reset(self) -> None:
        """Back to t = 0, every vehicle at rest at the scenario's start (plus its offset)."""
        self.t = 0.0
        self.state = np.zeros((self.n_vehicles, N_STATES))
        self.state[:, 0:3] = np.asarray(self.scenario.initial_position) + self.offsets
        self.state[:, 8] = self.scenario.initial_yaw
        self._step_count = 0

    def desired(self, t: float | np.ndarray) -> np.ndarray:
        """Desired references (..., N, 4) at times ``t`` (scalar or (T,)), without probing."""
        base = self.scenario.reference(np.asarray(t, dtype=float))[..., None, :]
        offsets = np.zeros((self.n_vehicles, N_REFERENCES))
        offsets[:, [0, 1, 3]] = self.offsets
        return base + offsets

    def reference(self, t: float | np.ndarray) -> np.ndarray:
        """Commanded references (..., N, 4) at times ``t``: desired plus probing."""
        return self.desired(t) + self.probing(np.asarray(t, dtype=float))[..., None, :]

    def disturbance_at(self, t: float | np.ndarray) -> np.ndarray:
        """Disturbances (..., N, 6) at times ``t``."""
        if isinstance(self.disturbance, list):
            return np.stack([d(t) for d in self.disturbance], axis=-2)
        d = self.disturbance(np.asarray(t, dtype=float))
        return np.broadcast_to(d[..., None, :], (*np.shape(t), self.n_vehicles, 6))

    def step(
        self,
        ref: np.ndarray | None = None,
        dist: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Advance every vehicle by one RK4 step of ``dt``.

        Args:
            ref: References (N, 4) held over the step; the scenario's at the current time if None.
            dist: Disturbances (N, 6) at ``t``, ``t + dt/2`` and ``t + dt``; computed if None.

        """
        t, h, s = self.t, self.dt, self.state
        if ref is None:
            ref = self.reference(t)
        if dist is None:
            d0, dm, d1 = self.disturbance_at(np.array([t, t + h / 2, t + h]))
        else:
            d0, dm, d1 = dist
        quad, gains, km = self.quad, self.gains, self._k_matrix
        k1 = closed_loop_derivative(s, ref, d0, quad, gains, km)
        k2 = closed_loop_derivative(s + (h / 2) * k1, ref, dm, quad, gains, km)
        k3 = closed_loop_derivative(s + (h / 2) * k2, ref, dm, quad, gains, km)
        k4 = closed_loop_derivative(s + h * k3, ref, d1, quad, gains, km)
        self.state = s + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        self._step_count += 1
        self.t = self._step_count * h

    @property
    def zeta(self) -> np.ndarray:
        """True model states (N, 12) at the current time."""
        return plant_to_model(self.state)

    def add_noise(self, zeta: np.ndarray) -> np.ndarray:
        """Measured states: ``zeta`` (..., 12) plus measurement noise drawn from ``rng``."""
        if not self.noise.enabled:
            return zeta.copy()
        return zeta + self.rng.normal(size=zeta.shape) * self.noise.sigma

    def run(
        self,
        duration: float | None = None,
        progress: Callable[[float], None] | None = None,
    ) -> SimulationResult:
        """Simulate from the current state for ``duration`` s (the scenario's by default).

        Samples are taken at every step, including the start. ``progress`` is called with the
        fraction done about a hundred times.
        """
        duration = self.scenario.duration if duration is None else duration
        n_steps = round(duration / self.dt)
        t = self.t + self.dt * np.arange(n_steps + 1)
        refs = self.reference(t)
        dist = self.disturbance_at(t)
        dist_mid = self.disturbance_at(t + self.dt / 2)
        plant = np.empty((n_steps + 1, self.n_vehicles, N_STATES))
        plant[0] = self.state
        every = max(1, n_steps // 100)
        for k in range(n_steps):
            self.step(refs[k], (dist[k], dist_mid[k], dist[k + 1]))
            plant[k + 1] = self.state
            if progress is not None and k % every == 0:
                progress(k / n_steps)
        if progress is not None:
            progress(1.0)
        zeta = plant_to_model(plant)
        return SimulationResult(
            t, zeta, self.add_noise(zeta), refs, true_parameters(self.quad, self.gains)
        )
