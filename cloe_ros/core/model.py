"""The linearized closed-loop quadrotor model identified by CLOE (docs/method.md).

State, in this order everywhere in the package::

    zeta = [x, x_dot, theta, theta_dot, y, y_dot, phi, phi_dot, psi, psi_dot, z, z_dot]

(theta pitch, phi roll, psi yaw; ZYX Euler angles as in ROS; positions in metres, angles in
radians, rates per second). The reference is ``r = [x_d, y_d, psi_d, z_d]``.

The closed loop splits into four decoupled blocks. Inside a block every row is a known integrator
chain, including the known tilt coupling ``x_ddot = +g theta`` and ``y_ddot = -g phi``, except the
last row, whose state coefficients and reference gain are unknown::

    x-theta:  theta_ddot = a1 x + a2 x_dot + a3 theta + a4 theta_dot + b x_d    (5 parameters)
    y-phi:    phi_ddot   = a1 y + a2 y_dot + a3 phi   + a4 phi_dot   + b y_d    (5 parameters)
    psi:      psi_ddot   = a1 psi + a2 psi_dot + b psi_d                          (3 parameters)
    z:        z_ddot     = a1 z   + a2 z_dot   + b z_d                            (3 parameters)

so ``zeta' = A(Theta) zeta + B(Theta) r`` with 16 unknown parameters ``Theta``, stored block by
block in the order above. For a block the regressor is ``phi_b = [zeta_b ; r_b]`` and the last row
reads ``zeta_b,last' = Theta_b . phi_b``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cloe_ros.core.matrix_exp import expm

GRAVITY = 9.81
"""Gravitational acceleration used by the model and the simulator, m/s^2."""

#: What no quadrotor exceeds, with margin: the fastest racing quadrotors fly at about 130 m/s,
#: accelerate at 4-5 g and turn at 35-70 rad/s (2000-4000 deg/s gyroscope ranges). Inputs beyond
#: these are rejected, and predictions are kept within reach (docs/anticipation.md, section 3).
QUADROTOR_MAX_SPEED = 150.0  # m/s
QUADROTOR_MAX_ACCELERATION = 100.0  # m/s^2
QUADROTOR_MAX_RATE = 100.0  # rad/s

STATE_NAMES: tuple[str, ...] = (
    'x', 'x_dot', 'theta', 'theta_dot',
    'y', 'y_dot', 'phi', 'phi_dot',
    'psi', 'psi_dot', 'z', 'z_dot',
)  # fmt: skip
REFERENCE_NAMES: tuple[str, ...] = ('x_d', 'y_d', 'psi_d', 'z_d')
N_STATES = 12
N_REFERENCES = 4

#: State indices of the physical subsystems used by the metrics (paper Tables 3 and 5).
POSITION = (0, 4, 10)
VELOCITY = (1, 5, 11)
ANGLES = (2, 6, 8)
RATES = (3, 7, 9)
SUBSYSTEMS: dict[str, tuple[int, ...]] = {
    'position': POSITION,
    'velocity': VELOCITY,
    'angles': ANGLES,
    'rates': RATES,
}


@dataclass(frozen=True)
class Block:
    """One decoupled subsystem of the closed loop.

    Attributes:
        name: Short name used in parameter labels and reports.
        states: Indices into ``zeta`` of the block's chain, in chain order.
        reference: Index into ``r`` of the block's reference.
        coupling: Known gain of the second row on the third state (``+g`` for x-theta,
            ``-g`` for y-phi); ``None`` for the 2-chains.

    """

    name: str
    states: tuple[int, ...]
    reference: int
    coupling: float | None = None

    @property
    def order(self) -> int:
        return len(self.states)

    @property
    def n_params(self) -> int:
        return self.order + 1

    @property
    def last(self) -> int:
        """Index into ``zeta`` of the row whose coefficients are unknown."""
        return self.states[-1]


BLOCKS: tuple[Block, ...] = (
    Block('x_theta', (0, 1, 2, 3), 0, +GRAVITY),
    Block('y_phi', (4, 5, 6, 7), 1, -GRAVITY),
    Block('psi', (8, 9), 2),
    Block('z', (10, 11), 3),
)
N_PARAMS = sum(b.n_params for b in BLOCKS)
#: Blocks with a tilt coupling (x-theta, y-phi) and the paper's values of those couplings.
COUPLED_BLOCKS = tuple(b for b in BLOCKS if b.coupling is not None)
N_COUPLINGS = len(COUPLED_BLOCKS)
PAPER_COUPLING = np.array([b.coupling for b in COUPLED_BLOCKS])

#: Slice of ``Theta`` belonging to each block.
BLOCK_SLICES: tuple[slice, ...] = tuple(
    slice(start, start + b.n_params)
    for start, b in zip(np.cumsum([0] + [b.n_params for b in BLOCKS[:-1]]), BLOCKS)
)
BLOCK_STARTS = np.array([s.start for s in BLOCK_SLICES], dtype=np.intp)


def _parameter_names() -> tuple[str, ...]:
    names = []
    for block in BLOCKS:
        names += [f'{block.name}.a_{STATE_NAMES[i]}' for i in block.states]
        names.append(f'{block.name}.b_{REFERENCE_NAMES[block.reference]}')
    return tuple(names)


PARAMETER_NAMES = _parameter_names()

#: For each entry of Theta: the index into ``w = [zeta ; r]`` (16,) of its regressor entry.
REGRESSOR_INDEX = np.array(
    [i for b in BLOCKS for i in (*b.states, N_STATES + b.reference)], dtype=np.intp
)
#: For each entry of Theta: the state row it drives (the block's last row).
PARAM_ROW = np.array([b.last for b in BLOCKS for _ in range(b.n_params)], dtype=np.intp)
#: The rows of zeta whose dynamics are unknown, one per block.
UNKNOWN_ROWS = np.array([b.last for b in BLOCKS], dtype=np.intp)


def known_dynamics() -> np.ndarray:
    """The known part ``A0`` (12, 12) of ``A``: integrator chains and the +-g tilt coupling."""
    a0 = np.zeros((N_STATES, N_STATES))
    for block in BLOCKS:
        s = block.states
        for k in range(block.order - 1):
            a0[s[k], s[k + 1]] = 1.0
        if block.coupling is not None:
            # the velocity row integrates g times the tilt angle: x_ddot = +g theta
            a0[s[1], s[2]] = block.coupling
    return a0


A_KNOWN = known_dynamics()
A_KNOWN.setflags(write=False)


def check_shape(name: str, array: np.ndarray, shape: tuple[int, ...]) -> None:
    """Raise ``ValueError`` naming ``name`` when ``array`` does not have trailing ``shape``."""
    got = np.shape(array)
    if got[len(got) - len(shape) :] != shape or len(got) < len(shape):
        msg = f'{name}: expected shape (..., {", ".join(map(str, shape))}) but found {got}'
        raise ValueError(msg)


def system_matrices(
    theta: np.ndarray, coupling: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``A(Theta)`` (..., 12, 12) and ``B(Theta)`` (..., 12, 4).

    Args:
        theta: Parameters (..., 16), block by block as in ``PARAMETER_NAMES``.
        coupling: Tilt couplings (..., 2) replacing the known ``+g`` (x-theta) and ``-g`` (y-phi)
            of the velocity rows, for models that identify them; None: the paper's ``+-g``.

    """
    theta = np.asarray(theta, dtype=float)
    check_shape('theta', theta, (N_PARAMS,))
    batch = theta.shape[:-1]
    a = np.broadcast_to(A_KNOWN, (*batch, N_STATES, N_STATES)).copy()
    b = np.zeros((*batch, N_STATES, N_REFERENCES))
    for block, sl in zip(BLOCKS, BLOCK_SLICES):
        tb = theta[..., sl]
        a[..., block.last, list(block.states)] = tb[..., :-1]
        b[..., block.last, block.reference] = tb[..., -1]
    if coupling is not None:
        coupling = np.asarray(coupling, dtype=float)
        check_shape('coupling', coupling, (N_COUPLINGS,))
        for k, block in enumerate(COUPLED_BLOCKS):
            a[..., block.states[1], block.states[2]] = coupling[..., k]
    return a, b


