"""Scoring inference outputs read from a bag against the truth (simulation) or the measurements."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cloe_ros.core import evaluation
from cloe_ros.core.kinematics import wrap_angle
from cloe_ros.core.metrics import parameter_error, rmse_norm, subsystem_itae, subsystem_rmse
from cloe_ros.core.model import N_PARAMS
from cloe_ros.io.dataset import Series, VehicleData


def interpolate(series: Series, t_ns: np.ndarray) -> np.ndarray:
    """``series`` linearly interpolated at ``t_ns`` (NaN outside its time span); the stamps are
    taken relative to the series' first, so that nanoseconds keep their precision as floats."""
    t_rel = (series.t_ns - series.t_ns[0]).astype(float)
    q = (np.asarray(t_ns) - series.t_ns[0]).astype(float)
    return evaluation.interpolate(t_rel, series.values, q)


def state_errors(estimate: Series, reference: Series) -> tuple[np.ndarray, np.ndarray]:
    """``reference - estimate`` (T, 12) at the estimate's stamps inside the reference's span, and
    those stamps (ns). Yaw differences are wrapped to [-pi, pi)."""
    ref = interpolate(reference, estimate.t_ns)
    err = ref - estimate.values
    err[:, 8] = wrap_angle(err[:, 8])
    keep = np.all(np.isfinite(err), axis=1)
    return err[keep], estimate.t_ns[keep]


@dataclass
class Score:
    """Paper-style metrics of one inference output."""

    name: str
    against: str  # 'truth' or 'measurement'
    steps: int
    rmse: float
    rmse_sub: dict[str, float]
    itae: dict[str, float]
    param_error: dict[str, float] | None
    duration_s: float


def score_output(vehicle: VehicleData, name: str, t0_ns: int | None = None) -> Score | None:
    """Score ``vehicle.outputs[name]`` against the ground truth when the bag has it, otherwise
    against the measurements; ITAE time counts from ``t0_ns`` (the first odometry by default)."""
    out = vehicle.outputs.get(name)
    if out is None or out.state is None or not len(out.state):
        return None
    truth = vehicle.ground_truth if vehicle.ground_truth is not None else vehicle.odom
    against = 'truth' if vehicle.ground_truth is not None else 'measurement'
    err, t_ns = state_errors(out.state, truth)
    if not len(err):
        return None
    t0 = vehicle.odom.t_ns[0] if t0_ns is None else t0_ns
    t = (t_ns - t0) * 1e-9
    perr = None
    if vehicle.true_parameters is not None and out.parameters is not None and len(out.parameters):
        theta_hat = out.parameters.values[-1, :N_PARAMS]
        perr = {
            k: float(v) for k, v in parameter_error(theta_hat, vehicle.true_parameters).items()
        }
    return Score(
        name=name,
        against=against,
        steps=len(out.state),
        rmse=float(rmse_norm(err)),
        rmse_sub={k: float(v) for k, v in subsystem_rmse(err).items()},
        itae={k: float(v) for k, v in subsystem_itae(t, err).items()},
        param_error=perr,
        duration_s=float(t[-1] - t[0]),
    )


def format_scores(scores: list[Score], paper: dict | None = None) -> str:
    """A table with one column per output (and the paper's values beside, when given)."""
    names = [s.name for s in scores]
    head = f'  {"":<34}' + ''.join(f'{n:>12}' for n in names)
    if paper:
        head += ''.join(f'{"paper " + k:>14}' for k in paper['rmse'])
    lines = [head]

    def row(label, values, paper_values=()):
        text = f'  {label:<34}' + ''.join(f'{v:>12.4g}' if v == v else f'{"-":>12}'
                                          for v in values)  # fmt: skip
        text += ''.join(f'{v:>14.4g}' for v in paper_values)
        lines.append(text)

    row('steps', [s.steps for s in scores])
    row(f'RMSE 12-state norm (vs {scores[0].against})', [s.rmse for s in scores],
        list(paper['rmse'].values()) if paper else ())  # fmt: skip
    for sub in ('position', 'velocity', 'angles', 'rates'):
        row(f'RMSE {sub}', [s.rmse_sub[sub] for s in scores])
    for sub in ('position', 'velocity', 'angles', 'rates'):
        row(f'ITAE {sub}', [s.itae[sub] for s in scores],
            list(paper['itae'][sub].values()) if paper else ())  # fmt: skip
    if any(s.param_error for s in scores):
        for block in ('x_theta', 'y_phi', 'psi', 'z', 'all'):
            row(
                f'parameter error {block} [%]',
                [100 * s.param_error[block] if s.param_error else float('nan') for s in scores],
            )
    return '\n'.join(lines)
