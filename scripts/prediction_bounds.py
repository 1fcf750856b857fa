"""How well *any* position-loop model of the reduced form could predict a recorded flight.

    .venv/bin/python scripts/prediction_bounds.py BAG [BAG ...]

Per axis, the model ``p'' = k_p (p_d + b - p) - k_v p'`` (the reduced closed loop the identifier
falls back on, with a constant offset ``b`` like the engine's offset tracking) is fitted to the
*whole* flight by minimising its own prediction errors, then scored on the same flight:
predictions from the measured state every 0.2 s from 5 s after the first message on, at
0.5/1/2/5 s, in flight (measured altitude above 0.2 m, setpoint above 0.05 m at the issue and at
the horizon time), the reference held or the recorded future reference given
(``reference_plan``). The fit sees the future and scores
itself in-sample: its numbers are a floor for a causal identifier with this model structure, not
something one should expect to reach online. See EVALUATION.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cloe_ros.core.evaluation import HORIZONS
from cloe_ros.io.dataset import load_flight

H = 0.01  # integration step and resampling grid, s
ISSUE_EVERY = 20  # grid steps between predictions (5 Hz, as the engine publishes them)
AXES = {'x': (0, 1, 0), 'y': (4, 5, 1), 'z': (10, 11, 3)}  # position, velocity, reference index


def flight(path: str):
    """The first vehicle's measured state and held reference on a 100 Hz grid, the in-flight
    mask, and the prediction issue indices."""
    data = next(iter(load_flight(path).values()))
    t0 = min(data.odom.t_ns[0], data.reference.t_ns[0])
    t = (data.odom.t_ns - t0) / 1e9
    t_ref = (data.reference.t_ns - t0) / 1e9
    grid = np.arange(t_ref[0], t[-1], H)
    zeta = np.column_stack([np.interp(grid, t, data.odom.values[:, i]) for i in range(12)])
    held = np.searchsorted(t_ref, grid, side='right') - 1
    ref = data.reference.values[np.maximum(held, 0)]
    in_flight = (zeta[:, 10] > 0.2) & (ref[:, 3] > 0.05)
    # from 5 s after the first message on, as `cloe evaluate bag` scores
    issues = np.arange(np.searchsorted(grid, 5.0), len(grid) - 1, ISSUE_EVERY)
    return zeta, ref, in_flight, issues[in_flight[issues]]


def predict(zeta, ref, issues, axis, params, plan: bool) -> np.ndarray:
    """Positions (len(issues), 5 s / H) predicted on one axis."""
    ip, iv, ir = AXES[axis]
    k_p, k_v, offset = params
    p, v = zeta[issues, ip].copy(), zeta[issues, iv].copy()
    n = round(HORIZONS[-1] / H)
    out = np.empty((len(issues), n))
    last = len(ref) - 1
    for j in range(n):
        target = ref[np.minimum(issues + j, last), ir] if plan else ref[issues, ir]
        v += H * (k_p * (target + offset - p) - k_v * v)
        p += H * v
        out[:, j] = p
    return out


def errors(zeta, in_flight, issues, axis, predicted) -> tuple[np.ndarray, np.ndarray]:
    """Prediction errors and where they count (the horizon time in flight and in the record)."""
    k = issues[:, None] + np.arange(1, predicted.shape[1] + 1)[None, :]
    valid = k < len(zeta)
    k = np.minimum(k, len(zeta) - 1)
    valid &= in_flight[k]
    return np.where(valid, predicted - zeta[k, AXES[axis][0]], 0.0), valid


def fit_axis(zeta, ref, in_flight, issues, axis: str, plan: bool):
    """``(k_p, k_v, offset)`` minimising the axis' prediction errors (every 0.1 s of the
    horizon), and the errors of the fitted model."""

    def axis_errors(params):
        predicted = predict(zeta, ref, issues, axis, params, plan)
        return errors(zeta, in_flight, issues, axis, predicted)

    fit = least_squares(lambda params: axis_errors(params)[0][:, 9::10].ravel(), [4.0, 3.2, 0.0],
                        bounds=([0.0, 0.0, -1.0], [400.0, 400.0, 1.0]))  # fmt: skip
    return fit.x, axis_errors(fit.x)


def rmse_at(sq: np.ndarray, valid: np.ndarray) -> list[float]:
    cols = [round(h / H) - 1 for h in HORIZONS]
    return [float(np.sqrt(sq[valid[:, c], c].mean())) for c in cols]


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__)
        return 2
    for path in paths:
        zeta, ref, in_flight, issues = flight(path)
        print(f'{path}: {len(issues)} predictions scored')
        print('  RMSE [m] at ' + ' / '.join(f'{h:g}' for h in HORIZONS) + ' s')
        for plan in (True, False):
            total = 0.0
            for axis in AXES:
                (k_p, k_v, offset), (e, valid) = fit_axis(zeta, ref, in_flight, issues, axis, plan)
                total = total + e**2
                print(f'  {"plan" if plan else "held"} {axis}: k_p {k_p:6.2f}, k_v {k_v:6.2f}, '
                      f'offset {offset:+.3f} m   '
                      + ' / '.join(f'{r:.3f}' for r in rmse_at(e**2, valid)))  # fmt: skip
            print(f'  {"plan" if plan else "held"} all three axes: '
                  + ' / '.join(f'{r:.3f}' for r in rmse_at(total, valid)))  # fmt: skip
        total = 0.0
        for axis, (ip, iv, _) in AXES.items():
            steps = H * np.arange(1, round(HORIZONS[-1] / H) + 1)
            cv = zeta[issues, ip][:, None] + zeta[issues, iv][:, None] * steps[None, :]
            e, valid = errors(zeta, in_flight, issues, axis, cv)
            total = total + e**2
        print('  constant velocity, all three axes: '
              + ' / '.join(f'{r:.3f}' for r in rmse_at(total, valid)))  # fmt: skip
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
