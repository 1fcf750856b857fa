"""Figures as PNG files: the paper reproduction's (Figures 6-8, 10-12), and the flight figures of
``cloe demo`` and ``cloe report``."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FuncFormatter, MaxNLocator

from cloe_ros.core.experiments import PaperCase
from cloe_ros.core.model import BLOCK_SLICES, BLOCKS, PARAMETER_NAMES, STATE_NAMES, SUBSYSTEMS

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


# -- figures of a recorded flight (`cloe demo`, `cloe report`) ----------------------------------

OUTPUT_PALETTE = ('tab:blue', 'tab:orange', 'tab:green', 'tab:red', 'tab:purple', 'tab:brown')
#: Line styles telling outputs apart where colours name something else (dotted is the truth).
OUTPUT_STYLES = ('-', '--', '-.')
PARAMETER_COLORS = ('tab:blue', 'tab:orange', 'tab:green', 'tab:red', 'tab:purple')
MEASURED_COLOR = 'black'
REFERENCE_COLOR = '0.6'
#: Error figures show |e(t)| thin and its moving RMS over this window thick, s.
RMS_WINDOW_S = 1.0
#: At most this many predicted paths are drawn on the path figure.
MAX_PREDICTED_PATHS = 12


def _output_colors(names) -> dict[str, str]:
    return {n: OUTPUT_PALETTE[i % len(OUTPUT_PALETTE)] for i, n in enumerate(names)}


def _stride(n: int, max_points: int = 4000) -> slice:
    """Every k-th sample so that at most ``max_points`` are drawn."""
    return slice(None, None, max(1, -(-n // max_points)))


def _moving_rms(t: np.ndarray, y: np.ndarray, window: float) -> np.ndarray:
    """RMS of ``y`` over a centred window of ``window`` seconds, at every sample."""
    c = np.concatenate([[0.0], np.cumsum(y * y)])
    lo = np.searchsorted(t, t - window / 2, side='left')
    hi = np.searchsorted(t, t + window / 2, side='right')
    return np.sqrt((c[hi] - c[lo]) / np.maximum(hi - lo, 1))


def _log_limits(values: list[np.ndarray]) -> tuple[float, float] | None:
    """y-limits of a log axis that show the bulk of ``values``: an exact zero or a single tiny
    sample (the estimate's first step equals the measurement) must not stretch the axis."""
    v = np.concatenate([np.ravel(a) for a in values]) if values else np.zeros(0)
    v = v[np.isfinite(v) & (v > 0)]
    if not len(v):
        return None
    return float(np.percentile(v, 0.5)) / 2.0, float(v.max()) * 2.0


def _break_jumps(points: np.ndarray, factor: float = 20.0, min_jump: float = 0.05) -> np.ndarray:
    """``points`` (N, d) with a NaN row where consecutive points jump (a setpoint switched), so a
    line plot does not draw the jump."""
    if len(points) < 3:
        return points
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    threshold = max(factor * float(np.median(d)), min_jump)
    idx = np.nonzero(d > threshold)[0] + 1
    return np.insert(points.astype(float), idx, np.nan, axis=0)


def _with_state(vehicle, names) -> list[str]:
    return [
        n
        for n in names
        if n in vehicle.outputs
        and vehicle.outputs[n].state is not None
        and len(vehicle.outputs[n].state)
    ]


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def flight_errors_figure(vehicle, names: dict[str, str], path: Path) -> Path:
    """Norms of the estimation error per subsystem over time, one colour per output.

    Against the simulator's ground truth when the bag has it (then the measurement's own error is
    drawn in grey for comparison), else against the measurements. Thin: ``|e(t)|``; thick: its
    moving RMS over ``RMS_WINDOW_S``.
    """
    from cloe_ros.cli.analysis import state_errors

    colors = _output_colors(names)
    t0 = vehicle.odom.t_ns[0]
    has_truth = vehicle.ground_truth is not None
    truth = vehicle.ground_truth if has_truth else vehicle.odom
    series = []  # (label, color, t, err)
    if has_truth:
        err, t_ns = state_errors(vehicle.odom, truth)
        if np.any(err):  # a noise-free simulation measures the truth: nothing to draw
            series.append(('measurement (odom)', '0.55', (t_ns - t0) * 1e-9, err))
    for name in _with_state(vehicle, names):
        err, t_ns = state_errors(vehicle.outputs[name].state, truth)
        series.append((names[name], colors[name], (t_ns - t0) * 1e-9, err))
    fig, axes = plt.subplots(4, 1, figsize=(10, 10.5), sharex=True, layout='constrained')
    starts = [s[2][0] for s in series if len(s[2]) and s[0] != 'measurement (odom)']
    for ax, (group, idx) in zip(axes, SUBSYSTEMS.items()):
        plotted = []
        for label, color, t, err in series:
            if not len(t):
                continue
            norm = np.linalg.norm(err[:, list(idx)], axis=1)
            sl = _stride(len(t))
            ax.plot(t[sl], norm[sl], color=color, linewidth=0.6, alpha=0.35)
            rms = _moving_rms(t, norm, RMS_WINDOW_S)
            ax.plot(t[sl], rms[sl], color=color, linewidth=1.7, label=label)
            plotted += [norm[sl], rms[sl]]
        ax.set_yscale('log')
        limits = _log_limits(plotted)
        if limits:
            ax.set_ylim(*limits)
        ax.set_ylabel(f'|{group} error| [{UNITS[group]}]')
        names_text = ', '.join(STATE_NAMES[i] for i in idx)
        ax.set_title(f'{group} ({names_text})', loc='left', fontsize=9)
        ax.grid(True, which='major', alpha=0.3)
    if starts:
        axes[-1].set_xlim(min(starts), max(s[2][-1] for s in series if len(s[2])))
    axes[-1].set_xlabel('t [s] from the first odometry message')
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:
        fig.legend(
            handles,
            labels,
            loc='outside lower center',
            ncol=min(len(labels), 4),
            fontsize=9,
            frameon=False,
        )
    else:
        axes[0].text(
            0.5,
            0.5,
            'no inference output to score',
            transform=axes[0].transAxes,
            ha='center',
            va='center',
        )
    against = 'the simulator ground truth' if has_truth else 'the measurements (odom)'
    fig.suptitle(
        f'{vehicle.namespace or "/"}: estimation error against {against}\n'
        f'thin: |e(t)|, thick: {RMS_WINDOW_S:g} s moving RMS',
        fontsize=11,
    )
    return _save(fig, path)


def flight_states_figure(vehicle, names: dict[str, str], path: Path) -> Path:
    """Position and attitude over time: reference, measured and inferred."""
    colors = _output_colors(names)
    t0 = vehicle.odom.t_ns[0]
    panels = (
        ('x', 0, 0, 'm', 1.0),
        ('y', 4, 1, 'm', 1.0),
        ('z', 10, 3, 'm', 1.0),
        ('pitch θ', 2, None, 'deg', np.degrees(1.0)),
        ('roll φ', 6, None, 'deg', np.degrees(1.0)),
        ('yaw ψ', 8, 2, 'deg', np.degrees(1.0)),
    )
    fig, axes = plt.subplots(3, 2, figsize=(12, 8), sharex=True, layout='constrained')
    t_meas = (vehicle.odom.t_ns - t0) * 1e-9
    sm = _stride(len(t_meas))
    t_ref = (vehicle.reference.t_ns - t0) * 1e-9
    sr = _stride(len(t_ref))
    for k, (label, i, j, unit, scale) in enumerate(panels):
        ax = axes[k % 3, k // 3]
        if j is not None and len(t_ref):
            ax.plot(
                t_ref[sr],
                scale * vehicle.reference.values[sr, j],
                color=REFERENCE_COLOR,
                linewidth=1.2,
                drawstyle='steps-post',
                label='reference',
            )
        ax.plot(
            t_meas[sm],
            scale * vehicle.odom.values[sm, i],
            color=MEASURED_COLOR,
            linewidth=1.0,
            label='measured',
        )
        for name in _with_state(vehicle, names):
            st = vehicle.outputs[name].state
            t = (st.t_ns - t0) * 1e-9
            s = _stride(len(t))
            ax.plot(
                t[s],
                scale * st.values[s, i],
                '--',
                color=colors[name],
                linewidth=1.2,
                label=f'{names[name]} inferred',
            )
        ax.set_ylabel(f'{label} [{unit}]')
        ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel('t [s]')
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(
        handles,
        labels,
        loc='outside lower center',
        ncol=len(labels),
        fontsize=9,
        frameon=False,
    )
    fig.suptitle(f'{vehicle.namespace or "/"}: position and attitude', fontsize=11)
    return _save(fig, path)


def model_columns(output) -> list[int] | None:
    """Columns of ``model.theta.*`` in an output's parameters, in ``PARAMETER_NAMES`` order; None
    when the output has none (older bags) or the model never differs from Theta_hat (the paper's
    algorithms run on their own estimate)."""
    index = {label: i for i, label in enumerate(output.labels)}
    try:
        columns = [index[f'model.theta.{name}'] for name in PARAMETER_NAMES]
    except KeyError:
        return None
    values = output.parameters.values
    if values.shape[1] != len(output.labels) or np.array_equal(
        values[:, columns], values[:, : len(PARAMETER_NAMES)], equal_nan=True
    ):
        return None
    return columns


def flight_parameters_figure(vehicle, names: dict[str, str], path: Path) -> Path | None:
    """The 16 identified parameters over time per block (symlog axis), the truth dotted in the
    same colour when the bag has it; outputs told apart by line style. None without parameters."""
    have = [
        n
        for n in names
        if n in vehicle.outputs
        and vehicle.outputs[n].parameters is not None
        and len(vehicle.outputs[n].parameters)
    ]
    if not have:
        return None
    t0 = vehicle.odom.t_ns[0]
    truth = vehicle.true_parameters
    models = {n: model_columns(vehicle.outputs[n]) for n in have}
    fig, axes = plt.subplots(4, 1, figsize=(11, 12), sharex=True, layout='constrained')
    for ax, block, sl in zip(axes, BLOCKS, BLOCK_SLICES):
        for j in range(sl.start, sl.stop):
            color = PARAMETER_COLORS[j - sl.start]
            for k, name in enumerate(have):
                par = vehicle.outputs[name].parameters
                t = (par.t_ns - t0) * 1e-9
                s = _stride(len(t))
                if models[name] is not None:
                    ax.plot(t[s], par.values[s, models[name][j]], '-', color=color, alpha=0.3,
                            linewidth=4.0, solid_capstyle='butt')  # fmt: skip
                ax.plot(
                    t[s],
                    par.values[s, j],
                    OUTPUT_STYLES[k % len(OUTPUT_STYLES)],
                    color=color,
                    linewidth=1.1,
                    label=PARAMETER_NAMES[j].split('.')[1] if k == 0 else None,
                )
            if truth is not None:
                ax.axhline(truth[j], color=color, linestyle=':', linewidth=1.4)
        ax.set_yscale('symlog', linthresh=1.0)
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:g}'))
        ax.set_title(f'{block.name} block', loc='left', fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0), frameon=False)
    axes[-1].set_xlabel('t [s]')
    keys = [
        plt.Line2D(
            [],
            [],
            color='k',
            linestyle=OUTPUT_STYLES[k % len(OUTPUT_STYLES)],
            label=f'{names[n]} ' + r'$\hat\Theta$',
        )
        for k, n in enumerate(have)
    ]
    keys += [
        plt.Line2D([], [], color='k', alpha=0.3, linewidth=4.0,
                   label=f'{names[n]}: model in use (observer, predictions)')
        for n in have if models[n] is not None
    ]  # fmt: skip
    if truth is not None:
        keys.append(
            plt.Line2D([], [], color='k', linestyle=':', label='true (hover linearization)')
        )
    fig.legend(
        handles=keys,
        loc='outside lower center',
        ncol=len(keys),
        fontsize=9,
        frameon=False,
    )
    fig.suptitle(
        f'{vehicle.namespace or "/"}: identified parameters ' + r'$\hat\Theta$' + ' (symlog axis)',
        fontsize=11,
    )
    return _save(fig, path)


