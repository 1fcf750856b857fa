"""The model runs' kernels (cloe_ros/core/kernels_models.py) give the numpy code's values bit for
bit under the golden test's pinned kernels: the closed loop's propagation, the recent offset fit,
the reference trust's replay and statistics, on random and edge-case arguments and on the
arguments the numpy code receives while the engine runs recorded flights."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloe_ros.core import kernels_models as km
from test.golden_outputs import REPO, run_pinned_script

pytestmark = pytest.mark.skipif(not km.AVAILABLE, reason="numpy's OpenBLAS not found")

RANDOM = r'''
import math
import numpy as np
from cloe_ros.core import kernels_models as km
from cloe_ros.core.anticipation import AnticipationConfig, Anticipator, ReferenceTrust, run
from cloe_ros.core.identifier import cascade_prior
from cloe_ros.core.model import discretise, propagate
from cloe_ros.core.prediction import fit_reference_offset, fit_reference_offsets
from test.golden_outputs import check_pinned_kernels

check_pinned_kernels()
rng = np.random.default_rng(7)
theta0, coupling0 = cascade_prior()


def model(kind):
    """(ad, bd): an identified-like model as discretise returns it (views of one array), the
    same copied, or a dense random one."""
    if kind < 2:
        theta = theta0 * (1.0 + 0.3 * rng.normal(size=16))
        coupling = coupling0 * (1.0 + 0.1 * rng.normal(size=2))
        ad, bd = discretise(theta, coupling, [0.1, 0.01, 0.05][rng.integers(3)])
        return (ad, bd) if kind == 0 else (ad.copy(), bd.copy())
    return rng.normal(size=(12, 12)) * 0.3, rng.normal(size=(12, 4))


def fit_numpy(ad, bd, states, refs, ridge, whole):
    try:
        if whole:
            return fit_reference_offset(ad, bd, states, refs, ridge)
        return fit_reference_offsets(ad[None], bd[None], states[None], refs[None], ridge)[0]
    except np.linalg.LinAlgError:
        return None


def check_fit(ad, bd, states, refs, ridge):
    for whole, kernel in ((False, km.fit_offset_one), (True, km.recent_offset_one)):
        if not whole and len(states) == 0:
            continue
        want = fit_numpy(ad, bd, states, refs, ridge, whole)
        got = np.full(4, np.nan)
        info = kernel(ad, bd, states, refs, ridge, got)
        assert (info != 0) == (want is None), (whole, len(states), ridge, info)
        assert want is None or np.array_equal(got, want, equal_nan=True), (whole, len(states))


# the closed loop's run: every horizon length, identified-like and dense models, the views
# discretise returns, no step at all
for trial in range(300):
    ad, bd = model(trial % 3)
    n = [0, 1, 2, 10, 50][trial % 5] if trial < 50 else int(rng.integers(1, 120))
    x0 = rng.normal(size=12) * 10.0 ** rng.integers(-3, 3)
    refs = rng.normal(size=(n, 4)) * 5.0
    want = propagate(ad[None], bd[None], x0[None], refs[None])[0]
    stacked = propagate(np.array([ad]), np.array([bd]), np.array([x0]), np.array([refs]))[0]
    got = np.full((n, 12), np.nan)
    km.propagate_one(ad, bd, x0, refs, got)
    assert np.array_equal(got, want) and np.array_equal(got, stacked), trial

# the offset fit: windows of 0 to 24 samples, ridges, non-finite windows, singular systems
for trial in range(300):
    ad, bd = model(trial % 3)
    m1 = [0, 1, 2, 6][trial % 4] if trial < 40 else int(rng.integers(2, 25))
    states = rng.normal(size=(m1, 12)) * 10.0 ** rng.integers(-2, 2)
    refs = rng.normal(size=(m1, 4))
    ridge = [1e-3, 0.0, 1.0, 1e-12][trial % 4 if trial >= 40 else trial // 4 % 4]
    check_fit(ad, bd, states, refs, ridge)
    if m1 and trial % 5 == 0:
        states[rng.integers(m1), rng.integers(12)] = [np.nan, np.inf, -np.inf][trial % 3]
        check_fit(ad, bd, states, refs, ridge)
    if m1 and trial % 7 == 0:
        refs[rng.integers(m1), rng.integers(4)] = np.nan
        check_fit(ad, bd, states, refs, ridge)
for m1 in (1, 2, 6):  # a reference that drives nothing, no ridge: singular, numpy raises
    ad, bd = model(1)
    bd[:, 2] = 0.0
    states, refs = rng.normal(size=(m1, 12)), rng.normal(size=(m1, 4))
    check_fit(ad, bd, states, refs, 0.0)
    assert km.fit_offset_one(ad, bd, states, refs, 0.0, np.empty(4)) > 0

# the trust's replay, against the method with its judging model given: histories of every
# length (none, shorter than the replay), jittered times, NaN rows, now before and after the end
for trial in range(300):
    ad, bd = model(trial % 3)
    ant = Anticipator(AnticipationConfig(), 0.1, 50, 100.0, 5.0, 0.05)
    size = [0, 1, 50, 99, 101][trial % 5] if trial < 50 else int(rng.integers(0, 300))
    t0 = rng.uniform(0.0, 100.0)
    ts = np.sort(t0 + np.arange(size) / 100.0 + rng.normal(size=size) * 1e-5 * (trial % 2))
    for k in range(size):
        meas = rng.normal(size=12)
        est = meas + 0.1 * rng.normal(size=12)
        logged = rng.normal(size=4)
        if trial % 4 == 1 and rng.random() < 0.03:
            [meas, est, logged][rng.integers(3)][rng.integers(4)] = np.nan
        ant.history.append(ts[k], meas, est, logged, logged)
    t = (ts[-1] if size else t0) - [0.0, 0.003, 0.5, -0.004, 0.02][trial % 5]
    horizon, step = [(1.0, 0.1), (0.25, 0.1), (0.95, 0.1), (1.05, 0.05), (3.0, 0.07)][trial % 5]
    ant.config = AnticipationConfig(trust_horizon=horizon)
    ant.step = step
    ant._judging_model = lambda t, theta, coupling: ((ad, bd), (theta, coupling))
    seen = []
    ant.trust.update = lambda t, miss_ref, miss_free: seen.append((miss_ref, miss_free))
    run(ant._update_trust_steps(t, theta0, coupling0))
    h = ant.history
    miss_ref, miss_free = np.full(4, np.nan), np.full(4, np.nan)
    done = km.trust_replay(h.ordered('t'), h.ordered('estimate'), h.ordered('measured'),
                           h.ordered('logged'), t, step, horizon, ad, bd, miss_ref, miss_free)
    assert done == len(seen), trial
    if seen:
        assert np.array_equal(miss_ref, seen[0][0]) and np.array_equal(miss_free, seen[0][1])

# the trust's statistics, against ReferenceTrust.update: NaN (fresh) statistics, NaN misses,
# ties of the two tests (ratio 1, equal misses; a miss at the floor; floor 0)
for trial in range(1000):
    ratio, floor = [(3.0, 0.3), (1.0, 0.3), (3.0, 0.0), (1.0, 0.0)][trial % 4]
    trust = ReferenceTrust(AnticipationConfig(trust_ratio=ratio, trust_floor=floor))
    for _ in range(int(rng.integers(0, 3))):
        trust.update(rng.uniform(0.0, 5.0), rng.exponential(size=4), rng.exponential(size=4))
    trust.e_ref[rng.random(4) < 0.2] = np.nan
    trust.e_free[rng.random(4) < 0.2] = np.nan
    trust.followed[:] = rng.random(4) < 0.5
    miss_ref, miss_free = 0.3 * rng.exponential(size=4), 0.3 * rng.exponential(size=4)
    if trial % 10 == 0:
        miss_free[rng.integers(4)] = np.nan
    if trial % 3 == 0:
        miss_ref[:] = miss_free
    if trial % 5 == 0:
        miss_ref[rng.integers(4)] = floor
    t = rng.uniform(4.0, 10.0)
    dt = 0.2 if trust._last_t is None else max(t - trust._last_t, 0.0)
    a = 1.0 - math.exp(-dt / trust.config.trust_time)
    e_ref, e_free, followed = trust.e_ref.copy(), trust.e_free.copy(), trust.followed.copy()
    trust.update(t, miss_ref, miss_free)
    every = km.trust_update(e_ref, e_free, followed, miss_ref, miss_free, a, ratio**2,
                            floor**2)
    assert np.array_equal(e_ref, trust.e_ref, equal_nan=True), trial
    assert np.array_equal(e_free, trust.e_free, equal_nan=True), trial
    assert np.array_equal(followed, trust.followed) and every == trust.all_followed, trial
print('ok')
'''

RECORDED = r'''
import math
import sys
from pathlib import Path

import numpy as np
from cloe_ros.core import anticipation, kernels_models as km, prediction

anticipation.COMPILED = prediction.COMPILED = False  # (the numpy code runs, and is recorded)
from test.golden_outputs import check_pinned_kernels, golden_outputs

check_pinned_kernels()
counts = dict.fromkeys(('propagate', 'fit', 'replay', 'early', 'update'), 0)
bad = []
numpy_propagate = anticipation.propagate
numpy_fit = prediction.fit_reference_offsets
numpy_update = anticipation.ReferenceTrust.update
numpy_trust_steps = anticipation.Anticipator._update_trust_steps


def propagate(ad, bd, x0, refs):
    want = numpy_propagate(ad, bd, x0, refs)
    for v in range(len(ad)):
        got = np.empty(want.shape[1:])
        km.propagate_one(ad[v], bd[v], x0[v], refs[v], got)
        counts['propagate'] += 1
        if not np.array_equal(got, want[v]):
            bad.append('propagate')
    return want


def fit(ad, bd, states, refs, ridge):
    want = numpy_fit(ad, bd, states, refs, ridge)
    for v in range(len(ad)):
        counts['fit'] += 1
        for kernel in (km.fit_offset_one, km.recent_offset_one):
            got = np.empty(4)
            if kernel(ad[v], bd[v], states[v], refs[v], ridge, got) or not np.array_equal(
                    got, want[v]):
                bad.append(kernel.__name__)
    return want


seen = []


def update(self, t, miss_ref, miss_free):
    seen.append((miss_ref.copy(), miss_free.copy()))
    dt = 0.2 if self._last_t is None else max(t - self._last_t, 0.0)
    a = 1.0 - math.exp(-dt / self.config.trust_time)
    e_ref, e_free, followed = self.e_ref.copy(), self.e_free.copy(), self.followed.copy()
    numpy_update(self, t, miss_ref, miss_free)
    every = km.trust_update(e_ref, e_free, followed, miss_ref, miss_free, a,
                            self.config.trust_ratio**2, self.config.trust_floor**2)
    counts['update'] += 1
    if not (np.array_equal(e_ref, self.e_ref, equal_nan=True)
            and np.array_equal(e_free, self.e_free, equal_nan=True)
            and np.array_equal(followed, self.followed) and every == self.all_followed):
        bad.append('update')


def trust_steps(self, t, theta, coupling):
    seen.clear()
    result = yield from numpy_trust_steps(self, t, theta, coupling)
    (ad, bd), h = self._judge, self.history  # (the judging model the method used)
    miss_ref, miss_free = np.empty(4), np.empty(4)
    done = km.trust_replay(h.ordered('t'), h.ordered('estimate'), h.ordered('measured'),
                           h.ordered('logged'), t, self.step, self.config.trust_horizon, ad, bd,
                           miss_ref, miss_free)
    counts['replay' if done else 'early'] += 1
    if done != len(seen) or done and not (np.array_equal(miss_ref, seen[0][0])
                                          and np.array_equal(miss_free, seen[0][1])):
        bad.append('replay')
    return result


anticipation.propagate = propagate
prediction.fit_reference_offsets = fit
anticipation.ReferenceTrust.update = update
anticipation.Anticipator._update_trust_steps = trust_steps
for bag in sys.argv[1:]:
    golden_outputs(Path(bag))
assert not bad, (bad[:10], counts)
assert min(counts.values()) > 0, counts
print('ok')
'''


def run_pinned(code: str, *args: str) -> None:
    done = run_pinned_script(code, *args)
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr[-3000:]


def test_the_model_kernels_are_numpys_bit_for_bit_on_random_and_edge_cases():
    """Propagation, offset fit (and its window checks, singular systems), trust replay (short,
    empty and non-finite histories) and trust statistics (NaN, ties), under the pin."""
    run_pinned(RANDOM)


def test_the_model_kernels_are_numpys_bit_for_bit_on_recorded_flights():
    """Every model run, offset fit, replay and trust update of the engine on a recorded flight
    and a corpus flight, against the numpy code's, under the pin."""
    from test.corpus import FLIGHTS

    flights = [REPO / 'bags' / 'position']
    flights += sorted(FLIGHTS.glob('nanobench_*'))[:1] if FLIGHTS.is_dir() else []
    run_pinned(RECORDED, *map(str, flights))