def discretise(
    theta: np.ndarray, coupling: np.ndarray | None, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of ``zeta' = A zeta + B r`` over ``dt``:
    ``(Ad (..., 12, 12), Bd (..., 12, 4))``, from ``expm`` of the augmented system (batched like
    :func:`system_matrices`)."""
    a, b = system_matrices(theta, coupling)
    m = np.zeros((*a.shape[:-2], N_STATES + N_REFERENCES, N_STATES + N_REFERENCES))
    m[..., :N_STATES, :N_STATES] = a
    m[..., :N_STATES, N_STATES:] = b
    e = expm(m * dt)
    return e[..., :N_STATES, :N_STATES], e[..., :N_STATES, N_STATES:]


def propagate(ad: np.ndarray, bd: np.ndarray, x0: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """The states (V, n, 12) of V discrete models ``x_{k+1} = Ad x_k + Bd r_k`` run from ``x0``
    (V, 12) over the references ``refs`` (V, n, 4), with ``ad`` (V, 12, 12) and ``bd`` (V, 12, 4).

    The stacked products call BLAS once per model, as ``ad @ x + bd @ r`` of one model does, so
    each model gets bitwise the states it gets run alone, however many run together."""
    v, n = refs.shape[:2]
    out = np.empty((v, n, x0.shape[-1]))
    x = x0[..., None]
    r = refs[..., None]
    for k in range(n):
        x = ad @ x + bd @ r[:, k]
        out[:, k] = x[..., 0]
    return out


def unstable_blocks(
    theta: np.ndarray, coupling: np.ndarray | None = None, margin: float = 0.0
) -> list[str]:
    """Names of the blocks of ``A(Theta, c)`` with a pole at real part >= -margin (one vehicle)."""
    a, _ = system_matrices(theta, coupling)
    unstable = set()
    for blocks, rows, cols in _BLOCKS_BY_ORDER:  # the blocks of one order in one call
        poles = np.linalg.eigvals(a[rows, cols])  # (blocks, order)
        unstable.update(b.name for b, p in zip(blocks, poles) if np.max(p.real) >= -margin)
    return [b.name for b in BLOCKS if b.name in unstable]


def _blocks_by_order() -> list[tuple[list, np.ndarray, np.ndarray]]:
    """The blocks grouped by order, with the indices that take their (order, order) matrices
    out of ``A`` at once."""
    out = []
    for order in sorted({b.order for b in BLOCKS}):
        blocks = [b for b in BLOCKS if b.order == order]
        states = np.array([b.states for b in blocks])  # (blocks, order)
        out.append((blocks, states[:, :, None], states[:, None, :]))
    return out


_BLOCKS_BY_ORDER = _blocks_by_order()


def parameters_from_matrices(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Inverse of :func:`system_matrices`: read Theta (..., 16) off the unknown rows of A and B."""
    check_shape('A', a, (N_STATES, N_STATES))
    check_shape('B', b, (N_STATES, N_REFERENCES))
    parts = []
    for block in BLOCKS:
        parts.append(a[..., block.last, list(block.states)])
        parts.append(b[..., block.last, block.reference][..., None])
    return np.concatenate(parts, axis=-1)


def block_matrices(theta_block: np.ndarray, block: Block) -> tuple[np.ndarray, np.ndarray]:
    """``A_b`` (n, n) and ``B_b`` (n,) of one block from its parameters (n + 1,)."""
    n = block.order
    a = np.zeros((n, n))
    for k in range(n - 1):
        a[k, k + 1] = 1.0
    if block.coupling is not None:
        a[1, 2] = block.coupling
    a[-1, :] = theta_block[:n]
    b = np.zeros(n)
    b[-1] = theta_block[n]
    return a, b