def flight_parameter_error_figure(vehicle, names: dict[str, str], path: Path) -> Path | None:
    """Relative parameter error per block over time (needs the true parameters); None otherwise."""
    from cloe_ros.core.metrics import parameter_error

    truth = vehicle.true_parameters
    have = [
        n
        for n in names
        if n in vehicle.outputs
        and vehicle.outputs[n].parameters is not None
        and len(vehicle.outputs[n].parameters)
    ]
    if truth is None or not have:
        return None
    t0 = vehicle.odom.t_ns[0]
    fig, ax = plt.subplots(figsize=(10, 4.8), layout='constrained')
    top = 0.0
    for k, name in enumerate(have):
        par = vehicle.outputs[name].parameters
        t = (par.t_ns - t0) * 1e-9
        errs = parameter_error(par.values[:, : len(truth)], truth)
        for c, (block, err) in enumerate(errs.items()):
            color = 'k' if block == 'all' else PARAMETER_COLORS[c]
            ax.plot(
                t,
                100 * err,
                OUTPUT_STYLES[k % len(OUTPUT_STYLES)],
                color=color,
                linewidth=1.8 if block == 'all' else 1.1,
                label=block if k == 0 else None,
            )
            top = max(top, float(np.nanmax(100 * err)))
    ax.axhline(100.0, color='0.4', linewidth=0.8)
    ax.annotate(
        r'100 %: no better than $\hat\Theta = 0$',
        (0.005, 100.0),
        xycoords=('axes fraction', 'data'),
        fontsize=8,
        color='0.3',
        va='bottom',
    )
    if top > 300.0:
        ax.set_yscale('log')
    else:
        ax.set_ylim(0, max(110.0, 1.05 * top))
    ax.set_ylabel(r'$\|\hat\Theta_b - \Theta_b\| \,/\, \|\Theta_b\|$ [%]')
    ax.set_xlabel('t [s]')
    ax.grid(True, alpha=0.3)
    handles = ax.get_legend_handles_labels()[0]
    handles += [
        plt.Line2D(
            [], [], color='k', linestyle=OUTPUT_STYLES[k % len(OUTPUT_STYLES)], label=names[n]
        )
        for k, n in enumerate(have)
        if len(have) > 1
    ]
    ax.legend(
        handles=handles, fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0), frameon=False
    )
    ax.set_title(
        f'{vehicle.namespace or "/"}: parameter error per block against the truth', fontsize=11
    )
    return _save(fig, path)


