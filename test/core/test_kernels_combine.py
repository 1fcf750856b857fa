"""The kernels of the guard's candidates, the published path and the radius
(cloe_ros/core/kernels_combine.py) give the numpy code's values bit for bit under the golden
test's pinned kernels: on random arguments (empty and short histories, grounded and not-allowed
masks, unscored horizons, fewer than ``min_errors`` scores, NaN gaps, ties, horizons scored
twice) and on the arguments the anticipator is given while the engine runs recorded flights.

The checks run in a child process with the pinned kernels (:data:`PINNED_KERNELS`): there
numpy's loops, OpenBLAS and libm are those the golden outputs were computed with. Unpinned
(numpy's AVX-512 loops and libm variants), the kernels agree with numpy to round-off.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path

import numpy as np
import pytest

from cloe_ros.core import anticipation as ant
from cloe_ros.core import kernels_combine as kc
from test.corpus import B3
from test.golden_outputs import REPO, run_pinned_script

needs_blas = pytest.mark.skipif(not kc.AVAILABLE, reason="numpy's OpenBLAS not found")


# ------------------------------------------------------------------ the numpy code


def numpy_candidates(measured, coupling, poses, recent, model):
    """``paths`` (6, K, 3) as :meth:`Anticipator.combine_steps` fills ``paths[:5]`` (its lines)."""
    paths = np.full((len(ant.CANDIDATES) + 1, len(poses), 3), np.nan)
    paths[0] = model
    paths[1] = ant.turn_positions(measured, coupling, poses)
    paths[2] = measured[ant.POSITION] + np.outer(poses, measured[ant.VELOCITY])
    paths[3] = measured[ant.POSITION]
    paths[4] = (recent[:, ant.POSITION].mean(axis=0) if len(recent)
                else measured[ant.POSITION])  # fmt: skip
    return paths


def numpy_publish(w, paths, p0, v0, poses, max_speed, max_acceleration, allowed):
    """The published path and the scales as :meth:`Anticipator.combine_steps` makes them (its
    lines); fills ``paths[-1]``."""
    published = np.einsum('km,mkd->kd', w, paths[:-1])
    published = ant.clip_to_envelope(p0, v0, poses, published, max_speed, max_acceleration)
    paths[-1] = published
    gap = paths[:-1][allowed] - published
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)  # (the mean over no candidate)
        spread = np.sqrt(np.mean(np.sum(gap**2, axis=-1), axis=0))
    return published, spread + ant.SCALE_FLOOR + ant.SCALE_GROWTH * poses


def numpy_scored(radius, scored, radii_table, scales_table):
    """The radius part of :meth:`Anticipator.update_steps` (its lines) on ``radius``."""
    slots, ks = scored.slots, scored.horizons
    errors = np.sqrt(scored.squared[:, -1])
    radii, scales = radii_table[slots, ks], scales_table[slots, ks]
    if len(ks) and len(np.unique(ks)) == len(ks):
        radius.update(ks, errors, radii, scales)
    elif len(ks):
        starts = np.flatnonzero(np.r_[True, slots[1:] != slots[:-1]])
        for a, b in zip(starts, [*starts[1:], len(slots)]):
            radius.update(ks[a:b], errors[a:b], radii[a:b], scales[a:b])


def bitwise(a, b) -> bool:
    """The same shape and bits (any NaN equal to any NaN; 0.0 and -0.0 different)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return False
    nan = np.isnan(a)
    return bool(np.array_equal(nan, np.isnan(b))
                and np.array_equal(a[~nan].view(np.int64), b[~nan].view(np.int64)))  # fmt: skip


# --------------------------------------------------------------------- the kernels


def kernel_candidates(measured, coupling, poses, recent, model):
    paths = np.full((len(ant.CANDIDATES) + 1, len(poses), 3), np.nan)
    kc.candidate_paths(measured, coupling, poses, recent, model, paths)
    return paths


