"""Figures of the paper reproduction (Figures 6-8, 10-11) as PNG files."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt

from cloe_ros.core.experiments import PaperCase
from cloe_ros.core.model import BLOCK_SLICES, BLOCKS, PARAMETER_NAMES, STATE_NAMES

ALGORITHM_LABELS = {'cloe': 'CLOE', 'cloe_sm': 'CLOE-SM', 'cloe_rls': 'CLOE-RLS'}
STATE_LABELS = {
    'x': 'x', 'y': 'y', 'z': 'z', 'x_dot': r'$\dot x$', 'y_dot': r'$\dot y$', 'z_dot': r'$\dot z$',
    'theta': r'$\theta$', 'phi': r'$\phi$', 'psi': r'$\psi$', 'theta_dot': r'$\dot\theta$',
    'phi_dot': r'$\dot\phi$', 'psi_dot': r'$\dot\psi$',
}  # fmt: skip
UNITS = {'position': 'm', 'velocity': 'm/s', 'angles': 'rad', 'rates': 'rad/s'}
GROUPS = {
    'position': ('x', 'y', 'z'),
    'velocity': ('x_dot', 'y_dot', 'z_dot'),
    'angles': ('theta', 'phi', 'psi'),
    'rates': ('theta_dot', 'phi_dot', 'psi_dot'),
}
COLORS = ('tab:blue', 'tab:orange', 'tab:green')


def _decimate(n: int, max_points: int = 5000) -> slice:
    return slice(None, None, max(1, n // max_points))


def error_figure(
    case: PaperCase, disturbed: bool, groups: tuple[str, str], title: str, path: Path
) -> Path:
    """Two panels of estimation errors (one per group), CLOE solid and CLOE-SM dashed."""
    mask = case.run.t <= case.table_duration + 1e-9
    t = case.run.t[mask]
    sl = _decimate(len(t))
    fig, axes = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    for ax, group, letter in zip(axes, groups, 'ab'):
        for alg, style in (('cloe', '-'), ('cloe_sm', '--')):
            err = case.run.error[mask, case.index(disturbed, alg)]
            for name, color in zip(GROUPS[group], COLORS):
                ax.plot(
                    t[sl], err[sl, STATE_NAMES.index(name)], style, color=color, linewidth=1.0,
                    label=f'{STATE_LABELS[name]} {ALGORITHM_LABELS[alg]}',
                )  # fmt: skip
        ax.set_ylabel(f'{group} error [{UNITS[group]}]')
        ax.set_title(f'({letter}) {group} errors', loc='left', fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(ncol=2, fontsize=8, loc='upper right')
    axes[-1].set_xlabel('t [s]')
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def parameter_figure(
    case: PaperCase, algorithm: str, disturbed: bool, title: str, path: Path
) -> Path:
    """The 28 adapted quantities (16 parameters, 12 gains L) over time, truth dashed."""
    i = case.index(disturbed, algorithm)
    t = case.run.t_rec
    theta = case.run.theta_hat[:, i]
    gain_l = case.run.gain_l[:, i]
    truth = case.sim.theta_true
    fig, axes = plt.subplots(5, 1, figsize=(9, 12), sharex=True)
    for ax, block, sl in zip(axes, BLOCKS, BLOCK_SLICES):
        for j in range(sl.start, sl.stop):
            (line,) = ax.plot(
                t, theta[:, j], linewidth=1.0, label=PARAMETER_NAMES[j].split('.')[1]
            )
            ax.axhline(truth[j], color=line.get_color(), linestyle=':', linewidth=1.0)
        ax.set_title(f'{block.name} block (dotted: true hover linearization)', loc='left',
                     fontsize=10)  # fmt: skip
        ax.grid(True, alpha=0.3)
        ax.legend(ncol=5, fontsize=7, loc='upper right')
        ax.set_yscale('symlog', linthresh=1.0)
    for j, name in enumerate(STATE_NAMES):
        axes[-1].plot(t, gain_l[:, j], linewidth=1.0, label=STATE_LABELS[name])
    axes[-1].set_title('observer gains L', loc='left', fontsize=10)
    axes[-1].set_ylabel('L [1/s]')
    axes[-1].grid(True, alpha=0.3)
    axes[-1].legend(ncol=6, fontsize=7, loc='upper left')
    axes[-1].set_xlabel('t [s]')
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def paper_figures(position: PaperCase, out_dir: Path) -> list[Path]:
    """Figures 6, 7, 8, 10 and 11 of the paper from the position-control case."""
    out_dir.mkdir(parents=True, exist_ok=True)
    return [
        error_figure(
            position, False, ('position', 'angles'),
            'Fig. 6: position and attitude errors, CLOE vs CLOE-SM (disturbance-free)',
            out_dir / 'fig6_errors_disturbance_free.png',
        ),
        error_figure(
            position, False, ('velocity', 'rates'),
            'Fig. 7: velocity and angular-rate errors, CLOE vs CLOE-SM (disturbance-free)',
            out_dir / 'fig7_velocity_errors.png',
        ),
        error_figure(
            position, True, ('position', 'angles'),
            'Fig. 8: position and attitude errors, CLOE vs CLOE-SM (with disturbances)',
            out_dir / 'fig8_errors_disturbance.png',
        ),
        parameter_figure(
            position, 'cloe', True,
            f'Fig. 10: identified parameters, CLOE ({position.run.t[-1]:.0f} s, disturbances)',
            out_dir / 'fig10_parameters_cloe.png',
        ),
        parameter_figure(
            position, 'cloe_sm', True,
            f'Fig. 11: identified parameters, CLOE-SM ({position.run.t[-1]:.0f} s, disturbances)',
            out_dir / 'fig11_parameters_cloe_sm.png',
        ),
    ]  # fmt: skip


def trajectory_figure(case: PaperCase, path: Path) -> Path:
    """Fig. 12-like: the trajectory-control flight (top view and time series) with disturbances."""
    i = case.index(True, 'cloe_sm')
    zeta = case.sim.zeta[:, 1]
    ref = case.sim.reference[:, 1]
    sl = _decimate(len(case.sim.t))
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5))
    ax0.plot(ref[sl, 0], ref[sl, 1], 'r-', linewidth=1.0, label='reference')
    ax0.plot(zeta[sl, 0], zeta[sl, 4], 'b-', linewidth=1.0, label='quadrotor')
    est = case.run.zeta_hat[:, i]
    ax0.plot(est[:, 0], est[:, 4], 'k:', linewidth=1.0, label='CLOE-SM estimate')
    ax0.set_xlabel('x [m]')
    ax0.set_ylabel('y [m]')
    ax0.set_aspect('equal', adjustable='datalim')
    ax0.legend(fontsize=8)
    ax0.grid(True, alpha=0.3)
    for c, (idx, name) in enumerate(((0, 'x'), (4, 'y'), (10, 'z'))):
        ax1.plot(case.sim.t[sl], zeta[sl, idx], color=COLORS[c], linewidth=1.0, label=name)
        ax1.plot(case.sim.t[sl], ref[sl, (0, 1, 3)[c]], '--', color=COLORS[c], linewidth=0.8)
    ax1.set_xlabel('t [s]')
    ax1.set_ylabel('position [m] (dashed: reference)')
    ax1.legend(fontsize=8)
    ax1.grid(True, alpha=0.3)
    fig.suptitle('Fig. 12: trajectory control (with disturbances)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
