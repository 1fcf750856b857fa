"""The paper's experiments (§6): simulate a scenario, run CLOE and CLOE-SM on it, score them.

Everything here is deterministic: the simulator is noise-free unless asked, and the estimators see
the simulator's samples at its own rate (1 kHz by default, as in the paper).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cloe_ros.core.estimator import CloeEstimator, EstimatorConfig
from cloe_ros.core.metrics import parameter_error, rmse_norm, subsystem_itae, subsystem_rmse
from cloe_ros.core.simulator import (
    NoDisturbance,
    PaperDisturbance,
    ProbingSignal,
    QuadrotorSimulator,
    SimulationResult,
    get_scenario,
)

Progress = Callable[[float], None]

#: The paper's published values (CoppeliaSim; absolute values are not comparable, orderings are).
PAPER_TABLES = {
    'position': {
        'rmse': {'cloe': 0.519, 'cloe_sm': 0.367},
        'itae': {
            'position': {'cloe': 0.983, 'cloe_sm': 0.58},
            'velocity': {'cloe': 1.946, 'cloe_sm': 1.378},
            'angles': {'cloe': 0.594, 'cloe_sm': 0.105},
            'rates': {'cloe': 1.05, 'cloe_sm': 1.24},
        },
    },
    'trajectory': {
        'rmse': {'cloe': 0.58, 'cloe_sm': 0.42},
        'itae': {
            'position': {'cloe': 14.567, 'cloe_sm': 11.51},
            'velocity': {'cloe': 17.17, 'cloe_sm': 15.05},
            'angles': {'cloe': 5.534, 'cloe_sm': 5.027},
            'rates': {'cloe': 3.278, 'cloe_sm': 2.91},
        },
    },
}


@dataclass
class EstimateRun:
    """Estimator outputs over a run.

    Attributes:
        t: Times (T,), s.
        error: ``zeta - zeta_hat`` (T, N, 12) at every step.
        zeta_hat: Estimates (T_rec, N, 12) at the recorded times ``t_rec``.
        theta_hat: Parameters (T_rec, N, 16).
        gain_l: Observer gains (T_rec, N, 12).
        t_rec: Recorded times (T_rec,), every ``record_every``-th step.

    """

    t: np.ndarray
    error: np.ndarray
    zeta_hat: np.ndarray
    theta_hat: np.ndarray
    gain_l: np.ndarray
    t_rec: np.ndarray


def run_estimators(
    configs: Sequence[EstimatorConfig],
    t: np.ndarray,
    measured: np.ndarray,
    reference: np.ndarray,
    record_every: int = 1,
    progress: Progress | None = None,
) -> EstimateRun:
    """Run one estimator per config over the samples, all in one batch.

    Args:
        configs: N estimator configurations.
        t: Sample times (T,), uniformly spaced, s.
        measured: Measurements (T, N, 12) or (T, 12) (shared by all estimators).
        reference: References (T, N, 4) or (T, 4); the step to ``t_k`` uses ``reference[k]``, the
            reference at the measurement's time (as the engine does).
        record_every: Keep estimates and parameters every this many steps.
        progress: Called with the fraction done about a hundred times.

    """
    n = len(configs)
    measured = np.broadcast_to(
        measured if measured.ndim == 3 else measured[:, None], (len(t), n, 12)
    )
    reference = np.broadcast_to(
        reference if reference.ndim == 3 else reference[:, None], (len(t), n, 4)
    )
    h = float(t[1] - t[0])
    est = CloeEstimator(list(configs), measured[0, 0])
    est.zeta_hat[:] = measured[0]
    n_rec = (len(t) - 1) // record_every + 1
    run = EstimateRun(
        t=t,
        error=np.empty((len(t), n, 12)),
        zeta_hat=np.empty((n_rec, n, 12)),
        theta_hat=np.empty((n_rec, n, 16)),
        gain_l=np.empty((n_rec, n, 12)),
        t_rec=t[::record_every][:n_rec],
    )
    every = max(1, len(t) // 100)
    for k in range(len(t)):
        if k:
            est.step(measured[k], reference[k], h)
        np.subtract(measured[k], est.zeta_hat, out=run.error[k])
        if k % record_every == 0:
            j = k // record_every
            run.zeta_hat[j] = est.zeta_hat
            run.theta_hat[j] = est.theta_hat
            run.gain_l[j] = est.gain_l
        if progress is not None and k % every == 0:
            progress(k / len(t))
    return run


@dataclass
class PaperCase:
    """One scenario of the paper, run with and without disturbances, CLOE and CLOE-SM.

    Vehicles (axis N) are ordered ``(disturbance, algorithm)`` as in :attr:`labels`.
    """

    scenario: str
    sim: SimulationResult
    run: EstimateRun
    labels: tuple[tuple[bool, str], ...]
    table_duration: float

    def index(self, disturbed: bool, algorithm: str) -> int:
        return self.labels.index((disturbed, algorithm))

    def table(self) -> dict[str, dict]:
        """RMSE of the norm, per-subsystem RMSE and ITAE over ``[0, table_duration]``, and the
        parameter error at the end of the run, for every (disturbance, algorithm)."""
        mask = self.run.t <= self.table_duration + 1e-9
        t = self.run.t[mask]
        err = self.run.error[mask]
        rmse = rmse_norm(err)
        sub_rmse = subsystem_rmse(err)
        sub_itae = subsystem_itae(t, err)
        perr = parameter_error(self.run.theta_hat[-1], self.sim.theta_true)
        out = {}
        for i, key in enumerate(self.labels):
            out[key] = {
                'rmse': float(rmse[i]),
                'rmse_sub': {k: float(v[i]) for k, v in sub_rmse.items()},
                'itae': {k: float(v[i]) for k, v in sub_itae.items()},
                'param_error': {k: float(v[i]) for k, v in perr.items()},
                'param_time': float(self.run.t[-1]),
            }
        return out


def run_paper_case(
    scenario: str,
    duration: float | None = None,
    table_duration: float | None = None,
    dt: float = 1e-3,
    probing: ProbingSignal | None = None,
    estimator_overrides: dict | None = None,
    record_every: int = 10,
    progress: Callable[[str, float], None] | None = None,
) -> PaperCase:
    """Simulate ``scenario`` with and without the §6.1 disturbances and run CLOE and CLOE-SM.

    Args:
        scenario: ``'position'`` or ``'trajectory'`` (any known scenario works).
        duration: Simulated time, s (the scenario's by default; the paper extends the position
            case to 200 s for its parameter figures).
        table_duration: Window of the error metrics, s (the scenario's length by default).
        dt: Simulation and estimation step, s.
        probing: Probing signal (the documented default if None).
        estimator_overrides: Keyword arguments for every :class:`EstimatorConfig`.
        record_every: Decimation of the recorded estimates and parameters.
        progress: ``progress(stage, fraction)``.

    """
    scen = get_scenario(scenario)
    duration = scen.duration if duration is None else duration
    table_duration = min(scen.duration, duration) if table_duration is None else table_duration
    sim = QuadrotorSimulator(
        scen,
        n_vehicles=2,
        disturbance=[NoDisturbance(), PaperDisturbance()],
        probing=ProbingSignal() if probing is None else probing,
        dt=dt,
    )
    sim_result = sim.run(
        duration, progress=(lambda f: progress(f'simulate {scenario}', f)) if progress else None
    )
    labels = tuple((dist, alg) for dist in (False, True) for alg in ('cloe', 'cloe_sm'))
    overrides = {'l_initial': 0.0, **(estimator_overrides or {})}
    configs = [EstimatorConfig(alg, **overrides) for _, alg in labels]
    vehicle = [1 if dist else 0 for dist, _ in labels]
    run = run_estimators(
        configs,
        sim_result.t,
        sim_result.measured[:, vehicle],
        sim_result.reference[:, vehicle],
        record_every=record_every,
        progress=(lambda f: progress(f'estimate {scenario}', f)) if progress else None,
    )
    return PaperCase(scenario, sim_result, run, labels, table_duration)