def kernel_publish(w, paths, p0, v0, poses, max_speed, max_acceleration, allowed):
    scales = np.full(len(poses), np.nan)
    kc.publish(w, paths, p0, v0, poses, float(max_speed), float(max_acceleration), allowed,
               scales)  # fmt: skip
    return paths[-1].copy(), scales


def kernel_radii(radius, scales):
    out = np.full(len(radius.offsets), np.nan)
    kc.coverage_radii(radius._errors, radius._count, radius.level, radius.prior, radius.offsets,
                      radius.min_errors, scales, out)  # fmt: skip
    return out


def radius_state(radius) -> tuple:
    return radius._errors.copy(), radius._count.copy(), radius.level.copy()


def set_state(radius, state) -> None:
    radius._errors[:], radius._count[:], radius.level[:] = state


def same_state(a, b) -> bool:
    return all(bitwise(x, y) for x, y in zip(a, b))


def kernel_update(radius, ks, errors, radii_then, scales):
    kc.coverage_update(ks, errors, radii_then, scales, radius._errors, radius._count,
                       radius.level, radius.gain, radius.coverage)  # fmt: skip


def kernel_scored(radius, scored, radii_table, scales_table):
    kc.coverage_scored(scored.slots, scored.horizons, scored.squared, radii_table,
                       scales_table, radius._errors, radius._count, radius.level, radius.gain,
                       radius.coverage)  # fmt: skip


# --------------------------------------------------------------- random arguments


def random_state(rng, k: int, window: int, min_errors: int, scarce: bool = False):
    """A radius of ``k`` horizons with random scores: ties, NaN scores, unfilled slots, horizons
    with fewer than ``min_errors`` scores (all of them when ``scarce``), levels at 0 and 1."""
    radius = ant.CoverageRadius(0.1 * np.arange(1, k + 1), 0.95, window=window,
                                min_errors=min_errors)  # fmt: skip
    count = rng.integers(0, 3 * window + 2, size=k)
    if scarce:
        count = np.minimum(count, min_errors - 1)
    count[rng.random(k) < 0.3] = 0
    radius._count[:] = count
    for j in range(k):
        filled = min(count[j], window)
        if rng.random() < 0.3:  # ties
            values = rng.choice([0.25, 0.5, 1.0, 2.0], size=filled)
        else:
            values = rng.lognormal(0.0, 1.0, size=filled)
        values[rng.random(filled) < 0.05] = np.nan
        values[rng.random(filled) < 0.02] = np.inf
        radius._errors[j, :filled] = values
    radius.level[:] = rng.choice([0.0, 1.0, 0.95, 0.5, 0.999], size=k)
    radius.level[rng.random(k) < 0.5] = rng.random()
    return radius


def random_scales(rng, k: int) -> np.ndarray:
    scales = rng.lognormal(-2.0, 2.0, size=k)
    scales[rng.random(k) < 0.1] = 1e-6  # below the 1e-3 floor
    if rng.random() < 0.2:
        scales[rng.integers(k)] = np.nan
    return scales


def random_measured(rng) -> np.ndarray:
    measured = rng.normal(size=12) * rng.choice([1e-3, 0.1, 1.0, 10.0], size=12)
    kind = rng.integers(6)
    if kind == 0:
        measured[ant.VELOCITY] = 0.0  # at rest: no turn rate
    elif kind == 1:
        measured[[1, 5]] = 1e-3  # speed^2 below 1e-4
    elif kind == 2:
        measured[[2, 6]] = 1e-7  # a turn rate below the threshold
    elif kind == 3:
        measured[[2, 6]] = rng.normal(size=2)  # a fast turn
    elif kind == 4 and rng.random() < 0.3:
        measured[rng.integers(12)] = np.nan
    return measured


