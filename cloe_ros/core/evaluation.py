"""Scoring identification and anticipation: parameter error over time, prediction RMSE per horizon
against the constant-velocity and hold-position baselines (and, in simulation, the true model).

The engine is run exactly as the node runs it (:class:`~cloe_ros.core.engine.VehicleEngine` on
odometry and reference samples), so the numbers describe what a user gets.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cloe_ros.core.engine import NS, EngineConfig, Estimate, VehicleEngine
from cloe_ros.core.identifier import IDENTIFIED, ROW_NAMES
from cloe_ros.core.kinematics import state_to_odometry, yaw_quaternion
from cloe_ros.core.metrics import parameter_error
from cloe_ros.core.model import BLOCKS, PAPER_COUPLING
from cloe_ros.core.prediction import PredictionConfig, Predictor
from cloe_ros.core.samples import OdometrySample, PathSample, PoseSample

#: The horizons every prediction score reports, s: ``cloe evaluate`` (sim, bag, corpus) and
#: ``cloe report``.
HORIZONS = (0.5, 1.0, 2.0, 5.0)
T0_NS = 1_700_000_000 * NS  # an epoch-like origin for simulated stamps


@dataclass
class PredictionScore:
    """Prediction RMSE (m) per horizon of a predictor beside the constant-velocity and
    hold-position baselines from the same start (:func:`score_positions`).

    ``count`` predictions were scored per horizon; ``true_model`` is the RMSE of the true-model
    predictor on the same predictions (simulation) or None. ``withheld``, ``t_from`` and ``t_to``
    describe the window of a run (``cloe evaluate``): predictions withheld, and the issue times
    scored, s."""

    horizons: tuple[float, ...]
    model: np.ndarray
    constant_velocity: np.ndarray
    hold_position: np.ndarray
    true_model: np.ndarray | None
    count: np.ndarray
    withheld: int = 0
    t_from: float = 0.0
    t_to: float = np.inf
    model_per_axis: np.ndarray | None = None  # (horizons, 3): the model's RMSE along x, y, z


def kinematic_baselines(start: np.ndarray, lead: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model-free predictions from states ``start`` (P, 12) at ``lead`` (P, H) s later:
    constant velocity ``p0 + v0 lead`` (world-frame velocity) and hold position ``p0``, positions
    (P, H, 3), m."""
    p0, v0 = start[:, None, [0, 4, 10]], start[:, None, [1, 5, 11]]
    cv = p0 + v0 * lead[..., None]
    return cv, np.broadcast_to(p0, cv.shape).copy()


def rmse_per_horizon(predicted: np.ndarray, actual: np.ndarray, scored: np.ndarray) -> np.ndarray:
    """``sqrt(mean ||predicted - actual||^2)`` per horizon over the predictions ``scored``, m.

    Args:
        predicted, actual: Positions (P, H, 3).
        scored: Which prediction counts at which horizon (P, H); NaN where none does.

    """
    sq = np.sum((predicted - actual) ** 2, axis=-1)
    return np.array([np.sqrt(np.mean(sq[scored[:, j], j])) if scored[:, j].any() else np.nan
                     for j in range(scored.shape[1])])  # fmt: skip


def score_positions(
    horizons: Sequence[float],
    predicted: np.ndarray,
    actual: np.ndarray,
    start: np.ndarray,
    lead: np.ndarray,
    true_predicted: np.ndarray | None = None,
    **window,
) -> PredictionScore:
    """Position RMSE of predictions at each horizon against where the vehicle was, beside the
    baselines from the state each prediction started from: the one scorer of ``cloe evaluate``
    (:func:`score_predictions`) and ``cloe report``.

    Prediction ``i`` counts at horizon ``j`` when ``predicted[i, j]``, ``actual[i, j]`` and
    ``start[i]`` are all finite: NaN marks a pose or an outcome that is missing. The baselines
    predict the same time, ``lead[i, j]`` s after the start: constant velocity
    ``p0 + v0 lead`` (world-frame velocity) and hold position ``p0``.

    Args:
        horizons: Horizons (H,), s.
        predicted: Predicted positions (P, H, 3), world frame, m.
        actual: Where the vehicle was at those times (P, H, 3), m.
        start: The state each prediction started from (P, 12) (model state order).
        lead: Time from each start to each predicted position (P, H), s.
        true_predicted: Positions (P, H, 3) of a second predictor (the true model), scored on
            the same predictions, or None.
        window: ``withheld``, ``t_from``, ``t_to`` of :class:`PredictionScore`.

    """
    horizons = tuple(horizons)
    scored = (np.isfinite(predicted).all(axis=-1) & np.isfinite(actual).all(axis=-1)
              & np.isfinite(start).all(axis=-1)[:, None])  # fmt: skip
    cv, hold = kinematic_baselines(start, lead)
    err2 = (predicted - actual) ** 2
    per_axis = [np.sqrt(np.mean(err2[scored[:, j], j], axis=0)) if scored[:, j].any()
                else np.full(3, np.nan) for j in range(len(horizons))]  # fmt: skip
    return PredictionScore(
        horizons=horizons,
        model=rmse_per_horizon(predicted, actual, scored),
        constant_velocity=rmse_per_horizon(cv, actual, scored),
        hold_position=rmse_per_horizon(hold, actual, scored),
        true_model=None
        if true_predicted is None
        else rmse_per_horizon(true_predicted, actual, scored),
        count=scored.sum(axis=0),
        model_per_axis=np.array(per_axis).reshape(len(horizons), 3),
        **window,
    )