def _zoom_target(vehicle, names) -> tuple[int, np.ndarray, np.ndarray, str] | None:
    """Where the first inferred path is farthest (horizontally) from the true one (simulation) or
    the measured one; without outputs, where the measured path is farthest from the reference.
    Returns the time (ns), the two positions (3,) and what they are."""
    from cloe_ros.cli.analysis import interpolate

    outs = _with_state(vehicle, names)
    actual = vehicle.ground_truth if vehicle.ground_truth is not None else vehicle.odom
    actual_label = 'true' if vehicle.ground_truth is not None else 'measured'
    if outs:
        st = vehicle.outputs[outs[0]].state
        t_ns = st.t_ns
        a = interpolate(actual, t_ns)[:, [0, 4, 10]]
        b = st.values[:, [0, 4, 10]]
        what = f'largest gap {actual_label} / {names[outs[0]]} inferred'
    elif len(vehicle.reference) > 1:
        t_ns = vehicle.odom.t_ns
        a = vehicle.odom.values[:, [0, 4, 10]]
        b = interpolate(vehicle.reference, t_ns)[:, [0, 1, 3]]
        what = 'largest tracking error measured / reference'
    else:
        return None
    d = np.linalg.norm(a[:, :2] - b[:, :2], axis=1)
    d = np.where(np.isfinite(d), d, -1.0)
    if not len(d) or d.max() <= 0:
        return None
    k = int(np.argmax(d))
    return int(t_ns[k]), a[k], b[k], what


