"""The ensembles' weights and the intent's candidates compiled (cloe_ros/core/kernels_ensemble.py)
are the numpy code's bit for bit under the golden test's pinned kernels: on random inputs (never,
partly and fully scored ensembles, the guard's five candidates of its six columns, masks without
the first candidate, singular systems; short reference histories that skip the fits, jumps,
holds, NaN, irregular sampling, a rounding tie of the subsampling step) and on the arguments the
engine passes while it runs recorded flights. Unpinned, where numpy runs its own SIMD log, pow,
cos and sin, they agree to round-off."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cloe_ros.core import anticipation as an
from cloe_ros.core import kernels_ensemble as ke
from test.corpus import FLIGHTS
from test.golden_outputs import REPO, run_pinned_script

pytestmark = pytest.mark.skipif(not ke.AVAILABLE, reason="numpy's OpenBLAS not found")

#: The statuses the kernels return where the numpy code raises these.
RAISES = ((np.linalg.LinAlgError, ke.LINALG_ERROR), (IndexError, ke.INDEX_ERROR),
          ((ValueError, OverflowError, ZeroDivisionError), ke.VALUE_ERROR))  # fmt: skip
#: Unpinned, the kernels' libm against numpy's SIMD log, pow, cos and sin: round-off, carried
#: through the solves.
RTOL, ATOL = 1e-12, 1e-13
RECORDED = (REPO / 'bags' / 'position', FLIGHTS / 'nanobench_B3_figure8_fast_rep1')


def same(got: np.ndarray, want: np.ndarray, exact: bool) -> bool:
    """Bit for bit (NaN where NaN) when ``exact``, else to round-off."""
    got, want = np.asarray(got, float), np.asarray(want, float)
    if got.shape != want.shape or not np.array_equal(np.isnan(got), np.isnan(want)):
        return False
    if not exact:
        return np.allclose(got, want, rtol=RTOL, atol=ATOL, equal_nan=True)
    bits = np.where(np.isnan(got), 0, got.view(np.uint64))
    return np.array_equal(bits, np.where(np.isnan(want), 0, want.view(np.uint64)))


def numpy_status(call) -> tuple[int, np.ndarray | None]:
    """``call()``'s value with status OK, or the status of the error it raises."""
    try:
        return ke.OK, np.asarray(call())
    except Exception as err:
        for kind, status in RAISES:
            if isinstance(err, kind):
                return status, None
        raise


# ---------------------------------------------------------------------------------- ensemble


def numpy_weights(cross, scored, offsets, min_growth, m, allowed):
    """What the package computes: ``Ensemble.weights_steps`` (m = M), the guard's
    ``Anticipator._weights_steps`` (its five candidates of six columns)."""
    ens = an.Ensemble([f'c{i}' for i in range(cross.shape[1])], offsets, 3, 5.0, 0.2, 4,
                      min_growth)  # fmt: skip
    ens.cross[:], ens.scored[:] = cross, scored
    if m == cross.shape[1]:
        return numpy_status(lambda: an.run(ens.weights_steps(allowed)))
    assert m == len(an.CANDIDATES) == cross.shape[1] - 1
    guard = SimpleNamespace(guard=ens, poses=ens.offsets)
    return numpy_status(lambda: an.run(an.Anticipator._weights_steps(guard, allowed)))


def kernel_weights(cross, scored, offsets, min_growth, m, allowed):
    out = np.full((len(offsets), m), np.nan)
    status = ke.ensemble_weights(cross, scored, offsets, np.asarray(min_growth, float), m,
                                 np.asarray(allowed, bool), out)  # fmt: skip
    return status, out