def check_random_candidates(rng) -> None:
    for trial in range(600):
        k = int(rng.choice([1, 2, 5, 30, 100, 101]))
        poses = float(rng.choice([0.1, 0.05, 0.37])) * np.arange(1, k + 1)
        measured = random_measured(rng)
        coupling = rng.normal(size=2) * 10.0
        t = int(rng.choice([0, 1, 2, 7, 8, 9, 50, 128, 129, 300, 601, 1200]))
        history = rng.normal(size=(t + 5, 12)) * 5.0 + rng.normal(size=12) * 100.0
        recent = history[3 : 3 + t]  # (a slice of the history's rows)
        model = rng.normal(size=(k, 3)) * 3.0
        want = numpy_candidates(measured, coupling, poses, recent, model)
        got = kernel_candidates(measured, coupling, poses, recent, model)
        assert bitwise(got[:5], want[:5]), ('candidates', trial, k, t)
        # the published path and the scales, from these candidates
        m = len(ant.CANDIDATES)
        allowed = np.ones(m, dtype=bool)
        if rng.random() < 0.3:
            allowed[[0, 4]] = False  # commanded to the ground
        elif rng.random() < 0.1:
            allowed[rng.random(m) < 0.5] = False  # (any mask: none allowed too)
        w = rng.random((k, m)) * (rng.random((k, m)) < 0.7)
        w[:, ~allowed] = 0.0
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        if rng.random() < 0.2:  # no guard, or no score yet: one candidate
            w[:] = 0.0
            w[:, int(rng.integers(m))] = 1.0
        if rng.random() < 0.2:
            w = np.asfortranarray(w)
        p0 = measured[ant.POSITION] + rng.normal(size=3) * 0.01
        v0 = measured[ant.VELOCITY] + rng.normal(size=3) * 0.01
        if rng.random() < 0.2:
            v0 = np.zeros(3)
        max_speed = float(rng.choice([0.5, 5.0, 20.0]))
        max_acceleration = float(rng.choice([1.0, 5.0, 30.0]))
        if rng.random() < 0.3:  # far candidates: the envelope clips
            want[rng.integers(m)] += rng.normal(size=(k, 3)) * 100.0
            got[:5] = want[:5]
        want_pub, want_scales = numpy_publish(w, want, p0, v0, poses, max_speed,
                                              max_acceleration, allowed)  # fmt: skip
        got_pub, got_scales = kernel_publish(w, got, p0, v0, poses, max_speed, max_acceleration,
                                             allowed)  # fmt: skip
        assert bitwise(got_pub, want_pub), ('published', trial)
        assert bitwise(got_scales, want_scales), ('scales', trial)


def check_random_radii(rng) -> None:
    for trial in range(1500):
        k = int(rng.choice([1, 2, 3, 10, 100]))
        window = int(rng.choice([1, 2, 5, 50]))
        min_errors = int(rng.choice([1, 5]))
        radius = random_state(rng, k, window, min_errors, scarce=rng.random() < 0.1)
        scales = random_scales(rng, k)
        before = radius_state(radius)
        want = radius.radii(scales)
        got = kernel_radii(radius, scales)
        assert same_state(radius_state(radius), before)
        assert bitwise(got, want), ('radii', trial, k, window, min_errors)


def check_random_updates(rng) -> None:
    for trial in range(1500):
        k = int(rng.choice([1, 3, 10, 100]))
        window = int(rng.choice([1, 5, 50]))
        radius = random_state(rng, k, window, 5)
        n = int(rng.integers(0, 2 * k + 2))
        if rng.random() < 0.5:
            ks = np.sort(rng.choice(k, size=min(n, k), replace=False))
        else:  # a horizon more than once: numpy's fancy assignment (the last write wins)
            ks = rng.integers(0, k, size=n)
        ks = ks.astype(np.intp)
        radii_then = rng.lognormal(0.0, 1.0, size=len(ks))
        errors = radii_then * rng.choice([0.5, 1.0, 2.0], size=len(ks))  # (ties: no miss)
        errors[rng.random(len(ks)) < 0.05] = np.nan
        radii_then[rng.random(len(ks)) < 0.05] = np.nan
        scales = random_scales(rng, len(ks)) if len(ks) else np.empty(0)
        state = radius_state(radius)
        radius.update(ks, errors, radii_then, scales)
        want = radius_state(radius)
        set_state(radius, state)
        kernel_update(radius, ks, errors, radii_then, scales)
        assert same_state(radius_state(radius), want), ('update', trial)