@dataclass
class Run:
    """One algorithm's run: the estimates (decimated) and every prediction issued."""

    algorithm: str
    t: np.ndarray  # estimate times, s from the start
    theta_hat: np.ndarray  # (T, 16)
    coupling: np.ndarray  # (T, 2)
    gain_l: np.ndarray  # (T, 12)
    status: np.ndarray | None  # (T, N_ROWS) or None
    excitation: np.ndarray | None
    pred_t: np.ndarray  # issue times (P,), s
    pred_states: list[np.ndarray]  # (n, 12) each
    pred_zeta0: np.ndarray  # (P, 12) the estimate at issue time
    pred_ref: np.ndarray  # (P, 4) the reference at issue time
    pred_status: list[int]
    withheld: int
    engine: VehicleEngine = field(repr=False)
    zeta_hat: np.ndarray | None = None  # (T, 12) the recorded estimates
    error_variance: np.ndarray | None = None  # (T, 12) their estimated error variances


def feed(
    engine: VehicleEngine,
    t: np.ndarray,
    zeta: np.ndarray,
    reference: np.ndarray,
    plans: Callable[[float], tuple[np.ndarray, np.ndarray] | None] | None = None,
    plan_every: float = 0.1,
    record_every: int = 10,
    progress: Callable[[float], None] | None = None,
) -> tuple[list[Estimate], list[Estimate]]:
    """Feed samples (stamps ``T0 + t``) to ``engine``; returns (decimated estimates, estimates
    carrying a prediction decision)."""
    recorded: list[Estimate] = []
    predicted: list[Estimate] = []
    next_plan = 0.0
    count = 0
    every = max(1, len(t) // 50)
    for k in range(len(t)):
        stamp = T0_NS + round(float(t[k]) * NS)
        if plans is not None and t[k] >= next_plan:
            next_plan = t[k] + plan_every
            plan = plans(float(t[k]))
            if plan is not None:
                times, refs = plan
                engine.add_plan(PathSample(
                    stamp, 'world', T0_NS + np.round(times * NS).astype(np.int64),
                    refs[:, [0, 1, 3]], yaw_quaternion(refs[:, 2])))  # fmt: skip
        p, q, v, w = state_to_odometry(zeta[k])
        engine.add_odometry(OdometrySample(stamp, 'world', 'base_link', p, q, v, w))
        r = reference[k]
        engine.add_reference(PoseSample(stamp, 'world', r[[0, 1, 3]], yaw_quaternion(r[2])))
        for est in engine.advance():
            if count % record_every == 0:
                recorded.append(est)
            if est.prediction_note:
                predicted.append(est)
            count += 1
        if progress is not None and k % every == 0:
            progress(k / len(t))
    for est in engine.finish():
        recorded.append(est)
        if est.prediction_note:
            predicted.append(est)
    return recorded, predicted


def collect(algorithm: str, engine: VehicleEngine, recorded, predicted) -> Run:
    """Arrays of a run from the engine's outputs."""
    t = np.array([(e.stamp_ns - T0_NS) / NS for e in recorded])
    ident = [e.identification for e in recorded]
    have_ident = all(i is not None for i in ident) and ident
    made = [e for e in predicted if e.prediction is not None]
    return Run(
        algorithm=algorithm,
        t=t,
        theta_hat=np.array([e.theta_hat for e in recorded]),
        coupling=np.array([e.coupling for e in recorded]),
        gain_l=np.array([e.gain_l for e in recorded]),
        status=np.array([i[2] for i in ident]) if have_ident else None,
        excitation=np.array([i[0] for i in ident]) if have_ident else None,
        pred_t=np.array([(e.stamp_ns - T0_NS) / NS for e in made]),
        pred_states=[e.prediction[1] for e in made],
        pred_zeta0=np.array([e.zeta_hat for e in made]).reshape(-1, 12),
        pred_ref=np.array([e.reference for e in made]).reshape(-1, 4),
        pred_status=[e.prediction_status for e in made],
        withheld=sum(1 for e in predicted if e.prediction is None),
        engine=engine,
        zeta_hat=np.array([e.zeta_hat for e in recorded]).reshape(-1, 12),
        error_variance=None if any(e.error_variance is None for e in recorded)
        else np.array([e.error_variance for e in recorded]).reshape(-1, 12),
    )


def actual_positions(t_truth: np.ndarray, zeta_truth: np.ndarray, times: np.ndarray) -> np.ndarray:
    """True/measured positions interpolated at ``times`` (NaN outside the data)."""
    out = np.empty((len(times), 3))
    for j, col in enumerate((0, 4, 10)):
        out[:, j] = np.interp(times, t_truth, zeta_truth[:, col], left=np.nan, right=np.nan)
    return out


def score_predictions(
    run: Run,
    t_truth: np.ndarray,
    zeta_truth: np.ndarray,
    step: float,
    horizons: Sequence[float] = HORIZONS,
    t_from: float = 0.0,
    t_to: float = np.inf,
    true_model: tuple[np.ndarray, np.ndarray] | None = None,
    plans: Callable[[float], tuple[np.ndarray, np.ndarray] | None] | None = None,
    valid: Callable[[np.ndarray], np.ndarray] | None = None,
) -> PredictionScore:
    """RMSE of the predicted positions at each horizon against ``zeta_truth``, beside the
    baselines from the same starting estimate (:func:`score_positions`); ``true_model = (theta,
    coupling)`` adds the true-model predictor (same start, same reference handling: held, or
    ``plans(t0)`` with times relative to the run's start). ``valid(times) -> bool array``
    restricts the scoring to predictions whose issue time and horizon time are both valid (e.g.
    in flight). A horizon counts at the prediction's step nearest to it."""
    horizons = tuple(horizons)
    keep = [i for i, t0 in enumerate(run.pred_t) if t_from <= t0 <= t_to]
    k_of = [round(h / step) for h in horizons]
    dts = np.array([k * step for k in k_of])
    predicted = np.full((len(keep), len(horizons), 3), np.nan)
    actual = np.full_like(predicted, np.nan)
    truth = np.full_like(predicted, np.nan) if true_model is not None else None
    truth_predictor = None
    if true_model is not None:
        n = max(k_of)
        truth_predictor = Predictor(PredictionConfig(horizon=n * step, step=step))
    for row, i in enumerate(keep):
        t0, states = run.pred_t[i], run.pred_states[i]
        zeta0 = run.pred_zeta0[i]
        times = actual_positions(t_truth, zeta_truth, t0 + dts)
        if valid is not None:
            ok = valid(np.concatenate([[t0], t0 + dts]))
            if not ok[0]:
                continue
            times[~ok[1:]] = np.nan
        actual[row] = times
        true_states = None
        if truth_predictor is not None:
            plan = plans(t0) if plans is not None else None
            if plan is not None:
                plan = (plan[0] - t0, plan[1].copy())
                plan[1][:, 2] += np.round((zeta0[8] - plan[1][0, 2]) / (2 * np.pi)) * 2 * np.pi
            true_states = truth_predictor.predict(zeta0, true_model[0], true_model[1],
                                                  run.pred_ref[i], plan)  # fmt: skip
        for j, k in enumerate(k_of):
            if k > len(states):
                continue
            predicted[row, j] = states[k - 1][[0, 4, 10]]
            if true_states is not None:
                truth[row, j] = true_states[k - 1][[0, 4, 10]]
    return score_positions(
        horizons,
        predicted,
        actual,
        run.pred_zeta0[keep].reshape(-1, 12),
        np.broadcast_to(dts, predicted.shape[:2]),
        truth,
        withheld=run.withheld,
        t_from=t_from,
        t_to=float(min(t_to, run.pred_t[-1])) if len(run.pred_t) else t_from,
    )


def parameter_error_over_time(
    run: Run, theta_true: np.ndarray, times: Sequence[float]
) -> dict[float, dict[str, float]]:
    """Relative parameter error per block at the estimates nearest ``times`` (s)."""
    out = {}
    for tq in times:
        if not len(run.t) or tq > run.t[-1] + 1e-9:
            continue
        i = int(np.argmin(np.abs(run.t - tq)))
        errors = parameter_error(run.theta_hat[i], theta_true)
        out[float(tq)] = {k: float(v) for k, v in errors.items()}
    return out


def status_calibration(
    run: Run, theta_true: np.ndarray, wrong: float = 0.10
) -> dict[str, dict[str, float]]:
    """How far to trust an "identified" status: per block, over the recorded estimates, the
    fraction of the run in which the block's row was reported identified, the fraction in which
    it was reported identified while its error exceeded ``wrong``, and the largest error while
    reported identified (NaN if never). Needs a run with an identifier (``run.status``)."""
    if run.status is None:
        raise ValueError(f'{run.algorithm} has no identifier status to calibrate')
    errors = parameter_error(run.theta_hat, theta_true)
    out = {}
    for block in BLOCKS:
        said = run.status[:, ROW_NAMES.index(block.name)] == IDENTIFIED
        err = errors[block.name]
        out[block.name] = {
            'identified': float(np.mean(said)),
            'identified_but_wrong': float(np.mean(said & (err > wrong))),
            'max_error_identified': float(np.max(err[said])) if np.any(said) else float('nan'),
        }
    return out


#: Gaussian probability of the 2-sigma interval (1-D) and of the 2-sigma ellipsoid (3-D):
#: ``P(chi2_k <= 4)``, k = 1 and 3.
GAUSSIAN_2SIGMA = {1: math.erf(2.0 / math.sqrt(2.0)),
                   3: math.erf(math.sqrt(2.0)) - 2.0 * math.sqrt(2.0 / math.pi) * math.exp(-2.0)}
#: The blocks of ``cloe/state`` whose covariance is scored: (name, pose or twist, rows).
COVARIANCE_BLOCKS = (('position', 'pose', slice(0, 3)), ('attitude', 'pose', slice(3, 6)),
                     ('velocity', 'twist', slice(0, 3)), ('rates', 'twist', slice(3, 6)))


def state_errors(zeta_hat: np.ndarray, zeta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate minus truth in ``cloe/state``'s terms (REP-105), ``(pose (T, 6), twist (T, 6))``:
    world position, Euler angles (roll, pitch, yaw; wrapped), body velocity, body rates."""
    p_hat, _, v_hat, w_hat = state_to_odometry(zeta_hat)
    p, _, v, w = state_to_odometry(zeta)
    angles = zeta_hat[:, [6, 2, 8]] - zeta[:, [6, 2, 8]]
    angles = (angles + np.pi) % (2.0 * np.pi) - np.pi
    return np.hstack([p_hat - p, angles]), np.hstack([v_hat - v, w_hat - w])


def covariance_coverage(
    run: Run, t_truth: np.ndarray, zeta_truth: np.ndarray, t_from: float = 0.0
) -> dict[str, dict[str, float]]:
    """How well ``cloe/state``'s covariance describes the true error: per block (position,
    attitude, body velocity, body rates), over the recorded estimates from ``t_from`` on, the
    fraction of errors (estimate minus ``zeta_truth`` interpolated) inside the 2-sigma ellipsoid
    of the block's 3x3 covariance (Gaussian: 73.9 %), the fraction inside each axis' 2-sigma
    interval (Gaussian: 95.4 %, the mean over the three axes and the lowest), and the RMS of the
    true error (norm) beside the median of the reported standard deviation (root of the trace)."""
    if run.error_variance is None:
        raise ValueError(f'{run.algorithm}: the run has no error variances')
    from cloe_ros.core.covariance import odometry_covariance

    keep = run.t >= t_from
    truth = interpolate(t_truth, zeta_truth, run.t[keep])
    ok = np.all(np.isfinite(truth), axis=1)
    zeta_hat, variance = run.zeta_hat[keep][ok], run.error_variance[keep][ok]
    errors = dict(zip(('pose', 'twist'), state_errors(zeta_hat, truth[ok])))
    covs = dict(zip(('pose', 'twist'), odometry_covariance(zeta_hat, variance)))
    out = {}
    for name, part, rows in COVARIANCE_BLOCKS:
        err, cov = errors[part][:, rows], covs[part][:, rows, rows]
        d2 = np.einsum('ti,ti->t', err, np.linalg.solve(cov, err[..., None])[..., 0])
        sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
        axis = np.mean(np.abs(err) <= 2.0 * sigma, axis=0)
        out[name] = {
            'ellipsoid_3d': float(np.mean(d2 <= 4.0)),
            'interval_1d': float(np.mean(axis)),
            'interval_1d_lowest': float(np.min(axis)),
            'rms_error': float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
            'median_sigma': float(np.median(np.sqrt(np.sum(sigma**2, axis=1)))),
            'count': len(err),
        }
    return out


def coupling_error(run: Run) -> np.ndarray:
    """Relative error of the identified tilt couplings against ``+-g`` (T, 2)."""
    return np.abs(run.coupling - PAPER_COUPLING) / np.abs(PAPER_COUPLING)


def run_engine(
    algorithm_config: EngineConfig,
    t: np.ndarray,
    zeta: np.ndarray,
    reference: np.ndarray,
    plans=None,
    progress=None,
    namespace: str = '/',
) -> Run:
    """One engine over samples; see :func:`feed`. ``namespace``: the vehicle's, as a recording
    shows it (it shifts the predictions with ``prediction_phase`` 'spread', from the samples'
    origin ``T0_NS``: the instants are not those of the recording's stamps)."""
    engine = VehicleEngine(algorithm_config, namespace=namespace)
    recorded, predicted = feed(engine, t, zeta, reference, plans, progress=progress)
    return collect(algorithm_config.estimator.algorithm, engine, recorded, predicted)


# ----------------------------------------------------------------- real flights, a corpus

#: Reference-free and reference-following baselines every prediction is scored beside.
BASELINES = ('constant_velocity', 'hold_position', 'reference_held', 'reference_lag')
#: Lags the reference-lag baseline searches, s, and the recent past it fits them on, s.
LAGS = np.arange(0.0, 1.51, 0.05)
LAG_WINDOW = 5.0


def interpolate(t: np.ndarray, values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``values`` (T, C) sampled at increasing ``t`` (T,), at ``times`` (...,): (..., C), NaN
    outside ``[t[0], t[-1]]``."""
    times = np.asarray(times, float)
    out = np.full((*times.shape, values.shape[1]), np.nan)
    if not len(t):
        return out
    ok = (times >= t[0]) & (times <= t[-1])
    for j in range(values.shape[1]):
        out[..., j] = np.where(ok, np.interp(times, t, values[:, j]), np.nan)
    return out


def held(t: np.ndarray, values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The latest sample of ``values`` at or before each of ``times`` (NaN before the first)."""
    idx = np.searchsorted(t, np.asarray(times, float), side='right') - 1
    out = values[np.clip(idx, 0, None)].astype(float)
    out[idx < 0] = np.nan
    return out


def causal_lag(t_pos: np.ndarray, pos: np.ndarray, t_ref: np.ndarray, ref: np.ndarray,
               now: float) -> float | None:  # fmt: skip
    """The lag (s, in ``LAGS``) with which the positions of the last ``LAG_WINDOW`` before
    ``now`` best follow the reference, ``p(s) ~ r(s - lag)``; None without enough data."""
    m = (t_pos > now - LAG_WINDOW) & (t_pos <= now)
    s = t_pos[m][::5]
    if len(s) < 10:
        return None
    p = pos[m][::5]
    costs = np.full(len(LAGS), np.nan)
    for i, lag in enumerate(LAGS):
        sq = np.sum((p - held(t_ref, ref, s - lag)) ** 2, axis=1)
        if np.isfinite(sq).any():
            costs[i] = np.nanmean(sq)
    if not np.isfinite(costs).any():
        return None
    return float(LAGS[int(np.nanargmin(costs))])


@dataclass
class FlightRecord:
    """What one vehicle's replay gives the corpus evaluation.

    Attributes:
        name: The flight (bag, and vehicle when there are several).
        t0: The first odometry stamp, s since the epoch (every other time is relative to it).
        odom_t, odom_p: Odometry stamps (T,) and positions (T, 3): what the vehicle did.
        ref_t, ref_p: Reference stamps (R,) and positions (R, 3) as received.
        issue_t: Issue times of the predictions (P,).
        state: The measured state at each issue time (P, 12).
        predicted: The published positions at each horizon (P, H, 3) (NaN past the path).
        radius: The published 95 % radius at each horizon (P, H).
        tracked: Per issue time, whether each reference channel was tracked (P, 4).
        horizons: The horizons, s (H,).

    """

    name: str
    t0: float
    odom_t: np.ndarray
    odom_p: np.ndarray
    ref_t: np.ndarray
    ref_p: np.ndarray
    issue_t: np.ndarray
    state: np.ndarray
    predicted: np.ndarray
    radius: np.ndarray
    tracked: np.ndarray
    horizons: tuple[float, ...] = HORIZONS


@dataclass
class FlightScore:
    """Prediction RMSE per horizon (m) of the package and the baselines on one flight.

    ``rmse`` maps ``'model'`` and each of ``BASELINES`` to (H,) arrays; ``coverage`` is the
    fraction of scored positions inside the published radius (H,); ``count`` the scored
    predictions per horizon; ``worst_ratio`` the largest, over horizons, of the model's RMSE over
    the better of constant velocity and hold; ``untracked`` the fraction of the scored issue
    times with a reference channel not tracked."""

    name: str
    horizons: tuple[float, ...]
    rmse: dict[str, np.ndarray]
    coverage: np.ndarray
    count: np.ndarray
    worst_ratio: float
    untracked: float

    def as_dict(self) -> dict:
        return {
            'name': self.name,
            'horizons_s': list(self.horizons),
            'rmse_m': {k: v.tolist() for k, v in self.rmse.items()},
            'coverage': self.coverage.tolist(),
            'count': self.count.tolist(),
            'worst_ratio': self.worst_ratio,
            'untracked_fraction': self.untracked,
        }


def baseline_paths(record: FlightRecord) -> dict[str, np.ndarray]:
    """The baselines' positions (P, H, 3) from each issue time of ``record``:

    * ``constant_velocity`` and ``hold_position`` from the measured state at the issue time;
    * ``reference_held``: the reference at the issue time, at every horizon;
    * ``reference_lag``: the vehicle follows its reference with a lag ``L`` estimated causally
      (:func:`causal_lag`): ``r(t + h - L)`` while that is in the past, else ``r(t)``.
    """
    h = np.asarray(record.horizons, float)
    cv, hold = kinematic_baselines(record.state, np.broadcast_to(h, (len(record.state), len(h))))
    out = {'constant_velocity': cv, 'hold_position': hold}
    now_ref = held(record.ref_t, record.ref_p, record.issue_t)
    out['reference_held'] = np.broadcast_to(now_ref[:, None, :], out['hold_position'].shape).copy()
    lagged = out['reference_held'].copy()
    for i, t in enumerate(record.issue_t):
        lag = causal_lag(record.odom_t, record.odom_p, record.ref_t, record.ref_p, t)
        if lag is None:
            continue
        back = np.minimum(t + h - lag, t)
        lagged[i] = held(record.ref_t, record.ref_p, back)
    out['reference_lag'] = lagged
    return out


def score_flight(record: FlightRecord, score_from: float = 5.0) -> FlightScore:
    """RMSE per horizon of the published predictions and the baselines against the odometry
    that followed, for predictions issued ``score_from`` s or more after the first odometry
    (each scored where the odometry covers its horizon); the coverage of the radius."""
    h = np.asarray(record.horizons, float)
    keep = record.issue_t >= score_from
    truth = interpolate(record.odom_t, record.odom_p, record.issue_t[keep, None] + h[None, :])
    paths = {'model': record.predicted[keep]}
    paths.update({k: v[keep] for k, v in baseline_paths(record).items()})
    ok = np.isfinite(truth).all(axis=-1) & np.isfinite(paths['model']).all(axis=-1)
    rmse = {name: rmse_per_horizon(pred, truth, ok) for name, pred in paths.items()}
    err = np.sqrt(np.sum((paths['model'] - truth) ** 2, axis=-1))
    inside = err <= record.radius[keep]
    coverage = np.array([np.mean(inside[ok[:, j], j]) if ok[:, j].any() else np.nan
                         for j in range(len(h))])  # fmt: skip
    best = np.minimum(rmse['constant_velocity'], rmse['hold_position'])
    with np.errstate(invalid='ignore', divide='ignore'):
        ratio = rmse['model'] / best
    tracked = record.tracked[keep]
    return FlightScore(
        name=record.name,
        horizons=record.horizons,
        rmse=rmse,
        coverage=coverage,
        count=ok.sum(axis=0),
        worst_ratio=float(np.nanmax(ratio)) if np.isfinite(ratio).any() else float('nan'),
        untracked=float(np.mean(~tracked.all(axis=1))) if len(tracked) else 0.0,
    )