def flight_path_figure(vehicle, names: dict[str, str], path: Path) -> Path:
    """Top view, a zoom on where the inferred path is farthest from the actual one, and the 3-D
    path: reference, measured (and true, in a simulation), inferred and some predicted paths."""
    colors = _output_colors(names)
    t0 = vehicle.odom.t_ns[0]
    meas = vehicle.odom.values[:, [0, 4, 10]]
    truth = None if vehicle.ground_truth is None else vehicle.ground_truth.values[:, [0, 4, 10]]
    ref = _break_jumps(vehicle.reference.values[:, [0, 1, 3]]) if len(vehicle.reference) else None
    outs = _with_state(vehicle, names)
    has_prediction = any(vehicle.outputs[n].prediction is not None for n in outs)
    fig = plt.figure(figsize=(16, 6.2), layout='constrained')
    grid = fig.add_gridspec(1, 3, width_ratios=(1.0, 1.0, 1.2))
    ax_top = fig.add_subplot(grid[0])
    ax_zoom = fig.add_subplot(grid[1])
    ax3 = fig.add_subplot(grid[2], projection='3d')

    def draw(ax, dims: tuple[int, ...]) -> None:
        def line(points, *args, **kwargs):
            return ax.plot(*points.T[list(dims)], *args, **kwargs)

        if ref is not None:
            line(ref, color=REFERENCE_COLOR, linewidth=1.2, label='reference')
        # in a simulation the (noisy) measurement is secondary to the truth
        line(
            meas[_stride(len(meas))],
            color=MEASURED_COLOR if truth is None else '0.3',
            linewidth=1.0 if truth is None else 0.6,
            label='measured',
        )
        if truth is not None:
            line(
                truth[_stride(len(truth))],
                color='tab:olive',
                linewidth=1.4,
                label='true (simulation)',
            )
        for name in outs:
            est = vehicle.outputs[name].state.values[:, [0, 4, 10]]
            line(
                est[_stride(len(est))],
                '--',
                color=colors[name],
                linewidth=1.3,
                label=f'{names[name]} inferred',
            )
            pred = vehicle.outputs[name].prediction
            if pred is None or not len(pred.t_ns):
                continue
            chosen = np.unique(np.linspace(0, len(pred.t_ns) - 1, MAX_PREDICTED_PATHS).astype(int))
            first = True
            for i in chosen:
                p = pred.positions[i]
                p = p[np.all(np.isfinite(p), axis=1)]
                if not len(p):
                    continue
                line(
                    p,
                    ':',
                    color=colors[name],
                    linewidth=1.8,
                    label=f'{names[name]} predicted' if first else None,
                )
                line(p[:1], 'o', color=colors[name], markersize=3)
                first = False
        line(meas[:1], '^', color='tab:green', markersize=8, label='start')
        line(meas[-1:], 's', color='tab:red', markersize=7, label='end')

    draw(ax_top, (0, 1))
    ax_top.set_aspect('equal', adjustable='datalim')
    ax_top.set_title('top view', fontsize=10)
    span = np.nanmax(meas, axis=0) - np.nanmin(meas, axis=0)
    horizontal = max(span[0], span[1], 1e-3)
    target = _zoom_target(vehicle, names)
    half = 0.0
    if target is not None:
        t_ns, a, b, what = target
        dist = float(np.linalg.norm(a[:2] - b[:2]))
        centre, half = 0.5 * (a + b), max(3.0 * dist, 0.05)
    if target is not None and 2 * half < 0.5 * horizontal:
        draw(ax_zoom, (0, 1))
        ax_zoom.plot([a[0], b[0]], [a[1], b[1]], '-', color='tab:red', linewidth=1.0)
        ax_zoom.plot(
            [a[0], b[0]], [a[1], b[1]], 'o', color='tab:red', markersize=5, markerfacecolor='none'
        )
        ax_zoom.set_xlim(centre[0] - half, centre[0] + half)
        ax_zoom.set_ylim(centre[1] - half, centre[1] + half)
        ax_zoom.set_aspect('equal', adjustable='box')
        ax_zoom.set_title(
            f'zoom: {what}\n({100 * dist:.1f} cm at t = {(t_ns - t0) * 1e-9:.1f} s, red circles)',
            fontsize=10,
        )
        ax_zoom.set_ylabel('y [m]')
        ax_top.add_patch(
            plt.Rectangle(
                (centre[0] - half, centre[1] - half),
                2 * half,
                2 * half,
                fill=False,
                edgecolor='tab:red',
                linewidth=1.0,
            )
        )
    else:  # the top view shows the gaps already (or the flight is mostly vertical): side view
        draw(ax_zoom, (0, 2))
        ax_zoom.set_title('side view', fontsize=10)
        ax_zoom.set_ylabel('z [m]')
    ax_top.set_ylabel('y [m]')
    for ax in (ax_top, ax_zoom):
        ax.set_xlabel('x [m]')
        ax.grid(True, alpha=0.3)
    draw(ax3, (0, 1, 2))
    # equal scales where the flight allows it, but no axis squeezed below a third of the largest
    box = np.maximum(np.nan_to_num(span), 1e-3)
    ax3.set_box_aspect(tuple(np.maximum(box, box.max() / 3.0)), zoom=0.85)
    for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
        axis.set_major_locator(MaxNLocator(4))
    ax3.set_xlabel('x [m]')
    ax3.set_ylabel('y [m]')
    ax3.set_zlabel('z [m]')
    ax3.set_title('3-D', fontsize=10)
    handles, labels = ax_top.get_legend_handles_labels()
    fig.legend(
        handles, labels, loc='outside lower center', ncol=len(labels), fontsize=9, frameon=False
    )
    what = 'measured, inferred' + (', predicted' if has_prediction else '')
    fig.suptitle(f'{vehicle.namespace or "/"}: path ({what})', fontsize=11)
    return _save(fig, path)


