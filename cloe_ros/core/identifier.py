"""A closed-loop identifier that converges: filtered-regressor recursive instrumental variables.

Why not the paper's gradient law: it is driven by the observer error, which the adaptive gain L
drives to zero long before the parameters are right. Why not least squares on the measurements: in
closed loop the disturbances drive the states, so the regressors correlate with the equation error
and least squares is biased (on the paper's position scenario the z block stays 10-70 % off; the
errors-in-variables of measurement noise bias it further). Instrumental variables are the classical
cure for both (Söderström & Stoica, *System Identification*, ch. 8; Young's refined IV).

For each unknown row ``y' = theta . phi + d`` (a block's last row, and for the 4th-order blocks the
tilt coupling row ``x_ddot = c theta``) and with

* ``F(s) = lambda^2 s / ((s + lambda)^2 (s + w_h))``, a band-pass state-variable filter: both sides
  filtered, ``sF{y} = theta . F{phi} + F{d}``, no differentiation of measurements, constants and
  drifts below ``w_h`` removed;
* instruments ``xi = F{[x_aux ; r]}`` where ``x_aux`` is the block simulated from the reference
  alone by an *auxiliary model* (the latest stable estimate, refreshed every ``aux_period``):
  correlated with the regressors through the reference, uncorrelated with disturbances and noise;

the estimate solves the exponentially weighted, regularised IV normal equations::

    C = int mu(t - s) xi phi^T ds,   b = int mu(t - s) xi sF{y} ds
    (C + W) theta = b + W theta_prior

with ``W`` a weak prior (``prior_weight``) toward a generic stable closed loop. Forgetting
(time constant ``window``) only runs while the block is excited: without excitation nothing is
forgotten and the estimate stays where the data put it (no covariance wind-up).

Excitation is measured per row on a shorter window (``excitation_window``) as the smallest
canonical correlation between instruments and regressors, ``sigma_min(G_xi^-1/2 C G_phi^-1/2)``,
in [0, 1]: zero when some direction of the regressor is not driven by the reference (persistent
excitation in the IV sense; Definition 1 of the paper with the instruments). The parameter
uncertainty is the IV covariance ``s2 tau C^-1 G_xi C^-T`` (``s2`` the residual variance, ``tau``
its correlation time, taken as ``4/lambda``). A row is *identified* when it is excited and its
relative uncertainty is below ``identified_uncertainty``; *not identifiable* when not excited or
above ``unidentifiable_uncertainty``; *converging* in between.

The filters start from a state that cannot be consistent with the unknown past, so the filtered
equation carries a start-up transient in the filter's slowest mode ``exp(-w_h t)``; a nuisance
regressor on that mode absorbs it. Rows are padded to 6 entries (5 parameters and the nuisance)
and batched over N vehicles (leading axis), so one set of array operations serves every row.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cloe_ros.core import kernels, kernels_identifier
from cloe_ros.core.model import (
    BLOCK_SLICES,
    BLOCKS,
    N_PARAMS,
    N_REFERENCES,
    N_STATES,
    PAPER_COUPLING,
    discretise,
    system_matrices,
)
from cloe_ros.core.rows import Rows
from cloe_ros.errors import ConfigError
from cloe_ros.settings import check_fields, default

#: Status codes per row, as published.
NOT_IDENTIFIABLE, CONVERGING, IDENTIFIED = 0, 1, 2
STATUS_NAMES = {NOT_IDENTIFIABLE: 'not identifiable', CONVERGING: 'converging',
                IDENTIFIED: 'identified'}  # fmt: skip

#: Names of the identified rows: the four blocks, the tilt couplings of the 4th-order blocks,
#: and the reduced position loops of those blocks (see ``ATTITUDE_LOOP``).
ROW_NAMES = ('x_theta', 'y_phi', 'psi', 'z', 'x_coupling', 'y_coupling', 'x_loop', 'y_loop')
N_ROWS = len(ROW_NAMES)
COUPLING_ROWS = (4, 5)
LOOP_ROWS = (6, 7)
#: The reference channel (x_d, y_d, psi_d, z_d) each row's block follows.
ROW_CHANNEL = np.array([0, 1, 2, 3, 0, 1, 0, 1])

#: The reduced model of a 4th-order block: a cascade whose attitude loop is assumed (stiffness
#: ``k_a``, damping ``k_d``: omega 14 rad/s, zeta 0.7, much faster than any position loop), so only
#: the position loop is identified, two numbers a single-frequency flight determines::
#:
#:     theta_ddot + k_a theta + k_d theta_dot = -k_a (p1 (x - x_d) + p2 x_dot)
#:
#: with ``p1 = k_p / c``, ``p2 = k_v / c`` (position gains over the tilt coupling). As a full row:
#: ``[a_x, a_x_dot, a_theta, a_theta_dot, b] = [-k_a p1, -k_a p2, -k_a, -k_d, k_a p1]``.
ATTITUDE_LOOP = (196.0, 19.6)
#: The prior of the reduced rows: ``k_p = 4``, ``k_v = 3.2`` m/s^2 per m and per m/s (omega 2
#: rad/s, zeta 0.8).
PRIOR_LOOP = (4.0, 3.2)
WIDTH = 6  # rows are padded to 5 entries, plus the start-up transient (see _DECAY)

#: Signals below this RMS (normalised units: 1 mm, 0.1 mrad of tilt) carry no excitation.
QUIET = 1e-3
#: Time constant of the low-pass against which a row's drift is measured, s. Long enough to
#: remember a large recent move: with measurement noise a row can move by 20 % within some
#: seconds and then sit 10 % off for as long, with a small nominal uncertainty (seen: the psi
#: row, seed 3). With 2 s such rows were reported identified while 10-21 % off for a quarter of
#: the run; with 10 s, over six noise seeds, never while more than 10 % off. The price: without
#: noise, a row is reported identified from about 30 s on instead of 6-10 s.
DRIFT_TIME = 10.0
#: Recent data on which a reduced loop not yet identified is compared with the model in use, s,
#: and the horizon of the comparison's predictions, s.
VALIDATION_WINDOW = 4.0
VALIDATION_HORIZON = 1.0
#: A reduced loop is taken on validation only if it predicts at least this much better.
VALIDATION_MARGIN = 0.8

#: Normalising scale of each state (positions m, velocities m/s, angles rad, rates rad/s).
STATE_SCALE = np.array([1.0, 1.0, 0.1, 0.5, 1.0, 1.0, 0.1, 0.5, 0.3, 1.0, 1.0, 1.0])
REFERENCE_SCALE = np.array([1.0, 1.0, 0.3, 1.0])


def loop_row(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """The full 5-parameter row (..., 5) of the reduced model with position loop ``(p1, p2)``."""
    k_a, k_d = ATTITUDE_LOOP
    p1, p2 = np.asarray(p1, float), np.asarray(p2, float)
    return np.stack(
        [-k_a * p1, -k_a * p2, np.full_like(p1, -k_a), np.full_like(p1, -k_d), k_a * p1], axis=-1
    )


def fresh(compute):
    """``compute``, a function of hashable settings that returns arrays, computed once per
    settings and copied at every call (the caller may write to them). What every identifier
    computes alike when it starts: two thirds of making one (0.37 -> 0.12 ms), which a swarm
    seen at once does a hundred times in one round."""
    cached = functools.lru_cache(maxsize=16)(compute)

    @functools.wraps(compute)
    def copies(*args):
        return tuple(v.copy() if isinstance(v, np.ndarray) else v for v in cached(*args))

    return copies


@fresh
def cascade_prior() -> tuple[np.ndarray, np.ndarray]:
    """The model used before anything is identified: for x-theta and y-phi the reduced cascade
    with the assumed attitude loop and the prior position loop (poles about -2.13 +- 1.32j and
    -7.67 +- 8.09j, a more quadrotor-like response than :func:`generic_prior`'s); psi and z as
    there."""
    theta, coupling = generic_prior()
    for block, sl, c in zip(BLOCKS, BLOCK_SLICES, (*PAPER_COUPLING, None, None)):
        if block.order == 4:
            theta[sl] = loop_row(PRIOR_LOOP[0] / c, PRIOR_LOOP[1] / c)
    return theta, coupling


@fresh
def generic_prior() -> tuple[np.ndarray, np.ndarray]:
    """A generic stable closed loop with unit static gain: the identifier's prior.

    x-theta and y-phi: poles -1.5 +- 1j and -6 +- 6j; psi and z: -5 +- 5j. Returns ``(theta (16,),
    coupling (2,))`` with the couplings at +g and -g. It only decides what the model is in
    directions the data have not excited yet, and it generates the first instruments. (The reduced
    cascade of ``ATTITUDE_LOOP`` was tried as this prior: as first instruments it made the y-phi
    estimate 60-170 % off for a minute with measurement noise, against 0.3-3 % with this one.)
    """
    theta = []
    for block in BLOCKS:
        if block.order == 4:
            p = np.poly([-1.5 + 1j, -1.5 - 1j, -6 + 6j, -6 - 6j]).real
            g = block.coupling
            theta += [-p[4] / g, -p[3] / g, -p[2], -p[1], p[4] / g]
        else:
            p = np.poly([-5 + 5j, -5 - 5j]).real
            theta += [-p[2], -p[1], p[2]]
    return np.array(theta), PAPER_COUPLING.copy()


@dataclass(frozen=True)
class IdentifierConfig:
    """Settings of the IV identifier.

    Attributes:
        bandwidth: lambda of the state-variable filter, rad/s.
        highpass: w_h of the filter, rad/s (removes offsets and slow drifts).
        window: Forgetting time constant of the estimate, s.
        excitation_window: Time constant of the excitation measure, s.
        excitation_threshold: Smallest canonical correlation counted as excited.
        aux_period: How often the auxiliary model takes the latest stable estimate, s.
        prior_weight: Weight of the prior, in seconds of unit-variance normalised data.
        estimate_coupling: Identify the tilt couplings (``+-g`` in the paper's model).
        identified_uncertainty: Relative parameter uncertainty below which a row is identified.
        unidentifiable_uncertainty: Relative uncertainty above which it is not identifiable.

    """

    bandwidth: float = default('id_bandwidth')
    highpass: float = default('id_highpass')
    window: float = default('id_window')
    excitation_window: float = default('id_excitation_window')
    excitation_threshold: float = default('id_excitation_threshold')
    aux_period: float = 2.0
    prior_weight: float = 1e-7
    estimate_coupling: bool = default('estimate_coupling')
    identified_uncertainty: float = 0.05
    unidentifiable_uncertainty: float = 0.3

    def __post_init__(self) -> None:
        check_fields(self, 'identifier')  # the settings' defaults and ranges: cloe_ros.settings
        checks = (
            ('aux_period', 0.01, 1e4), ('prior_weight', 1e-12, 1e6),
            ('identified_uncertainty', 1e-6, 10.0), ('unidentifiable_uncertainty', 1e-6, 100.0),
        )  # fmt: skip
        for name, low, high in checks:
            value = getattr(self, name)
            if not (np.isfinite(value) and low <= value <= high):
                msg = f'{name} must be within [{low:g}, {high:g}], got {value!r}'
                raise ConfigError(msg)
        if self.highpass >= self.bandwidth:
            reason = f'must be below id_bandwidth ({self.bandwidth:g}), got {self.highpass!r}'
            raise ConfigError(reason, 'id_highpass')
        if self.identified_uncertainty >= self.unidentifiable_uncertainty:
            msg = 'identified_uncertainty must be below unidentifiable_uncertainty'
            raise ConfigError(msg)


# Channels fed to the filter bank: the measured state (12), the reference (4), the auxiliary
# model's state (12), and a constant zero used for padding. After filtering one more column is
# appended, _DECAY = exp(-w_h (t - t0)): the filters start from a state that is not consistent with
# the data before t0 (nothing is known of it), and the filtered equation then carries a transient
# in the filter's slowest mode; a nuisance regressor on that mode (its own instrument) absorbs it.
_ZETA, _REF, _AUX, _ZERO = 0, N_STATES, N_STATES + N_REFERENCES, 2 * N_STATES + N_REFERENCES
N_CHANNELS = _ZERO + 1
_DECAY = N_CHANNELS


def _row_layout():
    """Linear maps from the filtered channels to every row's regressors, instruments and target.

    ``phi = F @ PHI_MAP[row]``, ``xi = F @ XI_MAP[row]`` (entries padded to ``WIDTH``, the last one
    the start-up transient), ``y = F @ Y_F_MAP[row] + sF @ Y_D_MAP[row]``, where ``F`` and
    ``sF`` are the filtered channels (normalised units). Also the number of parameters of each
    row and the normalising scales of its entries and target.
    """
    n_f = N_CHANNELS + 1
    phi = np.zeros((N_ROWS, n_f, WIDTH))
    xi = np.zeros((N_ROWS, n_f, WIDTH))
    y_f = np.zeros((N_ROWS, n_f))
    y_d = np.zeros((N_ROWS, N_CHANNELS))
    size = np.zeros(N_ROWS, dtype=np.intp)
    scale = np.ones((N_ROWS, WIDTH))
    target_scale = np.ones(N_ROWS)
    phi[:, _DECAY, WIDTH - 1] = xi[:, _DECAY, WIDTH - 1] = 1.0
    coupled = [b for b in BLOCKS if b.coupling is not None]
    for p, block in enumerate(BLOCKS):
        n = block.order
        for j, i in enumerate(block.states):
            phi[p, _ZETA + i, j] = 1.0
            xi[p, _AUX + i, j] = 1.0
            scale[p, j] = STATE_SCALE[i]
        phi[p, _REF + block.reference, n] = xi[p, _REF + block.reference, n] = 1.0
        scale[p, n] = REFERENCE_SCALE[block.reference]
        y_d[p, _ZETA + block.last] = 1.0
        size[p], target_scale[p] = n + 1, STATE_SCALE[block.last]
    for k, block in enumerate(coupled):
        p = COUPLING_ROWS[k]
        angle, velocity = block.states[2], block.states[1]
        phi[p, _ZETA + angle, 0] = xi[p, _AUX + angle, 0] = 1.0
        y_d[p, _ZETA + velocity] = 1.0
        size[p], target_scale[p], scale[p, 0] = 1, STATE_SCALE[velocity], STATE_SCALE[angle]
    k_a, k_d = ATTITUDE_LOOP
    for k, block in enumerate(coupled):
        p = LOOP_ROWS[k]
        pos, vel, angle, rate = block.states
        s_rate = STATE_SCALE[rate]
        # target: sF{rate} + k_a F{angle} + k_d F{rate}, in units of the rate's scale
        y_d[p, _ZETA + rate] = 1.0
        y_f[p, _ZETA + angle] = k_a * STATE_SCALE[angle] / s_rate
        y_f[p, _ZETA + rate] = k_d
        # regressors -k_a [F{pos - pos_d}, F{vel}] (positions and velocities have scale 1)
        ref = _REF + block.reference
        phi[p, _ZETA + pos, 0], phi[p, ref, 0], phi[p, _ZETA + vel, 1] = -k_a, k_a, -k_a
        xi[p, _AUX + pos, 0], xi[p, ref, 0], xi[p, _AUX + vel, 1] = -k_a, k_a, -k_a
        size[p], target_scale[p] = 2, s_rate
    return phi, xi, y_f, y_d, size, scale, target_scale


PHI_MAP, XI_MAP, Y_F_MAP, Y_D_MAP, ROW_SIZE, ROW_SCALE, TARGET_SCALE = _row_layout()


def _sparse_map(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A map (rows, channels, WIDTH) with at most two channels per entry as gathers: the
    channels (2, rows * WIDTH) and their coefficients (2, rows * WIDTH) (0 where unused), so that
    ``einsum('nc,rcw->nrw', f, m)`` is ``f[:, c0] a0 + f[:, c1] a1``: element-wise, the same
    values whatever the number of vehicles (a BLAS product's are not), 20x faster at N = 100."""
    flat = m.transpose(1, 0, 2).reshape(m.shape[1], -1)  # (channels, rows * WIDTH)
    channels = np.zeros((2, flat.shape[1]), dtype=np.intp)
    coefficients = np.zeros((2, flat.shape[1]))
    for j in range(flat.shape[1]):
        (used,) = np.nonzero(flat[:, j])
        if len(used) > 2:
            raise ValueError('a regressor entry maps more than two channels')
        channels[: len(used), j] = used
        coefficients[: len(used), j] = flat[used, j]
    return channels, coefficients


PHI_GATHER, XI_GATHER = _sparse_map(PHI_MAP), _sparse_map(XI_MAP)


def _statistic_layout() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The entries of the (rows, WIDTH, WIDTH) statistics that can be non-zero, as the
    identifier stores them (packed, :data:`N_PACKED` per vehicle): ``(p, i, j)`` with ``i`` and
    ``j`` among row ``p``'s regressors (``< ROW_SIZE[p]``) and the decay entry (``WIDTH - 1``).
    The others multiply a regressor or instrument entry that the row's mask holds at 0, so they
    are 0 exactly (while the statistics are finite: a non-finite one is caught as broken in the
    packed entries, the only ones the estimate reads). Returns each entry's row, its ``i`` and
    ``j`` as indices into a flattened (rows, WIDTH) vector, and its index into a flattened
    (rows, WIDTH, WIDTH) matrix."""
    rows, left, right = [], [], []
    for p, size in enumerate(ROW_SIZE):
        used = np.r_[0:size, WIDTH - 1]
        i, j = np.meshgrid(used, used, indexing='ij')
        rows += [p] * i.size
        left += (p * WIDTH + i.ravel()).tolist()
        right += (p * WIDTH + j.ravel()).tolist()
    rows, left, right = (np.array(a, dtype=np.intp) for a in (rows, left, right))
    return rows, left, right, left * WIDTH + right % WIDTH


STAT_ROW, STAT_LEFT, STAT_RIGHT, STAT_FLAT = _statistic_layout()
N_PACKED = len(STAT_ROW)
#: Where each entry of a flattened (rows, WIDTH, WIDTH) matrix is packed (-1: always 0).
STAT_PACKED = np.full(N_ROWS * WIDTH * WIDTH, -1, dtype=np.intp)
STAT_PACKED[STAT_FLAT] = np.arange(N_PACKED)
#: The statistics, in this order along the second axis of :attr:`IvIdentifier.statistics`: the
#: short window's (forgotten at every step) first, then the long window's (gated).
STATISTICS = ('cross_e', 'gram_xi', 'gram_phi', 'cross', 'gram_xi_long')
CROSS_E, GRAM_XI, GRAM_PHI, CROSS, GRAM_XI_LONG = range(len(STATISTICS))
_SHORT, _LONG = slice(0, 3), slice(3, 5)

#: Whether the periodic solve and excitation measures run compiled
#: (:mod:`~cloe_ros.core.kernels_identifier`, bit for bit the numpy code of
#: :meth:`IvIdentifier._solve` and :meth:`IvIdentifier._update_excitation`); False runs the numpy
#: code (numpy without its OpenBLAS; the kernels' tests set it to compare the two).
COMPILED = kernels_identifier.AVAILABLE
_ROW_SIZES = np.ascontiguousarray(ROW_SIZE, dtype=np.intp)
_SIZES = np.unique(_ROW_SIZES)
_COUPLING_ROWS = np.array(COUPLING_ROWS, dtype=np.intp)
_LOOP_ROWS = np.array(LOOP_ROWS, dtype=np.intp)
_BLOCK_ROWS = np.arange(len(BLOCKS), dtype=np.intp)  # (block p's parameters are row p's)
_BLOCK_STARTS = np.array([sl.start for sl in BLOCK_SLICES], dtype=np.intp)


@fresh
def filter_matrices(bandwidth: float, highpass: float, h: float):
    """Tustin discretisation of ``F`` and ``sF`` (common state): ``(Ad, Bd, Cf, Df, Cd, Dd)``.

    ``x+ = Ad x + Bd u``, ``F{u} = Cf x + Df u``, ``sF{u} = Cd x + Dd u`` (3 states).
    """
    ad, bd, cd, dd = tustin(*filter_system(bandwidth, highpass), h)
    return ad, bd[:, 0], cd[0], dd[0, 0], cd[1], dd[1, 0]


def filter_system(bandwidth: float, highpass: float):
    """The continuous ``(A, B, C, D)`` of ``F`` and ``sF`` that :func:`filter_matrices`
    discretises: ``F = lam^2 s / den`` and ``sF = lam^2 s^2 / den``, with ``den = (s + lam)^2
    (s + wh)`` (controllable canonical form, 3 states)."""
    lam, wh = bandwidth, highpass
    den = np.polymul(np.polymul([1.0, lam], [1.0, lam]), [1.0, wh])  # s^3 + a2 s^2 + a1 s + a0
    a = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-den[3], -den[2], -den[1]]])
    b = np.array([[0.0], [0.0], [1.0]])
    c = np.array([[0.0, lam**2, 0.0], [0.0, 0.0, lam**2]])  # lam^2 s / den, lam^2 s^2 / den
    return a, b, c, np.zeros((2, 1))


def tustin(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, h: float):
    """The bilinear (Tustin) discretisation of ``(A, B, C, D)`` with step ``h``: the operations
    of ``scipy.signal.cont2discrete(..., method='bilinear')``, whose module takes half a second to
    import (the node's start-up) for these five lines, with numpy's solves for scipy.linalg's (the
    same bits on the identifier's filters; test_identifier checks both)."""
    alpha = 0.5
    ima = np.eye(a.shape[0]) - alpha * h * a
    ad = np.linalg.solve(ima, np.eye(a.shape[0]) + (1.0 - alpha) * h * a)
    bd = np.linalg.solve(ima, h * b)
    cd = np.linalg.solve(ima.transpose(), c.transpose()).transpose()
    dd = d + alpha * np.dot(c, bd)
    return ad, bd, cd, dd


def block_is_stable(
    theta: np.ndarray, coupling: np.ndarray, margin: float = 0.0, step: float | None = None
) -> np.ndarray:
    """Per vehicle and block (N, 4): all poles have real part < -margin; with ``step`` also
    ``|1 + step * pole| < 1``, so an explicit step of that size on the model stays stable too."""
    a, _ = system_matrices(np.atleast_2d(theta), np.atleast_2d(coupling))
    out = np.empty((a.shape[0], len(BLOCKS)), dtype=bool)
    for j, block in enumerate(BLOCKS):
        idx = np.array(block.states)
        poles = np.linalg.eigvals(a[:, idx[:, None], idx[None, :]])
        ok = np.max(poles.real, axis=-1) < -margin
        if step is not None:
            ok &= np.max(np.abs(1.0 + step * poles), axis=-1) < 1.0
        out[:, j] = ok
    return out


@dataclass
class _StepWork:
    """Work arrays of :meth:`IvIdentifier.step` for N vehicles, allocated once: the step's
    kernels (:mod:`cloe_ros.core.kernels`) write their intermediate results into them, so
    that the step allocates no array the size of the statistics."""

    f: np.ndarray
    d: np.ndarray
    phi: np.ndarray
    xi: np.ndarray
    y: np.ndarray
    increments: np.ndarray
    active: np.ndarray
    whole: np.ndarray
    gate: np.ndarray
    weight: np.ndarray
    settled: np.ndarray
    mu_e: np.ndarray
    due: np.ndarray
    due_model: np.ndarray
    excited: np.ndarray
    phi_t: np.ndarray
    xi_t: np.ndarray
    forget: np.ndarray
    u: np.ndarray
    x: np.ndarray
    fx: np.ndarray

    @classmethod
    def allocate(cls, n: int) -> _StepWork:
        return cls(
            f=np.zeros((n, N_CHANNELS + 1)), d=np.zeros((n, N_CHANNELS)),
            phi=np.zeros((n, N_ROWS * WIDTH)), xi=np.zeros((n, N_ROWS * WIDTH)),
            y=np.zeros((n, N_ROWS)), increments=np.zeros((3, N_PACKED, n)),
            active=np.ones((n, N_ROWS), dtype=bool), whole=np.ones(n, dtype=bool),
            gate=np.ones((n, N_ROWS)), weight=np.ones(n), settled=np.ones(n, dtype=bool),
            mu_e=np.ones(n), due=np.zeros(n, dtype=bool), due_model=np.zeros(n, dtype=bool),
            excited=np.zeros((n, N_ROWS), dtype=bool),
            phi_t=np.zeros((N_ROWS * WIDTH, n)), xi_t=np.zeros((N_ROWS * WIDTH, n)),
            forget=np.zeros((N_ROWS, n)), u=np.zeros(N_CHANNELS), x=np.zeros(N_STATES),
            fx=np.zeros((N_CHANNELS, 3)),
        )  # fmt: skip


def _target_gathers() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:data:`Y_F_MAP` as gathers of at most two channels per row (channels (2, rows),
    coefficients (2, rows)), and :data:`Y_D_MAP` of one (rows,): with two terms at most, a
    product with the map is their sum in any order, the same as the matrix product's."""
    f_channels, f_coefficients = np.zeros((2, N_ROWS), dtype=np.intp), np.zeros((2, N_ROWS))
    d_channels, d_coefficients = np.zeros(N_ROWS, dtype=np.intp), np.zeros(N_ROWS)
    for p in range(N_ROWS):
        (used,) = np.nonzero(Y_F_MAP[p])
        (single,) = np.nonzero(Y_D_MAP[p])
        if len(used) > 2 or len(single) > 1:
            raise ValueError('a target maps more channels than its gather holds')
        f_channels[: len(used), p], f_coefficients[: len(used), p] = used, Y_F_MAP[p, used]
        d_channels[p], d_coefficients[p] = single[0], Y_D_MAP[p, single[0]]
    return f_channels, f_coefficients, d_channels, d_coefficients


Y_F_GATHER_C, Y_F_GATHER_A, Y_D_GATHER_C, Y_D_GATHER_A = _target_gathers()


class IvIdentifier(Rows):
    """The recursive IV identifier for N vehicles (see the module docstring).

    Args:
        config: Settings.
        h: Step, s (fixed).
        zeta0: First measurement (N, 12): starts the filters and the auxiliary model at rest.
        r0: First reference (N, 4).
        theta_prior: Prior parameters (16,) (default: :func:`generic_prior`).
        coupling_prior: Prior couplings (2,) (default ``(+g, -g)``).

    """

    def __init__(
        self,
        config: IdentifierConfig,
        h: float,
        zeta0: np.ndarray,
        r0: np.ndarray,
        theta_prior: np.ndarray | None = None,
        coupling_prior: np.ndarray | None = None,
    ) -> None:
        self.config = config
        self.h = float(h)
        zeta0 = np.atleast_2d(np.asarray(zeta0, dtype=float))
        r0 = np.atleast_2d(np.asarray(r0, dtype=float))
        n = zeta0.shape[0]
        prior_theta, prior_coupling = generic_prior()
        self.theta_prior = prior_theta if theta_prior is None else np.asarray(theta_prior, float)
        self.coupling_prior = (
            prior_coupling if coupling_prior is None else np.asarray(coupling_prior, float)
        )
        self.theta = np.tile(self.theta_prior, (n, 1))
        self.coupling = np.tile(self.coupling_prior, (n, 1))
        self.loop_prior = np.array([[PRIOR_LOOP[0] / c, PRIOR_LOOP[1] / c]
                                    for c in self.coupling_prior])  # fmt: skip
        self.loops = np.tile(self.loop_prior, (n, 1, 1))
        # filter bank, started in steady state for the first sample (constants are filtered out)
        ad, bd, cf, df, cd, dd = filter_matrices(config.bandwidth, config.highpass, self.h)
        self._ad_t, self._bd, self._cf, self._df, self._cd, self._dd = (
            *map(np.ascontiguousarray, (ad.T, bd, cf)), float(df), np.ascontiguousarray(cd),
            float(dd))  # (contiguous, as the kernels take them)
        x_ss = np.linalg.solve(np.eye(3) - ad, bd)  # state for a constant unit input
        u0 = self._channels(zeta0, r0, zeta0)
        self._fx = u0[..., None] * x_ss  # (N, C, 3)
        # auxiliary model (reference-driven simulation of every block), and the constant taken
        # off its output (see _set_aux)
        self.x_aux = zeta0.copy()
        self._aux_shift = np.zeros((n, N_STATES))
        self._last_r = r0.copy()
        self._aux_ad = np.zeros((n, N_STATES, N_STATES))
        self._aux_bd = np.zeros((n, N_STATES, N_REFERENCES))
        self.aux_theta = self.theta.copy()
        self.aux_coupling = self.coupling.copy()
        # the usable model (see _update_model): at first the cascade prior, unless a prior is given
        start = cascade_prior()[0] if theta_prior is None else self.theta_prior
        self.model_theta = np.tile(start, (n, 1))
        self.model_coupling = self.coupling.copy()
        self.model_kind = np.full((n, len(BLOCKS)), 'prior')  # per block: prior|reduced|full
        self._set_aux(np.ones(n, dtype=bool))
        # every vehicle keeps its own clocks, so that vehicles started at different times can
        # share one identifier (cloe_ros.core.rows)
        self._since_aux = np.zeros(n)
        # normal equations and excitation statistics per row (normalised coordinates), packed
        # (see STATISTICS and _statistic_layout): short window xi phi^T, xi xi^T, phi phi^T;
        # long window (gated) C = int xi phi^T and int xi xi^T (the estimate's covariance)
        self.statistics = np.zeros((n, len(STATISTICS), N_PACKED))  # (stored vehicles last)
        self.rhs = np.zeros((n, N_ROWS, WIDTH))  # b = int xi y
        self.res2 = np.zeros((n, N_ROWS))  # residual power (short window)
        self.weight_e = np.zeros(n)  # integral of the short-window weight (residual mean)
        self.excitation = np.zeros((n, N_ROWS))
        self.uncertainty = np.full((n, N_ROWS), np.inf)
        self.status = np.zeros((n, N_ROWS), dtype=np.int8)
        self._mu = float(np.exp(-self.h / config.window))
        self._mu_e = float(np.exp(-self.h / config.excitation_window))
        self._steps = np.zeros(n, dtype=np.int64)  # steps with statistics (after the settling)
        self._mask = np.zeros((N_ROWS, WIDTH), dtype=bool)
        for p in range(N_ROWS):
            self._mask[p, : ROW_SIZE[p]] = True
        self._mask[:, WIDTH - 1] = True
        if not config.estimate_coupling:
            self._mask[list(COUPLING_ROWS)] = False
        self._mask_flat = self._mask.ravel()
        self._t = np.zeros(n)  # time since the start
        # the estimate is solved at 20 Hz, the excitation measured at 4 Hz (both cheap enough)
        self._solve_every = max(1, round(0.05 / self.h))
        self._excitation_every = max(1, round(0.25 / self.h))
        self._settle = 5.0 / config.bandwidth  # the fast filter modes are gone after this
        prior_norm = self._normalised(self.theta_prior, self.coupling_prior, self.loop_prior)
        self._prior_norm = np.tile(prior_norm, (n, 1, 1))  # per vehicle (priors may differ)
        self._rows = self._prior_norm.copy()  # last solution (normalised)
        self._rows_slow = self._rows.copy()  # its low-pass (DRIFT_TIME), see _update_excitation
        # the last VALIDATION_WINDOW of measurements and references (see _validate)
        w = max(2, round(VALIDATION_WINDOW / self.h))
        self._hist_z = np.zeros((n, w, N_STATES))
        self._hist_r = np.zeros((n, w, N_REFERENCES))
        self._hist_active = np.zeros((n, w), dtype=bool)
        self._hist_next = np.zeros(n, dtype=np.intp)
        self._hist_count = np.zeros(n, dtype=np.int64)
        self._allocate_work(n)

    # ------------------------------------------------------------ vehicles as rows

    #: The attributes that hold one entry per vehicle (leading axis N); everything else is
    #: shared: the settings, the step and the filters built from them.
    ROW_FIELDS = (
        'theta', 'coupling', 'loops', '_fx', 'x_aux', '_aux_shift', '_last_r', '_aux_ad',
        '_aux_bd', 'aux_theta', 'aux_coupling', 'model_theta', 'model_coupling', 'model_kind',
        '_since_aux', 'statistics', 'rhs', 'res2',
        'weight_e', 'excitation', 'uncertainty', 'status', '_steps', '_t', '_prior_norm',
        '_rows', '_rows_slow', '_hist_z', '_hist_r', '_hist_active', '_hist_next',
        '_hist_count',
    )  # fmt: skip

    @property
    def statistics(self) -> np.ndarray:
        """The packed statistics (N, len(STATISTICS), N_PACKED), a view: they are stored with the
        vehicles as the innermost axis, so that the step's gathers and element-wise updates run
        along contiguous memory (at N = 100, 63 µs a step against 142 µs with the vehicles
        first, in a microbenchmark of the updates alone)."""
        return np.moveaxis(self._statistics_t, -1, 0)

    @statistics.setter
    def statistics(self, value: np.ndarray) -> None:
        self._statistics_t = np.ascontiguousarray(np.moveaxis(np.asarray(value, float), 0, -1))

    def statistic(self, which: int, sel=slice(None)) -> np.ndarray:
        """The statistic ``which`` (an index into :data:`STATISTICS`) of the vehicles ``sel``
        as (n, rows, WIDTH, WIDTH) matrices: a new array, read-only."""
        packed = self.statistics[sel, which]
        out = np.zeros((len(packed), N_ROWS * WIDTH * WIDTH))
        out[:, STAT_FLAT] = packed
        out.flags.writeable = False
        return out.reshape(-1, N_ROWS, WIDTH, WIDTH)

    cross_e = property(lambda self: self.statistic(CROSS_E), doc='Short window: xi phi^T.')
    gram_xi = property(lambda self: self.statistic(GRAM_XI), doc='Short window: xi xi^T.')
    gram_phi = property(lambda self: self.statistic(GRAM_PHI), doc='Short window: phi phi^T.')
    cross = property(lambda self: self.statistic(CROSS), doc='Long window: C = int xi phi^T.')
    gram_xi_long = property(lambda self: self.statistic(GRAM_XI_LONG),
                            doc='Long window: int xi xi^T (the covariance).')

    def shares_settings(self, other: Rows) -> bool:
        return isinstance(other, IvIdentifier) and (other.config, other.h) == (self.config, self.h)

    def _allocate_work(self, n: int) -> None:
        self._work = _StepWork.allocate(n)

    # ---------------------------------------------------------------- layout helpers

    @staticmethod
    def _channels(
        zeta: np.ndarray, r: np.ndarray, aux: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        u = np.empty((zeta.shape[0], N_CHANNELS)) if out is None else out
        np.divide(zeta, STATE_SCALE, out=u[:, _ZETA:_REF])
        np.divide(r, REFERENCE_SCALE, out=u[:, _REF:_AUX])
        np.divide(aux, STATE_SCALE, out=u[:, _AUX:_ZERO])
        u[:, _ZERO] = 0.0
        return u

    @staticmethod
    def _normalised(
        theta: np.ndarray, coupling: np.ndarray, loops: np.ndarray | None = None
    ) -> np.ndarray:
        """Row parameters (..., rows, WIDTH) in normalised units (scale_j / target scale); the
        transient's coefficient is zero."""
        theta = np.asarray(theta, float)
        coupling = np.asarray(coupling, float)
        out = np.zeros((*theta.shape[:-1], N_ROWS, WIDTH))
        for p, sl in enumerate(BLOCK_SLICES):
            out[..., p, : ROW_SIZE[p]] = theta[..., sl]
        out[..., list(COUPLING_ROWS), 0] = coupling
        if loops is not None:
            out[..., list(LOOP_ROWS), :2] = loops
        return out * ROW_SCALE / TARGET_SCALE[:, None]

    def _denormalise(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``theta (N, 16)``, ``coupling (N, 2)``, ``loops (N, 2, 2)`` (``p1, p2`` per axis)."""
        rows = rows * TARGET_SCALE[:, None] / ROW_SCALE
        theta = np.concatenate([rows[:, p, : ROW_SIZE[p]] for p in range(len(BLOCKS))], axis=1)
        return theta, rows[:, list(COUPLING_ROWS), 0].copy(), rows[:, list(LOOP_ROWS), :2].copy()

    def _set_aux(self, which: np.ndarray, before: np.ndarray | None = None) -> None:
        """Discretise the auxiliary model (exact ZOH) for the vehicles in ``which``.

        ``before``, the equilibrium (N, 12) of the model being replaced under the latest
        reference (:meth:`_aux_equilibrium`): the state first moves by the change of that
        equilibrium, and so does the constant taken off the output, so the instruments see no
        transient from the model change itself. Without it, a block whose static gain ``g``
        changes would ring by ``(g_new - g_old) r``, in proportion to where the vehicle is, and
        the estimate would depend on the origin of the world frame.
        """
        if before is not None:
            step = self._aux_equilibrium()[which] - before[which]
            self.x_aux[which] += step
            self._aux_shift[which] += step
        ad, bd = discretise(self.aux_theta[which], self.aux_coupling[which], self.h)
        self._aux_ad[which], self._aux_bd[which] = ad, bd

    def _aux_equilibrium(self) -> np.ndarray:
        """Steady state ``-A^-1 B r`` of the auxiliary model under the latest reference (N, 12)."""
        a, b = system_matrices(self.aux_theta, self.aux_coupling)
        rhs = -np.einsum('nij,nj->ni', b, self._last_r)
        return np.linalg.solve(a, rhs[..., None])[..., 0]

    # ------------------------------------------------------------------------ step

    def step(self, zeta: np.ndarray, r: np.ndarray, active: np.ndarray | None = None) -> None:
        """Take the measurement ``zeta`` (N, 12) and the reference ``r`` (N, 4) of the same
        time; update the estimate. Vehicles with ``active`` False (N,), or rows with ``active``
        False (N, rows), keep filtering but add nothing to the estimate (e.g. while landed, or
        while the vehicle does not track that row's reference: the closed-loop model does not
        hold)."""
        cfg, h = self.config, self.h
        w = self._work
        if active is not None:
            active = np.asarray(active, dtype=bool)
            if active.all():
                active = None
            elif active.ndim == 1:
                active = np.repeat(active[:, None], N_ROWS, axis=1)
            else:
                active = np.ascontiguousarray(active)
        zeta = np.ascontiguousarray(zeta, dtype=float)
        r = np.ascontiguousarray(r, dtype=float)
        self._t += h
        decay = np.exp(-cfg.highpass * self._t)
        # The step in two compiled calls around the excitation measures (kernels.iv_step_filter,
        # kernels.iv_step_long): the filters, the regressors and instruments, the short window,
        # then the long window's normal equations, forgetting only while excited. The statistics
        # start once the filters' fast modes are gone; in a batch whose vehicles started at
        # different times, those still settling take part with no weight (nothing added, nothing
        # forgotten, no clock advanced).
        active = w.active if active is None else active
        flags = kernels.iv_step_filter(
            zeta, r, w.whole, decay, self._hist_z, self._hist_r, self._hist_active,
            self._hist_next, self._hist_count, self._aux_ad, self._aux_bd, self.x_aux,
            self._last_r, self._aux_shift, self._fx, self._cf, self._df, self._cd, self._dd,
            self._ad_t, self._bd, STATE_SCALE, REFERENCE_SCALE, PHI_GATHER[0], PHI_GATHER[1],
            XI_GATHER[0], XI_GATHER[1], self._mask_flat, Y_F_GATHER_C, Y_F_GATHER_A,
            Y_D_GATHER_C, Y_D_GATHER_A, w.gate, w.weight, h, w.f, w.d, w.phi, w.xi, w.y, w.u,
            w.x, w.fx, self._t, self._settle, active, self._excitation_every, self._mu_e,
            _flat(self._rows), STAT_LEFT, STAT_RIGHT, self._statistics_t[_SHORT], self.res2,
            self.weight_e, self._steps, w.increments, w.phi_t, w.xi_t, w.settled, w.mu_e, w.due,
        )  # fmt: skip
        if not flags & kernels.ANY_SETTLED:
            return
        if flags & kernels.ANY_DUE:
            self._update_excitation(None if flags & kernels.ALL_DUE else w.due.copy())
        flags = kernels.iv_step_long(
            w.xi, w.y, self.excitation, cfg.excitation_threshold, active, w.settled, self._mu, h,
            STAT_ROW, w.increments, self._statistics_t[_LONG], _flat(self.rhs), w.excited,
            w.forget, self._steps, self._solve_every, self._since_aux, cfg.aux_period - 1e-9,
            w.due, w.due_model,
        )  # fmt: skip
        if flags & kernels.ANY_DUE:
            self._solve(None if flags & kernels.ALL_DUE else w.due.copy())
        if flags & kernels.ANY_DUE_MODEL:
            self._update_model(None if flags & kernels.ALL_DUE_MODEL else w.due_model.copy())

    def _update_model(self, which: np.ndarray | None = None) -> None:
        """Refresh the auxiliary model and the usable model (every ``aux_period``) of the
        vehicles ``which`` (a mask (N,); None: all).

        The auxiliary model (the instruments' generator) takes every block estimate that is
        stable, while the block's reference moves: it only has to correlate with the regressors,
        and waiting for a row to be declared identified would starve the very measure that
        declares it; with a quiet reference a model change would be all the instruments carry.

        The usable model (what the observer runs on and the predictions integrate) takes, per
        block, the full estimate when the block's rows are at least converging; for a 4th-order
        block whose full row is not, the reduced model (:data:`ATTITUDE_LOOP`) when its position
        loop is, or when the loop is excited and its estimate predicts the last
        ``VALIDATION_WINDOW`` clearly better than the model in use (:meth:`_validate`); otherwise
        it keeps what it had (at first, the prior). A candidate must be stable, and stable for an
        explicit step of ``h`` (the observer integrates the drift explicitly).
        """
        cfg = self.config
        n = self.theta.shape[0]
        which = np.ones(n, dtype=bool) if which is None else which.copy()
        finite = np.isfinite(self.theta).all(axis=1) & np.isfinite(self.coupling).all(axis=1)
        which &= finite  # (a vehicle whose estimate is not finite is restarted by the engine)
        usable = (self.status >= CONVERGING) & which[:, None]
        moving = self.reference_rms() > QUIET
        stable = np.zeros((n, len(BLOCKS)), dtype=bool)
        if which.any():
            stable[which] = block_is_stable(self.theta[which], self.coupling[which], margin=0.05)
        before = self._aux_equilibrium() if np.any(stable) else None
        for j, sl in enumerate(BLOCK_SLICES):
            ok = stable[:, j] & moving[:, j]
            self.aux_theta[ok, sl] = self.theta[ok, sl]
            if BLOCKS[j].coupling is not None:
                self.aux_coupling[ok, j] = self.coupling[ok, j]
        # usable model: full estimate, else the reduced loop, per block and vehicle
        coupling = self.model_coupling.copy()
        for k, row in enumerate(COUPLING_ROWS):
            take = usable[:, row] if cfg.estimate_coupling else np.zeros(n, dtype=bool)
            coupling[take, k] = self.coupling[take, k]
        full = self.model_theta.copy()
        reduced = self.model_theta.copy()
        use_full = np.zeros((n, len(BLOCKS)), dtype=bool)
        use_reduced = np.zeros((n, len(BLOCKS)), dtype=bool)
        for j, sl in enumerate(BLOCK_SLICES):
            use_full[:, j] = usable[:, j]
            full[use_full[:, j], sl] = self.theta[use_full[:, j], sl]
            if j < len(LOOP_ROWS):
                use_reduced[:, j] = ~usable[:, j] & usable[:, LOOP_ROWS[j]]
                rows = loop_row(self.loops[:, j, 0], self.loops[:, j, 1])
                reduced[use_reduced[:, j], sl] = rows[use_reduced[:, j]]
        # a reduced loop excited but not (yet) usable by its uncertainty: taken if it predicts
        # the recent past clearly better than the model in use (see _validate)
        for j, sl in enumerate(BLOCK_SLICES[: len(LOOP_ROWS)]):
            excited = (self.excitation[:, LOOP_ROWS[j]] >= cfg.excitation_threshold) & which
            vs = np.flatnonzero(~use_full[:, j] & ~use_reduced[:, j] & excited)
            if not len(vs):
                continue
            rows = loop_row(self.loops[vs, j, 0], self.loops[vs, j, 1])
            in_use = self._validate(vs, j, self.model_theta[vs, sl], self.model_coupling[vs, j])
            better = self._validate(vs, j, rows, coupling[vs, j]) < VALIDATION_MARGIN * in_use
            use_reduced[vs[better], j] = True
            reduced[vs[better], sl] = rows[better]
        candidate = np.where(np.repeat(use_full, [b.n_params for b in BLOCKS], axis=1), full,
                             reduced)  # fmt: skip
        ok = block_is_stable(candidate, coupling, margin=0.05, step=self.h)
        ok &= use_full | use_reduced
        for j, sl in enumerate(BLOCK_SLICES):
            self.model_theta[ok[:, j], sl] = candidate[ok[:, j], sl]
            if j < len(COUPLING_ROWS):
                self.model_coupling[ok[:, j], j] = coupling[ok[:, j], j]
        self.model_kind = np.where(ok & use_full, 'full', np.where(ok, 'reduced',
                                                                    self.model_kind))  # fmt: skip
        if before is not None:
            self._set_aux(which, before)

    def _validate(
        self, vs: np.ndarray, j: int, block_theta: np.ndarray, coupling: np.ndarray
    ) -> np.ndarray:
        """Mean squared position error (len(vs),) of block ``j``'s model ``block_theta``
        (len(vs), n_params) with tilt coupling ``coupling`` (len(vs),) predicting the last
        ``VALIDATION_WINDOW`` of vehicles ``vs``: from the measured block state every 0.5 s,
        ``VALIDATION_HORIZON`` ahead, driven by the recorded reference. ``inf`` where there is not
        enough data, the vehicle was not active all along (landed), or the model is unstable."""
        w = self._hist_z.shape[1]
        out = np.full(len(vs), np.inf)
        full = self._hist_count[vs] >= w
        if not np.any(full):
            return out
        block = BLOCKS[j]
        idx = list(block.states)
        theta = self.model_theta[vs].copy()
        theta[:, BLOCK_SLICES[j]] = block_theta
        c = self.model_coupling[vs].copy()
        c[:, j] = coupling
        ok = full & self._hist_active[vs].all(axis=1) & block_is_stable(theta, c)[:, j]
        if not np.any(ok):
            return out
        # (the blocks are decoupled: the block of the full discretisation is the block's own)
        ad, bd = discretise(theta[ok], c[ok], self.h)
        ad_t = np.swapaxes(ad[:, idx][:, :, idx], 1, 2)
        bd = bd[:, None, idx, block.reference]
        # the block's states and reference, oldest first, in one gather each (not the whole
        # history taken in order, then the block's columns: 4.5 against 0.8 ms per call at 100
        # vehicles, run four times every aux_period, every other callback of a node waiting)
        v = vs[ok]
        order = (self._hist_next[v, None] + np.arange(w)) % w  # (V, w)
        z = self._hist_z[v[:, None, None], order[..., None], np.asarray(idx)]  # (V, w, n)
        r = self._hist_r[v[:, None], order, block.reference]  # (V, w)
        steps = round(VALIDATION_HORIZON / self.h)
        starts = np.arange(0, w - steps, max(1, round(0.5 / self.h)))
        x = z[:, starts]  # (V, S, n)
        err = np.zeros(len(x))
        for k in range(steps):
            x = x @ ad_t + r[:, starts + k, None] * bd
            err += np.sum((x[..., 0] - z[:, starts + k + 1, 0]) ** 2, axis=1)
        out[ok] = err / (len(starts) * steps)
        return out

    def reference_rms(self) -> np.ndarray:
        """RMS of each block's filtered reference over the short window (N, 4), normalised."""
        idx = ROW_SIZE[: len(BLOCKS)] - 1  # the reference is the last entry of a block's row
        diagonal = (np.arange(len(BLOCKS)) * WIDTH + idx) * WIDTH + idx  # (p, idx, idx)
        power = self._statistics_t[GRAM_XI, STAT_PACKED[diagonal]].T
        return np.sqrt(np.maximum(power, 0.0) / np.maximum(self.weight_e, 1e-12)[:, None])

    def _solve(self, which: np.ndarray | None = None) -> None:
        """The regularised IV normal equations: ``(C + W) theta = b + W theta_prior``, for the
        vehicles ``which`` (a mask (N,); None: all).

        ``W = prior_weight I``: small, so the prior only decides the directions the data have not
        reached. (A weight growing with the residual power was tried: in closed loop the residual
        is mostly disturbance, which IV already handles, and it biased the z block.)
        """
        sel = slice(None) if which is None else np.flatnonzero(which)
        w = self.config.prior_weight
        if COMPILED:
            failed = kernels_identifier.iv_solve(
                np.arange(len(self._rows)) if which is None else sel, self._statistics_t,
                STAT_PACKED, self.rhs, self._prior_norm, self._mask, w, TARGET_SCALE, ROW_SCALE,
                _BLOCK_ROWS, _BLOCK_STARTS, _COUPLING_ROWS, _LOOP_ROWS, self._rows, self.theta,
                self.coupling, self.loops,
            )  # fmt: skip
            if failed:
                raise np.linalg.LinAlgError('Singular matrix')
            return
        prior = self._prior_norm[sel]
        lhs = self.statistic(CROSS, sel) + w * np.eye(WIDTH)
        rhs = self.rhs[sel] + w * prior
        # (padded entries have zero regressors and instruments: the prior weight alone keeps them
        # at the prior, zero)
        rows = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        rows = np.where(self._mask, rows, prior)
        self._rows[sel] = rows
        self.theta[sel], self.coupling[sel], self.loops[sel] = self._denormalise(rows)

    def _update_excitation(self, which: np.ndarray | None = None) -> None:
        """Canonical correlations, uncertainty and status of every row (every 0.25 s), for the
        vehicles ``which`` (a mask (N,); None: all)."""
        cfg = self.config
        broken = self._broken_statistics(which)
        if broken.any():
            # a vehicle whose statistics overflowed gets a non-finite estimate (the engine then
            # restarts it); the others are measured as usual (linalg would raise for all)
            self.theta[broken] = np.nan
            which = (np.ones(len(broken), dtype=bool) if which is None else which) & ~broken
            if not which.any():
                return
        sel = slice(None) if which is None else np.flatnonzero(which)
        # (the low-pass of the drift, below: its gain per update)
        step = self._excitation_every * self.h
        gain = min(1.0, step / DRIFT_TIME)
        if COMPILED:
            due = np.arange(len(self._rows)) if which is None else sel
            failed = kernels_identifier.iv_excitation(
                due, self._statistics_t, STAT_PACKED, self._rows, self._rows_slow,
                self.weight_e, self.res2, self._mask, _ROW_SIZES, _SIZES, _COUPLING_ROWS,
                cfg.prior_weight, 4.0 / cfg.bandwidth, QUIET, gain,
                cfg.identified_uncertainty, cfg.unidentifiable_uncertainty,
                cfg.excitation_threshold, cfg.estimate_coupling, self.excitation,
                self.uncertainty, self.status,
            )  # fmt: skip
            if failed == kernels_identifier.EIGH_FAILED:
                raise np.linalg.LinAlgError('Eigenvalues did not converge')
            if failed == kernels_identifier.SVD_FAILED:
                raise np.linalg.LinAlgError('SVD did not converge')
            return
        rows = self._rows[sel]  # the current solution, normalised
        n = rows.shape[0]
        exc = np.zeros((n, N_ROWS))
        unc = np.full((n, N_ROWS), np.inf)
        weight = np.maximum(self.weight_e[sel], 1e-12)[:, None]
        sigma2 = self.res2[sel] / weight  # mean residual power
        # correlation time of the filtered residual; 4/lambda calibrated against the spread of
        # estimates over noise seeds (docs/identifier.md)
        tau = 4.0 / cfg.bandwidth
        cross_e, gram_xi, gram_phi, cross, gram_xi_long = (
            self.statistic(i, sel) for i in range(len(STATISTICS)))
        for size in np.unique(ROW_SIZE):
            ps = np.flatnonzero(ROW_SIZE == size)
            if not self._mask[ps[0], 0]:
                continue
            k = slice(0, size)
            gx = gram_xi[:, ps][..., k, k]
            gp = gram_phi[:, ps][..., k, k]
            c = cross_e[:, ps][..., k, k]
            wx = _inv_sqrt(gx)
            wp = _inv_sqrt(gp)
            s = np.linalg.svd(wx @ c @ wp, compute_uv=False)
            # instruments too weak to mean anything (below 1e-3 RMS in normalised units: 1 mm of
            # position, 0.1 mrad of tilt) count as no excitation at all
            rms = np.sqrt(np.trace(gx, axis1=-2, axis2=-1) / weight / size)
            exc[:, ps] = np.where(rms > QUIET, np.nan_to_num(s[..., -1]), 0.0)
            # IV covariance s2 tau C^-1 G_xi C^-T of the estimate's (long) window, relative to
            # the row's size
            c_long = cross[:, ps][..., k, k]
            gx_long = gram_xi_long[:, ps][..., k, k]
            try:
                ci = np.linalg.inv(c_long + self.config.prior_weight * np.eye(size))
                cov = np.einsum('...ij,...jk,...lk->...il', ci, gx_long, ci)
                var = np.trace(cov, axis1=-2, axis2=-1) * sigma2[:, ps] * tau
                norm = np.linalg.norm(rows[:, ps, :size], axis=-1)
                unc[:, ps] = np.sqrt(np.maximum(var, 0.0)) / np.maximum(norm, 1e-12)
            except np.linalg.LinAlgError:
                pass
        unc[~np.isfinite(unc)] = np.inf
        # An estimate that is still moving is not identified, whatever its covariance says: the
        # instruments come from the estimate's own earlier values, and with noisy measurements
        # that loop can drift along a poorly determined direction while the nominal uncertainty
        # stays small (seen: the x-theta row 418 % off, nominal uncertainty 0.05), or move and
        # then settle off the truth for a while (see DRIFT_TIME). The drift,
        # |rows - their low-pass over DRIFT_TIME| relative to the row's size, bounds the
        # published uncertainty from below and keeps a moving row from being called identified;
        # it does not make it unidentifiable (a row converging fast from its prior moves too).
        slow = self._rows_slow[sel]
        slow += gain * (rows - slow)
        self._rows_slow[sel] = slow
        drift = np.linalg.norm(rows - slow, axis=-1) / np.maximum(
            np.linalg.norm(rows, axis=-1), 1e-12
        )
        uncertainty = np.maximum(unc, drift)
        status = np.full((n, N_ROWS), CONVERGING, dtype=np.int8)
        status[uncertainty <= cfg.identified_uncertainty] = IDENTIFIED
        status[(exc < cfg.excitation_threshold) | (unc > cfg.unidentifiable_uncertainty)] = (
            NOT_IDENTIFIABLE
        )
        if not cfg.estimate_coupling:
            status[:, list(COUPLING_ROWS)] = IDENTIFIED  # known (fixed) coupling
        self.excitation[sel], self.uncertainty[sel], self.status[sel] = exc, uncertainty, status

    def _broken_statistics(self, which: np.ndarray | None) -> np.ndarray:
        """Vehicles (a mask (N,)) among ``which`` whose statistics are not all finite."""
        ok = np.isfinite(self.res2).all(axis=1) & np.isfinite(self._rows).all(axis=(1, 2))
        ok &= np.isfinite(self._statistics_t).all(axis=(0, 1))
        return ~ok if which is None else which & ~ok

    @property
    def n_vehicles(self) -> int:
        return self.theta.shape[0]


def _flat(a: np.ndarray) -> np.ndarray:
    """``a`` (N, ...) as (N, -1), a view (an error if that would need a copy: the kernels
    write into it)."""
    out = a.view()
    out.shape = (len(a), -1)
    return out


def _inv_sqrt(g: np.ndarray) -> np.ndarray:
    """``g^-1/2`` of symmetric positive semi-definite matrices (..., n, n); tiny eigenvalues
    clipped so unexcited directions give a canonical correlation of about zero."""
    w, v = np.linalg.eigh(g)
    scale = np.maximum(np.max(w, axis=-1, keepdims=True), 1e-300)
    w = np.where(w > 1e-12 * scale, w, np.inf)
    return np.einsum('...ij,...j,...kj->...ik', v, 1.0 / np.sqrt(w), v)


def n_params() -> int:
    return N_PARAMS