def random_scores(rng, pending: int, k: int, once: bool) -> ant.Scores:
    """Scored poses as :meth:`Ensemble.score` gives them: by slot (in slot order, runs of one
    prediction), then horizon (each once per prediction); with ``once``, no horizon twice."""
    slots, horizons = [], []
    taken: set[int] = set()
    chosen = rng.choice(pending, size=min(pending, int(rng.integers(0, 4))), replace=False)
    for slot in np.sort(chosen):
        ks = np.flatnonzero(rng.random(k) < 0.3)
        if once:
            ks = np.array([j for j in ks if j not in taken], dtype=np.intp)
            taken.update(ks.tolist())
        slots += [slot] * len(ks)
        horizons += ks.tolist()
    n = len(slots)
    squared = rng.lognormal(-2.0, 2.0, size=(n, len(ant.CANDIDATES) + 1))
    squared[rng.random(squared.shape) < 0.02] = np.nan
    return ant.Scores(np.array(slots, np.intp), rng.random(n), np.array(horizons, np.intp),
                      squared)  # fmt: skip


def check_random_scored(rng) -> None:
    for trial in range(1500):
        k, pending = int(rng.choice([1, 5, 100])), int(rng.choice([1, 4, 57]))
        radius = random_state(rng, k, int(rng.choice([5, 50])), 5)
        scored = random_scores(rng, pending, k, once=rng.random() < 0.5)
        radii_table = rng.lognormal(-1.0, 1.0, size=(pending, k))
        radii_table[rng.random(radii_table.shape) < 0.05] = np.nan  # (a grounded prediction's)
        scales_table = rng.lognormal(-2.0, 1.0, size=(pending, k))
        state = radius_state(radius)
        numpy_scored(radius, scored, radii_table, scales_table)
        want = radius_state(radius)
        set_state(radius, state)
        kernel_scored(radius, scored, radii_table, scales_table)
        assert same_state(radius_state(radius), want), ('scored', trial)


def check_random(seed: int = 20260516) -> None:
    rng = np.random.default_rng(seed)
    check_random_radii(rng)
    check_random_updates(rng)
    check_random_scored(rng)
    if kc.AVAILABLE:
        check_random_candidates(rng)


# ------------------------------------------------------------- recorded arguments


