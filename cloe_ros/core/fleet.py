"""Many vehicles, one batched estimator step: the engines of a node (or bag) stepped together.

Each vehicle keeps its own :class:`~cloe_ros.core.engine.VehicleEngine`: its input validation,
its timeline (grid, held samples, time jumps) and its anticipation. What a :class:`Fleet` adds is
where the estimators live: the vehicles whose estimator settings agree are rows of one estimator
(an :class:`EstimatorPool`, see :mod:`cloe_ros.core.rows`), and :meth:`Fleet.advance` runs in
rounds, each round one grid step of every vehicle that is due, in one batched call per pool. A
vehicle behind the others (its inputs came late) catches up over the next rounds, alone or with
the others that are still due. Besides the estimator step, a round batches the error statistics
of the vehicles that stepped (:meth:`~cloe_ros.core.covariance.ErrorCovariance.update_many`) and
the costliest solves of the predictions due (:func:`~cloe_ros.core.anticipation.run_together`),
which run at the end of the round, before any of those vehicles steps again.

The estimates are the ones each vehicle gets alone (every operation is per row; the test suite
checks it to 1e-9), so the node, ``cloe infer`` and ``cloe evaluate`` agree whatever the batching.

Numerical failures. A vehicle whose estimate turns non-finite is restarted by its engine, as
alone. The identifier keeps one vehicle's overflowed statistics from raising for the others;
should a batched step raise all the same, every vehicle of that batch is restarted.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from typing import TYPE_CHECKING

import numpy as np

from cloe_ros.core.anticipation import run_together
from cloe_ros.core.covariance import ErrorCovariance
from cloe_ros.core.rows import Rows

if TYPE_CHECKING:
    from cloe_ros.core.engine import Estimate, Step, VehicleEngine


class _Row:
    """One vehicle's view of a batched object: every attribute read is that vehicle's row
    (shape (1, ...)), tuples of arrays element-wise, nested batched objects as views too."""

    __slots__ = ('_i', '_of')

    def __init__(self, of, i: int) -> None:
        self._of, self._i = of, i

    def __getattr__(self, name: str):
        value = getattr(self._of, name)
        i = self._i
        if isinstance(value, tuple):
            return tuple(v[i : i + 1] for v in value)
        if isinstance(value, Rows):
            return _Row(value, i)
        return value[i : i + 1]


class PooledEstimator:
    """A vehicle's estimator that is a row of an :class:`EstimatorPool`: reads like an estimator
    of one vehicle (``zeta_hat``, ``theta_hat``, ``gain_l``, ``coupling``, ``model``,
    ``identifier``: arrays of shape (1, ...)), steps through the pool."""

    def __init__(self, pool: EstimatorPool, key: Hashable) -> None:
        self.pool, self.key = pool, key

    def __getattr__(self, name: str):
        return getattr(_Row(*self.pool.row_of(self.key)), name)

    @property
    def config(self):
        return getattr(self.pool.row_of(self.key)[0], 'config', None)

    def step(self, zeta, r, h, tracked=None) -> None:
        """Step this vehicle alone (the pool's other vehicles wait)."""
        if self.pool.step([self.key], zeta, r, h, tracked) is None:
            raise np.linalg.LinAlgError('the batched step failed')

    def detach(self) -> Rows:
        """This vehicle's estimator as one of its own, out of the pool."""
        return self.pool.remove(self.key)


def row_of(est) -> tuple[object, int]:
    """Where the state of vehicle estimator ``est`` lives: the batched estimator and the row
    (a pool's, or ``est`` itself and row 0), to read its arrays without a view per attribute."""
    if isinstance(est, PooledEstimator):
        return est.pool.row_of(est.key)
    return est, 0


class StepOutputs:
    """What the estimates of a batch that stepped hold, gathered from the batched estimator
    ``est`` once for its vehicles ``rows`` (new arrays, (K, ...)): each vehicle's estimate takes
    views of its row (:meth:`row`) instead of copying each array out of the estimator."""

    __slots__ = ('coupling', 'finite', 'gain_l', 'identification', 'model', 'theta_hat',
                 'zeta_hat')  # fmt: skip

    def __init__(self, est, rows: np.ndarray) -> None:
        # every row in order (one vehicle, or a whole pool): copies, cheaper than a gather
        whole = all_rows_in_order(rows, len(est.zeta_hat))
        take = (lambda a: a.copy()) if whole else (lambda a: a[rows])
        self.zeta_hat, self.theta_hat = take(est.zeta_hat), take(est.theta_hat)
        self.gain_l, self.coupling = take(est.gain_l), take(est.coupling)
        ident = getattr(est, 'identifier', None)
        self.identification = None if ident is None else (
            take(ident.excitation), take(ident.uncertainty), take(ident.status))  # fmt: skip
        model_theta, model_coupling = est.model
        self.model = take(model_theta), take(model_coupling)
        #: per vehicle: its state and parameters are all finite
        self.finite = (np.isfinite(self.zeta_hat).all(axis=1)
                       & np.isfinite(self.theta_hat).all(axis=1))  # fmt: skip

    def row(self, k: int) -> tuple:
        """Vehicle ``k``'s ``(zeta_hat, theta_hat, gain_l, coupling, identification, model)``."""
        ident = self.identification
        return (self.zeta_hat[k], self.theta_hat[k], self.gain_l[k], self.coupling[k],
                None if ident is None else (ident[0][k], ident[1][k], ident[2][k]),
                (self.model[0][k], self.model[1][k]))  # fmt: skip


class EstimatorPool:
    """The estimators of vehicles whose settings agree, as the rows of one estimator.

    A vehicle added joins the batched arrays when the pool is next stepped (or read as a whole,
    :attr:`est`), together with the others added since: vehicles that start on the same step (a
    swarm seen at once) are joined in one copy of the arrays, not one each, which grew as the
    square of their number (about 50 ms at 100 vehicles). Until then its state is its own
    estimator's (:meth:`row_of`), the same values."""

    def __init__(self, est: Rows, key: Hashable) -> None:
        self._est = est
        self.keys = [key]
        self.rows = {key: 0}
        self._joining: dict[Hashable, Rows] = {}  # added since the arrays were last joined

    @property
    def est(self) -> Rows:
        """The batched estimator, every vehicle of the pool a row of it."""
        if self._joining:
            self._est = type(self._est).concatenate([self._est, *self._joining.values()])
            self._joining = {}
        return self._est

    def row_of(self, key: Hashable) -> tuple[Rows, int]:
        """Where vehicle ``key``'s state is: its own estimator and row 0 while it waits to join,
        else the batched one and its row."""
        own = self._joining.get(key)
        return (own, 0) if own is not None else (self.est, self.rows[key])

    def accepts(self, est: Rows) -> bool:
        return self._est.shares_settings(est)

    def add(self, key: Hashable, est: Rows) -> PooledEstimator:
        self._joining[key] = est
        self.rows[key] = len(self.keys)
        self.keys.append(key)
        return PooledEstimator(self, key)

    def remove(self, key: Hashable) -> Rows:
        """Take ``key``'s vehicle out; returns its estimator (of one vehicle)."""
        i = self.rows.pop(key)
        own = self.est.take([i])
        self.keys.pop(i)
        self._est = self._est.delete([i]) if self.keys else None
        self.rows = {k: j for j, k in enumerate(self.keys)}
        return own

    def step(self, keys: list, zeta, r, h: float, tracked=None) -> np.ndarray | None:
        """One step of the vehicles ``keys`` with their measurements (K, 12), references (K, 4)
        and tracked channels (K, 4) or None, in ``keys``' order. Returns their rows (K,), or
        None if it failed (nothing is then known of their state)."""
        rows = np.fromiter((self.rows[k] for k in keys), dtype=np.intp, count=len(keys))
        try:
            if len(rows) == len(self.keys):  # everyone: in place, in row order
                if not all_rows_in_order(rows, len(self.keys)):
                    order = np.argsort(rows)
                    zeta, r = zeta[order], r[order]
                    tracked = None if tracked is None else tracked[order]
                self.est.step(zeta, r, h, tracked)
            else:
                part = self.est.take(rows)
                part.step(zeta, r, h, tracked)
                self.est.put(rows, part)
        except (ArithmeticError, np.linalg.LinAlgError):
            return None
        return rows


def all_rows_in_order(rows: np.ndarray, n: int) -> bool:
    """Whether ``rows`` are the ``n`` rows of a pool in order, ``0, 1, ..., n - 1``."""
    return len(rows) == n and (n == 1 or bool((np.diff(rows) == 1).all()))


class Fleet:
    """The engines of many vehicles, their estimators batched (see the module docstring).

    Args:
        pooled: Keep the estimators as rows of shared ones. False: each vehicle keeps its own
            and steps alone (for callers that step one vehicle at a time: a row stepped without
            the others of its pool is copied out and back, which costs more than its step).

    """

    def __init__(self, pooled: bool = True) -> None:
        self.engines: dict[str, VehicleEngine] = {}
        self.pooled = pooled
        self._pools: list[EstimatorPool] = []

    def add(self, engine: VehicleEngine) -> VehicleEngine:
        """Add ``engine`` (one of the same name leaves the fleet first); its estimator joins a
        pool at its next start."""
        if engine.name in self.engines:
            self.remove(engine.name)
        self.engines[engine.name] = engine
        engine.fleet = self
        return engine

    def remove(self, name: str) -> VehicleEngine:
        """Take vehicle ``name`` out of the fleet; its engine keeps its estimator, as its own."""
        engine = self.engines.pop(name)
        est = engine._set_estimator(None)
        engine.fleet = None
        engine._set_estimator(est)
        return engine

    def adopt(self, engine: VehicleEngine, est: Rows) -> PooledEstimator | Rows:
        """Where ``engine``'s newly started estimator lives: a row of the pool whose settings
        it shares (a new pool if none)."""
        if not (self.pooled and isinstance(est, Rows)):
            return est  # (unpooled, or an estimator of its own kind, e.g. a test's: alone)
        self._pools = [p for p in self._pools if p.keys]
        for pool in self._pools:
            if pool.accepts(est):
                return pool.add(engine.name, est)
        pool = EstimatorPool(est, engine.name)
        self._pools.append(pool)
        return PooledEstimator(pool, engine.name)

    def advance(self, names: Iterable[str] | None = None) -> dict[str, list[Estimate]]:
        """Run every step whose inputs are complete, of the vehicles ``names`` (default: all),
        each grid step of all the vehicles due in one batched call per pool; a vehicle whose step
        or prediction fails numerically stops there (its estimator restarts on the next step's
        data, at the next call). Returns the estimates per vehicle, in time order (vehicles with
        none are left out)."""
        engines = [self.engines[n] for n in (self.engines if names is None else names)]
        out = {engine.name: engine.take_pending() for engine in engines}
        while engines:
            batches: dict[int, list[tuple[VehicleEngine, Step]]] = {}
            for engine in engines:
                step = engine.next_step(False, out[engine.name])
                if step is not None:
                    est = engine._est  # (the property without its call, per vehicle-step)
                    where = id(est.pool) if isinstance(est, PooledEstimator) else id(engine)
                    batches.setdefault(where, []).append((engine, step))
            engines = []
            deferred: list[tuple[VehicleEngine, Estimate]] = []
            for batch in batches.values():
                first, step = batch[0]
                est = first.estimator
                variances = [None] * len(batch)
                outputs = None
                if isinstance(est, PooledEstimator):
                    steps = [s for _, s in batch]
                    zeta = np.array([s.zeta for s in steps])
                    names = [e.name for e, _ in batch]
                    used = np.array([s.used for s in steps])
                    tracked = _tracked([s.tracked for s in steps])
                    rows = est.pool.step(names, zeta, used, first.step_s, tracked)
                    ok = rows is not None
                    if ok:
                        outputs = StepOutputs(est.pool.est, rows)
                        if len(batch) > 1:
                            variances = _error_variances(outputs, batch, zeta)
                else:
                    ok = first.step_alone(step)
                for k, ((engine, step), variance) in enumerate(zip(batch, variances)):
                    row = None if outputs is None else (outputs, k)
                    if engine.complete_step(step, ok, out[engine.name], variance, defer=True,
                                            outputs=row):  # fmt: skip
                        engines.append(engine)
                        e = engine.take_deferred()
                        if e is not None:
                            deferred.append((engine, e))
            if deferred:  # the predictions due this round, side by side
                values = run_together([engine.prediction_steps(e) for engine, e in deferred])
                for (engine, e), value in zip(deferred, values):
                    if isinstance(value, BaseException):  # as a failure of the step
                        of_vehicle = out[engine.name]
                        if of_vehicle and of_vehicle[-1] is e:
                            of_vehicle.pop()
                        engine.prediction_failed(e)
                        engines.remove(engine)
        return {name: estimates for name, estimates in out.items() if estimates}


class RecordingBatches:
    """A fleet fed in recording order (a bag read by log time), stepped in batches: the
    vehicles with input during ``span_ns`` of recording time (a grid step) step together.

    Call :meth:`before` before feeding an input logged at ``log_ns`` (it returns the estimates of
    the batch that input ends, per vehicle, or nothing), :meth:`fed` after feeding it, and
    :meth:`flush` after the last one."""

    def __init__(self, fleet: Fleet, span_ns: int) -> None:
        self.fleet, self.span_ns = fleet, span_ns
        self._due: dict[str, None] = {}  # the vehicles with input in this batch, in order
        self._end: int | None = None  # log time at which this batch ends

    def before(self, log_ns: int) -> dict[str, list[Estimate]]:
        if self._end is None or log_ns < self._end:
            return {}
        return self.flush()

    def fed(self, vehicle: str, log_ns: int) -> None:
        self._due[vehicle] = None
        if self._end is None:
            self._end = log_ns + self.span_ns

    def flush(self) -> dict[str, list[Estimate]]:
        due, self._due, self._end = list(self._due), {}, None
        return self.fleet.advance(due)


def _error_variances(outputs: StepOutputs, batch: list, zeta: np.ndarray) -> list:
    """The error statistics' updates of a batch that stepped (:class:`ErrorCovariance`), at
    once; None for a vehicle whose estimate is not finite (its engine restarts it, and its
    statistics take nothing of that step)."""
    out = [None] * len(batch)
    which = np.flatnonzero(outputs.finite)
    if len(which):
        covs = [batch[i][0]._covariance for i in which]
        variances = ErrorCovariance.update_many(covs, zeta[which], outputs.zeta_hat[which],
                                                outputs.gain_l[which])  # fmt: skip
        for j, i in enumerate(which):
            out[i] = variances[j]
    return out


def _tracked(tracked: list) -> np.ndarray | None:
    """The tracked channels of a batch (K, 4), None when every vehicle tracks every channel."""
    if all(t is None for t in tracked):
        return None
    return np.array([np.ones(4, dtype=bool) if t is None else t for t in tracked])