def random_cross(rng, k: int, m: int, kind: str) -> np.ndarray:
    """Error cross-products (K, M, M) as the scores make them (mean outer products of errors
    growing with the horizon), or of a kind that tests an edge."""
    growth = (1.0 + np.arange(k))[:, None, None, None] ** rng.uniform(0.0, 2.0, (1, m, 1, 1))
    errors = rng.normal(size=(k, m, 12, 3)) * rng.uniform(0.01, 1.0, (1, m, 1, 1)) * growth
    if kind == 'duplicate':  # two candidates alike: rank-deficient without the ridge
        errors[:, 2] = errors[:, 1]
    if kind == 'perfect':  # one candidate without error
        errors[:, 3] = 0.0
    if kind == 'correlated':  # the others beat the first only combined: negative weights
        errors[:, 1:] += 3.0 * errors[:, :1]
    cross = np.einsum('kmnd,kpnd->kmp', errors, errors) / 12.0
    if kind == 'indefinite':
        cross += rng.normal(size=cross.shape)
    if kind == 'huge':  # overflow: inf and NaN through the extrapolation and the solves
        cross[:, 0, :] *= 1e300
    return cross


def random_scored(rng, k: int, kind: str) -> np.ndarray:
    scored = np.zeros(k, bool)
    if kind == 'all':
        scored[:] = True
    elif kind == 'prefix':
        scored[: rng.integers(1, k + 1)] = True
    elif kind == 'random':
        scored[:] = rng.uniform(size=k) < 0.3
    elif kind == 'first':
        scored[0] = True
    elif kind == 'last':
        scored[-1] = True
    elif kind == 'two':
        scored[rng.choice(k, size=min(2, k), replace=False)] = True
    return scored


def random_allowed(rng, m: int, kind: str) -> np.ndarray:
    allowed = np.ones(m, bool)
    if kind == 'not first':
        allowed[0] = False
    elif kind == 'guard grounded':
        allowed[[0, m - 1]] = False
    elif kind == 'random':
        allowed[:] = rng.uniform(size=m) < 0.6
    elif kind == 'one':
        allowed[:] = False
        allowed[rng.integers(m)] = True
    elif kind == 'none':
        allowed[:] = False
    return allowed