def test_the_model_kernels_agree_with_numpy_on_this_machine():
    """In this process, whatever its kernels: the same values to round-off (the bitwise
    equality is the pinned tests')."""
    from cloe_ros.core.identifier import cascade_prior
    from cloe_ros.core.model import discretise, propagate
    from cloe_ros.core.prediction import fit_reference_offsets

    rng = np.random.default_rng(3)
    theta, coupling = cascade_prior()
    ad, bd = discretise(theta, coupling, 0.1)
    x0, refs = rng.normal(size=12), rng.normal(size=(50, 4))
    got = np.empty((50, 12))
    km.propagate_one(ad, bd, x0, refs, got)
    want = propagate(ad[None], bd[None], x0[None], refs[None])[0]
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    states, refs = rng.normal(size=(6, 12)), rng.normal(size=(6, 4))
    got = np.empty(4)
    assert km.fit_offset_one(ad, bd, states, refs, 1e-3, got) == 0
    want = fit_reference_offsets(ad[None], bd[None], states[None], refs[None], 1e-3)[0]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert km.recent_offset_one(ad, bd, states[:1], refs[:1], 1e-3, got) == 0
    assert not got.any()
    e_ref, e_free = np.full(4, np.nan), np.array([1.0, 1.0, np.nan, 1.0])
    followed = np.ones(4, bool)
    miss_ref, miss_free = np.array([3.0, 0.1, 1.0, 0.0]), np.array([0.5, 0.1, 0.1, 0.0])
    a = 1.0 - math.exp(-0.2)
    every = km.trust_update(e_ref, e_free, followed, miss_ref, miss_free, a, 9.0, 0.09)
    np.testing.assert_array_equal(e_ref, miss_ref**2)  # (fresh: the new values)
    np.testing.assert_array_equal(e_free, [1.0 + a * (0.25 - 1.0), 1.0 + a * (0.1**2 - 1.0),
                                           0.1**2, 1.0 - a])  # fmt: skip
    np.testing.assert_array_equal(followed, [False, True, False, True])
    assert not every