def prediction_figure(
    horizons, results: dict[str, dict[str, list[float]]], path: Path, title: str
) -> Path:
    """Prediction RMSE against the horizon: per output the identified model (solid) beside the
    constant-velocity (dashed) and hold-position (dotted) baselines.

    Args:
        horizons: Horizons, s.
        results: ``{output label: {'model' | 'constant velocity' | 'hold position': RMSE per
            horizon (m, NaN where none)}}``.
        path: PNG file to write.
        title: Figure title.

    """
    colors = _output_colors(results)
    styles = {'model': ('-', 'o'), 'constant velocity': ('--', 's'), 'hold position': (':', 'x')}
    fig, ax = plt.subplots(figsize=(8.5, 4.8), layout='constrained')
    for label, rows in results.items():
        for kind, (style, marker) in styles.items():
            values = np.asarray(rows.get(kind, [np.nan] * len(horizons)), dtype=float)
            if not np.any(np.isfinite(values)):
                continue
            ax.plot(
                horizons,
                values,
                style,
                marker=marker,
                color=colors[label],
                linewidth=2.0 if kind == 'model' else 1.2,
                label=f'{label}: {kind}',
            )
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xticks(list(horizons))
    ax.set_xticklabels([f'{h:g}' for h in horizons])
    ax.minorticks_off()
    ax.set_xlabel('horizon [s]')
    ax.set_ylabel('position RMSE [m]')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(title, fontsize=11)
    return _save(fig, path)