def singular_cross(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Cross-products (1, M, M) whose shrunk system on the candidates 0 and 1 is exactly
    singular (every entry one value), and that mask: numpy raises."""
    for d in np.linspace(1.0, 2.0, 101):
        cross = np.diag(np.full(m, d))[None]
        on = (0.9 * d + 0.1 * d) + 1e-12 * (1.0 + d)
        guess = on / 0.9
        for o in guess + np.arange(-8, 9) * np.spacing(guess):
            if 0.9 * o == on:
                cross[0, 0, 1] = cross[0, 1, 0] = o
                return cross, np.arange(m) < 2
    raise AssertionError('no exactly singular system found')


def check_weights(exact: bool, seed: int = 0) -> dict[str, int]:
    """The kernel against the numpy code on random ensembles, one vehicle at a time and
    against the batched ``SimplexWeights.answer_all``. Returns counts of what was covered."""
    rng = np.random.default_rng(seed)
    seen = {'cases': 0, 'raised': 0, 'singular': 0, 'extrapolated': 0, 'dropped': 0,
            'batched': 0}
    batch = []
    cases = [(k, mm, m) for k in (1, 2, 3, 7, 100) for mm, m in ((4, 4), (6, 6), (6, 5))]
    for k, mm, m in cases:
        for cross_kind in ('psd', 'duplicate', 'perfect', 'correlated', 'indefinite', 'huge'):
            for scored_kind in ('none', 'all', 'prefix', 'random', 'first', 'last', 'two'):
                for allowed_kind in ('all', 'not first', 'guard grounded', 'random', 'one',
                                     'none'):  # fmt: skip
                    if allowed_kind == 'guard grounded' and m != 5:
                        continue
                    step = rng.choice([0.1, 0.2])
                    offsets = step * (np.arange(k) + rng.integers(0, 2))  # poses, or starts
                    growth = (an.GROWTH if mm == 6 else
                              rng.choice([0.0, 2.0, 4.0], size=mm) * (rng.uniform() < 0.5))
                    cross = random_cross(rng, k, mm, cross_kind)
                    scored = random_scored(rng, k, scored_kind)
                    allowed = random_allowed(rng, m, allowed_kind)
                    args = (cross, scored, offsets, growth, m, allowed)
                    with np.errstate(all='ignore'):
                        want_status, want = numpy_weights(*args)
                        got_status, got = kernel_weights(*args)
                    assert got_status == want_status, (args, got_status, want_status)
                    assert want is None or same(got, want, exact), (args, got, want)
                    seen['cases'] += 1
                    seen['raised'] += want is None
                    last = np.flatnonzero(scored)[-1] if scored.any() else k - 1
                    seen['extrapolated'] += bool(last < k - 1)
                    seen['dropped'] += bool(want is not None and scored.any()
                                            and ((want == 0) & allowed).any())  # fmt: skip
                    if scored.any() and want is not None and len(batch) < 40:
                        ens_cross = np.empty((k, m, m))
                        ke.expected_cross(cross, scored, offsets, growth, m, ens_cross)
                        batch.append((ens_cross, allowed, got))
    for cross, want_singular in (singular_cross(4), singular_cross(6)):
        scored = np.ones(1, bool)
        for allowed in (want_singular, np.ones(len(want_singular), bool)):
            args = (cross, scored, np.array([0.1]), np.zeros(cross.shape[1]), cross.shape[1],
                    allowed)  # fmt: skip
            want_status, want = numpy_weights(*args)
            got_status, got = kernel_weights(*args)
            assert got_status == want_status and (want is None or same(got, want, exact))
            seen['singular'] += got_status == ke.LINALG_ERROR
    # several vehicles' systems solved together, as run_together asks: each its own answer
    for first in range(0, len(batch), 8):
        group = [b for b in batch[first:first + 8] if b[0].shape[1] == batch[first][0].shape[1]]
        with np.errstate(all='ignore'):
            answers = an.SimplexWeights.answer_all([an.SimplexWeights(c, a) for c, a, _ in group])
        for (_, _, got), want in zip(group, answers):
            assert same(got, want, exact)
            seen['batched'] += 1
    return seen


# ------------------------------------------------------------------------------------ intent


def numpy_candidates(t, r, ahead, window, hz=None):
    """``run(Intent(window, ahead).candidates_steps(t, r))`` (with the subsampling rate
    ``hz``, default ``Intent.SUBSAMPLE_HZ``)."""
    intent = an.Intent(window, ahead)
    if hz is not None:
        intent.SUBSAMPLE_HZ = hz
    return numpy_status(lambda: an.run(intent.candidates_steps(t, r)))


def kernel_candidates(t, r, ahead, window, hz=None):
    out = np.full((len(an.INTENT_MODELS), len(ahead), 4), np.nan)
    hz = an.Intent.SUBSAMPLE_HZ if hz is None else hz
    status = ke.intent_candidates(np.ascontiguousarray(t, float),
                                  np.ascontiguousarray(r, float), ahead, an.Intent.OMEGAS,
                                  window, hz, out)  # fmt: skip
    return status, out


def random_reference(rng, n: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (n,) s, increasing, now at some time of the flight, and references (n, 4): a
    circle, an ellipse or a line, per kind with a jump, held, noisy, a NaN, or sparse."""
    rate = {'sparse': 30.0, 'uneven': 100.0}.get(kind, 100.0)
    dt = 1.0 / rate * (1.0 + (0.3 if kind == 'uneven' else 0.02) * rng.uniform(-1, 1, n))
    now = rng.uniform(5.0, 500.0)
    t = now - (np.cumsum(dt[::-1])[::-1] - dt)  # (the last at now)
    period = rng.uniform(1.5, 30.0)
    phase = 2.0 * np.pi * t / period
    radius = rng.uniform(0.2, 3.0, 2)
    r = np.column_stack([radius[0] * np.cos(phase), radius[1] * np.sin(phase),
                         rng.uniform(-3, 3) + 0.1 * t,
                         1.0 + 0.2 * np.sin(0.5 * phase)])  # fmt: skip
    if kind == 'line':
        r[:, :2] = rng.uniform(-1, 1, 2) * (t - now)[:, None] + rng.uniform(-5, 5, 2)
    if kind == 'noisy':
        r += rng.normal(size=r.shape) * 0.05
    if kind == 'hold' and n:
        r[:] = r[-1]
    if kind in ('jump', 'late jump') and n > 3:
        at = rng.integers(1, n) if kind == 'jump' else n - rng.integers(1, 4)
        r[at:, [0, 1, 3]] += rng.uniform(0.5, 3.0, 3)
    if kind == 'nan' and n:
        r[rng.integers(n), rng.integers(4)] = np.nan
    return t, r


def check_candidates(exact: bool, seed: int = 1) -> dict[str, int]:
    """The kernel against the numpy code on random references, and the harmonic fits against
    ``HarmonicFits.answer_all`` of one request and of several. Returns counts of what was
    covered."""
    rng = np.random.default_rng(seed)
    seen = {'cases': 0, 'raised': 0, 'jump': 0, 'linear': 0, 'harmonic': 0}
    lengths = (0, 1, 2, 3, 4, 6, 40, 60, 100, 120, 149, 152, 200, 351, 400)
    kinds = ('circle', 'line', 'noisy', 'hold', 'jump', 'late jump', 'nan', 'sparse', 'uneven')
    for n in lengths:
        for kind in kinds:
            for window, starts in ((3.0, 0.1 * np.arange(100)), (1.0, 0.2 * np.arange(7))):
                t, r = random_reference(rng, n, kind)
                with np.errstate(all='ignore'):
                    want_status, want = numpy_candidates(t, r, starts, window)
                    got_status, got = kernel_candidates(t, r, starts, window)
                assert got_status == want_status, (n, kind, got_status, want_status)
                assert want is None or same(got, want, exact), (n, kind, got, want)
                seen['cases'] += 1
                seen['raised'] += want is None
                if want is not None and n >= 3:
                    jumped = an.last_jump(r[:, an.POSITION_CHANNELS])
                    seen['jump'] += jumped > 0
                    seen['linear'] += not np.array_equal(want[1], want[0], equal_nan=True)
                    seen['harmonic'] += not np.array_equal(want[2], want[0], equal_nan=True)
    # the subsampling step (samples 1/64 s apart): rounding ties to even (2.5 -> 2, 3.5 -> 4,
    # 4.5 -> 4, 0.5 -> 0, so 1), a NaN (ValueError), a zero rate (ZeroDivisionError), a step
    # longer than the history
    t = -np.arange(200)[::-1] / 64.0
    r = np.column_stack([np.sin(t), np.cos(t), t, 1.0 + 0.0 * t])
    for hz in (25.6, 64.0 / 3.5, 64.0 / 4.5, 128.0, 12.8, np.nan, 0.0, 1e-300):
        want_status, want = numpy_candidates(t, r, 0.1 * np.arange(20), 3.0, hz)
        got_status, got = kernel_candidates(t, r, 0.1 * np.arange(20), 3.0, hz)
        assert got_status == want_status and (want is None or same(got, want, exact)), hz
    # the harmonic fits of one series, against the batched request's answer
    requests = []
    for _ in range(6):
        t, r = random_reference(rng, 70, 'noisy')
        t = (t - t[-1]) * 3.0
        request = an.HarmonicFits(t, r, 0.1 * np.arange(100), an.Intent.OMEGAS, an.XY)
        requests.append(request)
        (want_separate, want_joint), = an.HarmonicFits.answer_all([request])
        separate, joint = np.empty((100, 4)), np.empty((100, 2))
        status = ke.harmonic_fits(t, r, request.ahead, request.omegas, request.joint, separate,
                                  joint)  # fmt: skip
        assert status == ke.OK and same(separate, want_separate, exact)
        assert same(joint, want_joint, exact)
    for request, (want_separate, want_joint) in zip(requests,
                                                    an.HarmonicFits.answer_all(requests)):
        separate, joint = np.empty((100, 4)), np.empty((100, 2))
        ke.harmonic_fits(request.t, request.y, request.ahead, request.omegas, request.joint,
                         separate, joint)  # fmt: skip
        assert same(separate, want_separate, exact) and same(joint, want_joint, exact)
    # the pieces: median and last jump (ties, even and odd lengths, NaN)
    for n in range(1, 40):
        for x in (rng.normal(size=n), rng.integers(0, 3, n).astype(float)):
            assert same(ke.median(x), an.median(x), True)
            x[rng.integers(n)] = np.nan
            assert np.isnan(ke.median(x)) and np.isnan(an.median(x))
        r = np.cumsum(rng.normal(size=(n, 3)) * 0.01, axis=0)
        if n > 4:
            r[rng.integers(1, n):] += 1.0
        assert ke.last_jump(r, 10.0, 0.1) == an.last_jump(r)
    return seen


# ----------------------------------------------------------------------------------- recorded


def check_recorded(exact: bool, bags=RECORDED) -> dict[str, int]:
    """The kernels against the numpy code on the arguments ``Ensemble.weights_steps``,
    ``Anticipator._weights_steps`` and ``Intent.candidates_steps`` receive while the engine
    runs ``bags`` (those that are there), and their values (as the fleet answers them: the
    batched requests). Returns counts of what was compared."""
    from test.golden_outputs import golden_outputs

    seen = {'bags': 0, 'ensemble': 0, 'guard': 0, 'intent': 0, 'partly scored': 0,
            'linear': 0, 'harmonic': 0}  # fmt: skip
    weights_steps = an.Ensemble.weights_steps
    guard_steps = an.Anticipator._weights_steps
    candidates_steps = an.Intent.candidates_steps

    def check_weights(what, ens, allowed, want):
        m = want.shape[1]
        allowed = np.ones(m, bool) if allowed is None else np.asarray(allowed, bool)
        got = np.full(want.shape, np.nan)
        status = ke.ensemble_weights(ens.cross, ens.scored, ens.offsets, ens.min_growth, m,
                                     allowed, got)  # fmt: skip
        assert status == ke.OK and same(got, want, exact), what
        seen[what] += 1
        seen['partly scored'] += bool(ens.scored.any() and not ens.scored.all())

    def recorded_weights(self, allowed=None):
        ens = SimpleNamespace(cross=self.cross.copy(), scored=self.scored.copy(),
                              offsets=self.offsets, min_growth=self.min_growth)  # fmt: skip
        w = yield from weights_steps(self, allowed)
        check_weights('ensemble', ens, allowed, np.asarray(w))
        return w

    def recorded_guard(self, allowed):
        g = self.guard
        ens = SimpleNamespace(cross=g.cross.copy(), scored=g.scored.copy(), offsets=g.offsets,
                              min_growth=g.min_growth)  # fmt: skip
        w = yield from guard_steps(self, allowed)
        check_weights('guard', ens, allowed, np.asarray(w))
        return w

    def recorded_candidates(self, t, r):
        t, r = np.array(t), np.array(r)
        out = yield from candidates_steps(self, t, r)
        got = np.full(out.shape, np.nan)
        status = ke.intent_candidates(t, r, self.ahead, self.OMEGAS, self.window,
                                      self.SUBSAMPLE_HZ, got)  # fmt: skip
        assert status == ke.OK and same(got, out, exact)
        seen['intent'] += 1
        seen['linear'] += not np.array_equal(out[1], out[0])
        seen['harmonic'] += not np.array_equal(out[2], out[0])
        return out

    patches = (('weights_steps', an.Ensemble, recorded_weights),
               ('_weights_steps', an.Anticipator, recorded_guard),
               ('candidates_steps', an.Intent, recorded_candidates))  # fmt: skip
    try:
        for name, owner, patched in patches:
            setattr(owner, name, patched)
        for bag in bags:
            if Path(bag).is_dir():
                golden_outputs(Path(bag))
                seen['bags'] += 1
    finally:
        an.Ensemble.weights_steps = weights_steps
        an.Anticipator._weights_steps = guard_steps
        an.Intent.candidates_steps = candidates_steps
    return seen


# -------------------------------------------------------------------------------------- tests

PINNED_CHECK = r'''
from test.core import test_kernels_ensemble as t
from test.golden_outputs import check_pinned_kernels

check_pinned_kernels()
weights, candidates, recorded = t.check_weights(True), t.check_candidates(True), \
    t.check_recorded(True)
assert weights['raised'] and weights['extrapolated'] and weights['dropped'], weights
assert weights['singular'] >= 2, weights
assert weights['batched'] >= 30, weights
assert candidates['jump'] and candidates['linear'] and candidates['harmonic'], candidates
assert candidates['raised'], candidates
assert recorded['bags'] >= 1 and recorded['partly scored'], recorded
assert recorded['linear'] and recorded['harmonic'], recorded
print(weights, candidates, recorded)
print('ok')
'''


def test_the_kernels_are_the_numpy_code_bit_for_bit_under_the_pin():
    """Random inputs and every call of a recorded flight (bags/position, a corpus flight), in a
    child process with the golden test's pinned kernels."""
    done = run_pinned_script(PINNED_CHECK)
    assert done.returncode == 0 and done.stdout.strip().endswith('ok'), done.stderr[-3000:]


def test_the_ensemble_weights_are_the_numpy_codes_to_round_off_unpinned():
    check_weights(False)


def test_the_intent_candidates_are_the_numpy_codes_to_round_off_unpinned():
    check_candidates(False)


def test_the_kernels_are_the_numpy_code_on_a_recorded_flight_unpinned():
    assert check_recorded(False, RECORDED[:1])['bags'] == 1


def test_the_kernels_are_compiled_at_import_and_never_at_a_call():
    """Every kernel Python calls has its one signature compiled when the module is imported; a
    call with other types is refused rather than compiled (the helpers, which only kernels
    call, are compiled into them: test_kernels.py)."""
    compiled = [k for k in vars(ke).values() if hasattr(k, 'overloads') and not k._can_compile]
    assert {'ensemble_weights', 'intent_candidates'} <= {k.__name__ for k in compiled}
    assert all(len(k.overloads) == 1 for k in compiled)
    with pytest.raises(TypeError):
        ke.ensemble_weights(np.zeros((2, 3, 3), np.float32), np.ones(2, bool), np.ones(2),
                            np.zeros(3), 3, np.ones(3, bool), np.zeros((2, 3)))  # fmt: skip
    assert all(len(k.overloads) == 1 for k in compiled)


def test_no_candidate_or_no_frequency_is_the_error_numpy_raises():
    out = np.zeros((2, 0))
    status = ke.ensemble_weights(np.zeros((2, 1, 1)), np.ones(2, bool), np.ones(2), np.zeros(1),
                                 0, np.zeros(0, bool), out)  # fmt: skip
    assert status == ke.VALUE_ERROR
    with pytest.raises(ValueError):
        an.simplex_weights(np.zeros((2, 0, 0)), np.zeros(0, bool))
    t, y = -np.arange(12.0)[::-1], np.zeros((12, 4))
    separate, joint = np.zeros((3, 4)), np.zeros((3, 2))
    status = ke.harmonic_fits(t, y, np.arange(3.0), np.zeros(0), np.arange(2), separate, joint)
    assert status == ke.VALUE_ERROR
    with pytest.raises(ValueError):
        an.harmonic_fits(t, y, np.arange(3.0), np.zeros(0), np.arange(2))