@contextlib.contextmanager
def recording():
    """Record the arguments (and results) of the anticipator's combine and radius steps while
    the engine runs: yields the lists ``combine``, ``radii``, ``update`` and ``scored``."""
    calls: dict[str, list] = {'combine': [], 'radii': [], 'update': [], 'scored': []}
    originals = {
        (ant.Anticipator, 'combine_steps'): ant.Anticipator.combine_steps,
        (ant.Anticipator, 'update_steps'): ant.Anticipator.update_steps,
        (ant.CoverageRadius, 'radii'): ant.CoverageRadius.radii,
        (ant.CoverageRadius, 'update'): ant.CoverageRadius.update,
        (ant.Ensemble, 'score'): ant.Ensemble.score,
        (ant.Ensemble, 'add'): ant.Ensemble.add,
    }
    combine, update_steps = ant.Anticipator.combine_steps, ant.Anticipator.update_steps
    radii, update = ant.CoverageRadius.radii, ant.CoverageRadius.update
    score, add = ant.Ensemble.score, ant.Ensemble.add

    def combine_rec(self, t, model_positions, measured, coupling, center=None):
        hist = self.history
        cfg = self.config
        p0, v0 = (measured[ant.POSITION], measured[ant.VELOCITY]) if center is None else center
        record = dict(
            measured=np.array(measured, float), coupling=np.array(coupling, float),
            poses=self.poses.copy(), model=np.array(model_positions, float),
            recent=hist.measured[hist.last(cfg.centroid_window)].copy(),
            p0=np.array(p0, float), v0=np.array(v0, float), max_speed=cfg.max_speed,
            max_acceleration=cfg.max_acceleration, grounded=self.trust.grounded,
        )  # fmt: skip
        self.guard._added = None
        result = yield from combine(self, t, model_positions, measured, coupling, center)
        record.update(weights=result.weights.copy(), positions=result.positions.copy(),
                      radius=result.radius.copy(), scales=calls['radii'][-1]['scales'],
                      paths=self.guard._added)  # fmt: skip
        calls['combine'].append(record)
        return result

    def update_steps_rec(self, t, theta, coupling):
        before = radius_state(self.radius)
        radii_table, scales_table = self._radii.copy(), self._scales.copy()
        result = yield from update_steps(self, t, theta, coupling)
        calls['scored'].append(dict(
            before=before, after=radius_state(self.radius), scored=self.guard._scored,
            radii=radii_table, scales=scales_table, gain=self.radius.gain,
            coverage=self.radius.coverage, window=self.radius.window,
        ))  # fmt: skip
        return result

    def radii_rec(self, scales):
        state = radius_state(self)
        out = radii(self, scales)
        calls['radii'].append(dict(state=state, prior=self.prior.copy(),
                                   offsets=self.offsets.copy(), min_errors=self.min_errors,
                                   scales=np.array(scales, float), out=out.copy()))  # fmt: skip
        return out

    def update_rec(self, ks, errors, radii_then, scales):
        before = radius_state(self)
        update(self, ks, errors, radii_then, scales)
        calls['update'].append(dict(
            before=before, after=radius_state(self), ks=np.array(ks, np.intp),
            errors=np.array(errors, float), radii=np.array(radii_then, float),
            scales=np.array(scales, float), gain=self.gain, coverage=self.coverage,
            window=self.window,
        ))  # fmt: skip

    def score_rec(self, *args):
        scored = score(self, *args)
        self._scored = ant.Scores(*(np.array(x) for x in (
            scored.slots, scored.issued, scored.horizons, scored.squared)))  # fmt: skip
        return scored

    def add_rec(self, t, paths):
        self._added = np.array(paths, float)
        return add(self, t, paths)

    # (the package's numpy code runs, and is recorded: not its compiled path)
    from cloe_ros.core import prediction

    compiled = ant.COMPILED
    ant.COMPILED = prediction.COMPILED = False
    ant.Anticipator.combine_steps, ant.Anticipator.update_steps = combine_rec, update_steps_rec
    ant.CoverageRadius.radii, ant.CoverageRadius.update = radii_rec, update_rec
    ant.Ensemble.score, ant.Ensemble.add = score_rec, add_rec
    try:
        yield calls
    finally:
        for (cls, name), method in originals.items():
            setattr(cls, name, method)
        ant.COMPILED = prediction.COMPILED = compiled


def record(bag: Path) -> dict[str, list]:
    from test.golden_outputs import golden_outputs

    with recording() as calls:
        golden_outputs(bag)
    return calls


def new_radius(r: dict) -> ant.CoverageRadius:
    errors, count, level = r['state'] if 'state' in r else r['before']
    radius = ant.CoverageRadius(r.get('offsets', np.arange(1, len(count) + 1) * 0.1), 0.95,
                                window=errors.shape[1])  # fmt: skip
    set_state(radius, (errors, count, level))
    for name in ('gain', 'coverage', 'min_errors'):
        if name in r:
            setattr(radius, name, r[name])
    if 'prior' in r:
        radius.prior = r['prior']
    return radius