def flight_figures(
    vehicle,
    out_dir: Path,
    outputs: dict[str, str] | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[Path]:
    """Errors, states, parameters (and their error when the truth is known) and paths of one
    vehicle of a bag (see :mod:`cloe_ros.io.dataset`) as PNG files.

    Args:
        vehicle: A :class:`cloe_ros.io.dataset.VehicleData`.
        out_dir: Folder for the PNG files (``<vehicle>_errors.png``, ``_states``, ``_parameters``,
            ``_parameter_error``, ``_path``; the vehicle is ``vehicle`` when un-namespaced).
        outputs: Output namespaces to show and their labels (all found by default).
        progress: Called with the number of figures done (of 5) after each one.

    """
    out_dir.mkdir(parents=True, exist_ok=True)
    names = outputs or {n: o.label for n, o in vehicle.outputs.items()}
    tag = vehicle.namespace.strip('/').replace('/', '_') or 'vehicle'
    figures = (
        (flight_errors_figure, 'errors'),
        (flight_states_figure, 'states'),
        (flight_parameters_figure, 'parameters'),
        (flight_parameter_error_figure, 'parameter_error'),
        (flight_path_figure, 'path'),
    )
    paths = []
    for done, (figure, kind) in enumerate(figures, start=1):
        paths.append(figure(vehicle, names, out_dir / f'{tag}_{kind}.png'))
        if progress is not None:
            progress(done)
    return [p for p in paths if p is not None]