def check_recorded(calls: dict[str, list], exact: bool = True) -> dict[str, int]:
    """Kernels against the recorded runs' own values (bitwise when ``exact``, else to
    round-off); also checks that the transcriptions above are the package's code. Returns how
    many calls of each were checked."""
    same = bitwise if exact else (lambda a, b: np.allclose(a, b, rtol=1e-12, atol=1e-12,
                                                           equal_nan=True))  # fmt: skip
    for i, c in enumerate(calls['combine']):
        args = (c['measured'], c['coupling'], c['poses'], c['recent'], c['model'])
        allowed = np.ones(len(ant.CANDIDATES), dtype=bool)
        if c['grounded']:
            allowed[[0, 4]] = False
        envelope = (c['p0'], c['v0'], c['poses'], c['max_speed'], c['max_acceleration'], allowed)
        want = numpy_candidates(*args)
        if c['paths'] is not None:  # (what the guard was given: the package's own values)
            assert bitwise(want[:5], c['paths'][:5]), ('transcription', i)
            assert bitwise(c['paths'][5], c['positions']), ('transcription', i)
        want_pub, want_scales = numpy_publish(c['weights'], want, *envelope)
        assert bitwise(want_pub, c['positions']) and bitwise(want_scales, c['scales']), i
        got = kernel_candidates(*args)
        assert same(got[:5], want[:5]), ('candidates', i)
        got_pub, got_scales = kernel_publish(c['weights'], got, *envelope)
        assert same(got_pub, c['positions']), ('published', i)
        assert same(got_scales, c['scales']), ('scales', i)
    for i, r in enumerate(calls['radii']):
        radius = new_radius(r)
        assert bitwise(radius.radii(r['scales']), r['out']), ('transcription', i)
        assert same(kernel_radii(radius, r['scales']), r['out']), ('radii', i)
    for i, u in enumerate(calls['update']):
        radius = new_radius(u)
        kernel_update(radius, u['ks'], u['errors'], u['radii'], u['scales'])
        assert same_state(radius_state(radius), u['after']), ('update', i)
    for i, s in enumerate(calls['scored']):
        radius = new_radius(s)
        numpy_scored(radius, s['scored'], s['radii'], s['scales'])
        assert same_state(radius_state(radius), s['after']), ('transcription', i)
        radius = new_radius(s)
        kernel_scored(radius, s['scored'], s['radii'], s['scales'])
        assert same_state(radius_state(radius), s['after']), ('scored', i)
    return {name: len(value) for name, value in calls.items()}


def recorded_bags() -> list[Path]:
    return [REPO / 'bags' / 'position', *([B3] if B3.is_dir() else [])]


# ------------------------------------------------------------------------- tests

CHILD = r'''
import sys
from pathlib import Path
from test.golden_outputs import check_pinned_kernels
check_pinned_kernels()
from test.core import test_kernels_combine as t
if sys.argv[1] == 'random':
    t.check_random()
else:
    counts = t.check_recorded(t.record(Path(sys.argv[1])))
    assert counts['combine'] > 50 and counts['scored'] > 50 and counts['update'] > 50, counts
print('ok')
'''


def pinned(what: str) -> None:
    done = run_pinned_script(CHILD, what)
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr[-3000:]


def test_the_kernels_are_the_numpy_code_bit_for_bit_on_random_arguments_under_the_pin():
    pinned('random')


@needs_blas
@pytest.mark.parametrize('bag', recorded_bags(), ids=lambda bag: bag.name)
def test_the_kernels_are_the_numpy_code_bit_for_bit_on_recorded_flights_under_the_pin(bag):
    pinned(str(bag))


@needs_blas
def test_unpinned_the_kernels_agree_with_numpy_to_round_off():
    """Whatever numpy's loops and libm's variants (the turn candidate's sin and cos, numpy's
    SIMD sums): to 1e-12 on the first flight; the radius's updates, which only divide, compare
    and add, exactly (they are bitwise on random arguments too)."""
    calls = record(REPO / 'bags' / 'position')
    check_recorded(calls, exact=False)
    rng = np.random.default_rng(7)
    check_random_radii(rng)
    check_random_updates(rng)
    check_random_scored(rng)


def test_the_kernels_constants_are_the_anticipators():
    assert kc._POS == tuple(ant.POSITION) and kc._VEL == tuple(ant.VELOCITY)
    assert (kc.SCALE_FLOOR, kc.SCALE_GROWTH) == (ant.SCALE_FLOOR, ant.SCALE_GROWTH)
