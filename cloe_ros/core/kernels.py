"""Compiled kernels (numba) of the per-vehicle paths that numpy ran as many small calls.

The identifier's and the observer's step, the guard's scoring, the history's interpolation, an
odometry sample's checks and state, the values of ``cloe/state``, and the basis and residuals of
the intent's harmonic fits: in numpy each was a few dozen calls on arrays of a few dozen entries
(or, for the fits, temporaries and a reduction along a strided axis), so call overhead, not
arithmetic, was their cost.
Each kernel here does one of them in one call, with the same operations in the same order as
the numpy code it replaced, so that under the golden test's pinned kernels (numpy's x86-64
baseline loops, OpenBLAS's Nehalem kernels) the outputs are bitwise those of that code:

* element-wise arithmetic is IEEE's in either (numba contracts nothing into fused multiply-adds
  without ``fastmath``, which is off); transcendental functions are libm's in either;
* a matrix product over at most three terms adds them from the first (OpenBLAS's order), or has
  at most two non-zero terms, whose sum is the same in any order;
* an ``einsum`` sum of products adds in the baseline loop's two lanes (:func:`einsum_dot`;
  test/core/test_kernels.py checks it against numpy under the pin), ``np.add.reduceat``
  adds the first term to the sum of the rest, and a sum along a strided axis adds from its
  first entry on.

What stays out of this module: LAPACK's solves and decompositions (the identifier's periodic
solve and excitation measures, the predictions' fits), and the products over many terms that
OpenBLAS sums in its own blocked order. Equivalent small-matrix code is not enough there: the
identifier's systems are ill-conditioned along the directions the flight does not excite, and
a compiled LU and Jacobi eigensolver moved the golden outputs by up to 6e-9 (EVALUATION.md,
section 4). The kernels that need them (the identifier's solve and excitation measures,
:mod:`~cloe_ros.core.kernels_identifier`; the error statistics' third differences,
:mod:`~cloe_ros.core.kernels_covariance`; the predictions', :mod:`~cloe_ros.core.kernels_models`,
:mod:`~cloe_ros.core.kernels_ensemble`, :mod:`~cloe_ros.core.kernels_combine`) call the routines
numpy calls instead, in numpy's own OpenBLAS (:mod:`~cloe_ros.core.blas`), which gives numpy's
bits.

Where the kernels were built ahead (:mod:`~cloe_ros.core.ahead`), each kernel Python calls is
the built module's function, and numba is not imported. Otherwise the kernels Python calls
compile when their module is imported (explicit signatures) and are cached on disk beside it
(``cache=True``), so no message ever waits on a compile: the first import on a machine takes
about a minute, later ones load the machine code. The helpers, which
only other kernels call (:meth:`Compiler.helper`), are compiled into their callers and never
loaded by themselves: an import loads only the kernels Python calls (24 of the 52). When that
came in, it loaded 25 kernels instead of 64, about 0.2 s less per process (EVALUATION.md,
section 4).
"""

from __future__ import annotations

import warnings

import numpy as np

from cloe_ros.core import ahead


class Compiler:
    """The decorator of a module's kernels: ``numba.njit(signature)`` (or, for a helper,
    ``numba.njit`` alone: :meth:`helper`), without the GIL, with
    numpy's errors (``x / 0`` gives inf or nan, not an exception) and with numba's cache where
    it can have one; or, in a process that runs the kernels built ahead
    (:mod:`~cloe_ros.core.ahead`), the built module's function of the same name, and numba is
    not imported.

    The cache holds machine code by the file's path, and what it pickles names the module: the
    file loaded under another name (a script's importlib, a checker) would leave entries that
    the package's own import then fails to load. So only the package's own module (``own``,
    the name it is imported by, against ``module``, the name it was loaded as) reads and writes
    it. Where numba can have no cache (no writable folder for it: the package's read-only, and
    so the user's cache folder, with no ``NUMBA_CACHE_DIR``; or an entry it cannot load), the
    kernels compile without it, in every process that imports them (about a minute, still
    before any message), and one warning says so."""

    def __init__(self, module: str, own: str) -> None:
        self.name = own.rsplit('.', 1)[1]  # (the built module's functions are named by it)
        self.cached = module == own

    def __call__(self, signature):
        """A kernel Python calls: compiled for ``signature`` when it is decorated (the built
        module's, where one runs; registered for the build, in the build)."""
        if ahead.MODULE is not None:
            return lambda func: ahead.function(self.name, func.__name__, signature)
        if ahead.BUILDING:
            return lambda func: self._register(func, signature)
        return lambda func: self._jit(signature, func)

    def _register(self, func, signature):
        ahead.register(self.name, func, signature)
        return self._jit(signature, func)  # (as numba's JIT has it: a recursive kernel needs it)

    def helper(self, func):
        """A kernel only other kernels call: compiled, for the types they pass, into each
        kernel that calls it when that kernel compiles. A kernel loaded from the cache holds
        its helpers' machine code, so a helper is never loaded by itself, and importing the
        modules loads only what Python calls (numba's load of a cached kernel costs about as
        much as its code is long). Python may call a helper (the tests do): numba then
        compiles it for those types, or loads them from its cache. In a process that runs
        the kernels built ahead, the helper is its Python function."""
        if ahead.MODULE is not None:
            return func
        return self._jit(None, func)

    def _jit(self, signature, func):
        from numba import njit
        from numba.core.errors import NumbaError

        from cloe_ros.core import blas

        if blas.AVAILABLE:  # (OpenBLAS linked before a cached kernel that calls it loads)
            blas.link_for_numba()
        options = dict(nogil=True, error_model='numpy')
        signature = () if signature is None else (signature,)
        if self.cached:
            try:
                return njit(*signature, cache=True, **options)(func)
            except NumbaError:  # the kernel itself does not compile: not the cache's
                raise
            except Exception as err:  # whatever else the cache's problem, do without it
                self.cached = False
                warnings.warn(
                    f'cloe_ros: numba cannot cache the compiled kernels ({err}); each '
                    'process compiles them when it starts. Set NUMBA_CACHE_DIR to a '
                    'writable folder to keep them.', RuntimeWarning, stacklevel=3)  # fmt: skip
        return njit(*signature, cache=False, **options)(func)


_compiled = Compiler(__name__, 'cloe_ros.core.kernels')


_F1 = 'float64[::1]'
_F2 = 'float64[:, ::1]'
_I1 = 'intp[::1]'


@_compiled.helper
def maximum(a, b):
    """``np.maximum(a, b)`` of two floats: ``a`` where it is NaN or not below ``b``, else ``b``
    (so a NaN on either side is kept)."""
    return a if (a >= b or a != a) else b


@_compiled.helper
def einsum_dot(a, i, b, j, start, n):
    """``np.einsum('j,j->', a[i, start:start + n], b[j, start:start + n])`` of rows ``i`` and
    ``j`` of the 2-D ``a`` and ``b``, as numpy's x86-64 baseline (two-lane) loop adds it: two
    lanes, the even and the odd terms; blocks of eight terms taken from their last pair; then
    the lanes added. (Indices, not the rows' views: a view in numba takes a reference to its
    array and gives it back, which cost more than the sum in the kernels' inner loops.)"""
    even = odd = 0.0
    q, end = start, start + n
    while end - q >= 8:
        for s in (6, 4, 2, 0):
            even = a[i, q + s] * b[j, q + s] + even
            odd = a[i, q + s + 1] * b[j, q + s + 1] + odd
        q += 8
    while q < end:
        even = a[i, q] * b[j, q] + even
        odd = (a[i, q + 1] * b[j, q + 1] if q + 1 < end else 0.0) + odd
        q += 2
    return even + odd


@_compiled.helper
def _count_not_after(t, x):
    """How many of the increasing ``t`` are <= ``x``: ``np.searchsorted(t, x, 'right')``."""
    low, high = 0, t.shape[0]
    while low < high:
        mid = (low + high) >> 1
        if t[mid] <= x:
            low = mid + 1
        else:
            high = mid
    return low


@_compiled.helper
def _interp_into(t, data, x, channels, out):
    """``data`` (T, C) sampled at ``t`` (T,), at ``x`` (in the span), for ``channels``, into
    ``out``: the arithmetic of ``np.interp`` (a sample's own time, and the ends, give the
    sample itself)."""
    j = max(_count_not_after(t, x) - 1, 0)  # (before the first sample: the first)
    if x < t[0] or j >= t.shape[0] - 1 or t[j] == x:
        for c in range(channels.shape[0]):
            out[c] = data[j, channels[c]]
        return
    dt = t[j + 1] - t[j]
    for c in range(channels.shape[0]):
        d0 = data[j, channels[c]]
        out[c] = (data[j + 1, channels[c]] - d0) / dt * (x - t[j]) + d0


@_compiled(f'void({_F1}, float64[:, :], {_F1}, {_I1}, {_F2})')
def interpolate(t, data, times, channels, out):
    """``out`` (M, C) = ``data`` (T, C) sampled at the increasing ``t`` (T,), interpolated at
    ``times`` (M,) for ``channels`` (C,) as ``np.interp`` does; NaN outside the span (1e-9 s
    of slack) and at NaN times."""
    n = t.shape[0]
    for i in range(times.shape[0]):
        x = times[i]
        if n < 1 or not (t[0] - 1e-9 <= x <= t[n - 1] + 1e-9):
            out[i, :] = np.nan
        else:
            _interp_into(t, data, x, channels, out[i])


@_compiled(
    f'intp({_F1}, float64[:, :, :, ::1], {_F1}, float64, float64, {_F1}, float64[:, :], {_I1},'
    f' float64[:, :, ::1], boolean[::1], float64, {_I1}, {_F1}, {_I1}, {_F2})'
)
def score_ensemble(pending_t, pending, offsets, since, now, t, data, channels, cross, scored,
                   alpha, slots, issued, horizons, squared):  # fmt: skip
    """:meth:`~cloe_ros.core.anticipation.Ensemble.score` against a history column: scores the
    poses of the pending predictions (issue times ``pending_t`` (P,), NaN for none; paths
    ``pending`` (P, M, K, D)) whose times fall in ``(since, now]`` against ``data`` (T, ·)
    sampled at ``t`` (T,) (``channels``, D of them), into the error cross-products ``cross``
    (K, M, M) and ``scored`` (K,); forgets the predictions all of whose poses are due. Writes
    each scored pose's slot, issue time, horizon and candidates' squared errors (M,) into the
    outputs (P * K long) in the order of the numpy code (by slot, then horizon), and returns
    how many there are."""
    n_slots, m, k_max, d = pending.shape
    actual = np.empty(d)
    err = np.empty((m, d))
    after, until = since + 1e-9, now + 1e-9
    low, high = (t[0] - 1e-9, t[t.shape[0] - 1] + 1e-9) if t.shape[0] else (np.inf, -np.inf)
    n = 0
    for p in range(n_slots):
        issue = pending_t[p]
        if not np.isfinite(issue):
            continue
        for k in range(k_max):
            time = issue + offsets[k]
            if not (after < time <= until) or not (low <= time <= high):
                continue
            _interp_into(t, data, time, channels, actual)
            if not np.all(np.isfinite(actual)):
                continue
            for i in range(m):
                for c in range(d):
                    err[i, c] = pending[p, i, k, c] - actual[c]
            weight = alpha if scored[k] else 1.0
            for i in range(m):  # (einsum's 'pmd,pnd->pmn' and 'pmd,pmd->pm')
                for j in range(m):
                    cross[k, i, j] += weight * (einsum_dot(err, i, err, j, 0, d) - cross[k, i, j])
            scored[k] = True
            slots[n], issued[n], horizons[n] = p, issue, k
            for i in range(m):
                squared[n, i] = einsum_dot(err, i, err, i, 0, d)
            n += 1
        if issue + offsets[k_max - 1] <= until:  # every pose is due: done
            pending_t[p] = np.nan
    return n


# --------------------------------------------------------------------- the IV identifier


_IV_FILTER = (
    # inputs
    f'void({_F2}, {_F2}, boolean[::1], float64[::1],'  # zeta, r, whole (all rows active), decay
    # history
    ' float64[:, :, ::1], float64[:, :, ::1], boolean[:, ::1], intp[::1], int64[::1],'
    # auxiliary model: ad, bd, x, last r, shift
    f' float64[:, :, ::1], float64[:, :, ::1], {_F2}, {_F2}, {_F2},'
    # filter bank: state (N, C, 3), cf, df, cd, dd, ad^T, bd
    f' float64[:, :, ::1], {_F1}, float64, {_F1}, float64, {_F2}, {_F1},'
    # scales: state, reference
    f' {_F1}, {_F1},'
    # regressor and instrument gathers (channels (2, rows * W), coefficients), mask (rows * W),
    # target gathers: F's (2, rows) channels and coefficients, sF's (rows,)
    f' intp[:, ::1], {_F2}, intp[:, ::1], {_F2}, boolean[::1], intp[:, ::1], {_F2}, {_I1}, {_F1},'
    # gate (N, rows), weight of the settled (N,), step h
    f' {_F2}, {_F1}, float64,'
    # out: f, d, phi, xi (N, rows * W), y (N, rows); work: u (C,), x (12,), the next state (C, 3)
    f' {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F1}, {_F1}, {_F2})'
)


@_compiled.helper
def iv_filter(zeta, r, whole, decay, hist_z, hist_r, hist_active, hist_next, hist_count,
              aux_ad, aux_bd, x_aux, last_r, aux_shift, fx, cf, df, cd, dd, ad_t, bd,
              state_scale, reference_scale, phi_c, phi_a, xi_c, xi_a, mask, yf_c, yf_a, yd_c,
              yd_a, gate, weight, h, f, d, phi, xi, y, u, x_new, fx_new):  # fmt: skip
    """The per-vehicle part of :meth:`~cloe_ros.core.identifier.IvIdentifier.step` up to its
    statistics, with that method's operations in its order: the history, the auxiliary model,
    the filter bank (its state advanced in place), and each vehicle's filtered channels ``f``,
    ``d``, regressors ``phi``, instruments ``xi`` and targets ``y``, gated by ``gate`` and
    ``weight`` (1 where the numpy code does not multiply: a product by 1 is exact)."""
    n_vehicles, n_states = zeta.shape
    n_refs = r.shape[1]
    n_channels = fx.shape[1]
    width = phi.shape[1] // y.shape[1]
    for n in range(n_vehicles):
        k = hist_next[n]
        for i in range(n_states):
            hist_z[n, k, i] = zeta[n, i]
        for i in range(n_refs):
            hist_r[n, k, i] = r[n, i]
        hist_active[n, k] = whole[n]
        hist_next[n] = (k + 1) % hist_z.shape[1]
        hist_count[n] += 1
        # auxiliary model, driven by the reference only
        ad, bd_aux = aux_ad[n], aux_bd[n]
        for i in range(n_states):
            x_new[i] = (einsum_dot(ad, i, x_aux, n, 0, n_states)
                        + einsum_dot(bd_aux, i, r, n, 0, n_refs))  # fmt: skip
        for i in range(n_states):
            x_aux[n, i] = x_new[i]
        for i in range(n_refs):
            last_r[n, i] = r[n, i]
        # channels: the measured state, the reference, the auxiliary model's state, zero
        for i in range(n_states):
            u[i] = zeta[n, i] / state_scale[i]
            u[n_states + 4 + i] = (x_aux[n, i] - aux_shift[n, i]) / state_scale[i]
        for i in range(4):
            u[n_states + i] = r[n, i] / reference_scale[i]
        u[n_channels - 1] = 0.0
        # the filter bank: F{u}, sF{u} and the next state (matmul's order: term by term)
        for c in range(n_channels):
            s = 0.0
            s += fx[n, c, 0] * cf[0]
            s += fx[n, c, 1] * cf[1]
            s += fx[n, c, 2] * cf[2]
            f[n, c] = s + df * u[c]
            s = 0.0
            s += fx[n, c, 0] * cd[0]
            s += fx[n, c, 1] * cd[1]
            s += fx[n, c, 2] * cd[2]
            d[n, c] = s + dd * u[c]
            for q in range(3):
                s = 0.0
                s += fx[n, c, 0] * ad_t[0, q]
                s += fx[n, c, 1] * ad_t[1, q]
                s += fx[n, c, 2] * ad_t[2, q]
                fx_new[c, q] = s + u[c] * bd[q]
        for c in range(n_channels):
            for q in range(3):
                fx[n, c, q] = fx_new[c, q]
        f[n, n_channels] = decay[n]
        # regressors, instruments, targets
        for j in range(phi.shape[1]):
            on, g = (1.0 if mask[j] else 0.0), gate[n, j // width]
            phi[n, j] = (f[n, phi_c[0, j]] * phi_a[0, j] + f[n, phi_c[1, j]] * phi_a[1, j]) * on
            phi[n, j] = phi[n, j] * g * weight[n]
            xi[n, j] = (f[n, xi_c[0, j]] * xi_a[0, j] + f[n, xi_c[1, j]] * xi_a[1, j]) * on
            xi[n, j] = xi[n, j] * g * weight[n]
        for p in range(y.shape[1]):
            y[n, p] = (f[n, yf_c[0, p]] * yf_a[0, p] + f[n, yf_c[1, p]] * yf_a[1, p]
                       + d[n, yd_c[p]] * yd_a[p]) * gate[n, p] * weight[n]  # fmt: skip


@_compiled.helper
def _transpose(a, out):
    """``out`` (M, N) = ``a`` (N, M) transposed."""
    for n in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[j, n] = a[n, j]


_IV_SHORT = (
    # phi, xi (N, rows * W), y (N, rows), the last solution (N, rows * W), the entries' left
    # and right factors (packed), h, mu_e (N,), the settled weight (N,)
    f'void({_F2}, {_F2}, {_F2}, {_F2}, {_I1}, {_I1}, float64, {_F1}, {_F1},'
    # in/out: the short statistics (3, packed, N), residual power (N, rows), weight_e (N,),
    # steps (N,); out: the increments (3, packed, N); work: phi and xi transposed (rows * W, N)
    f' float64[:, :, ::1], {_F2}, {_F1}, int64[::1], float64[:, :, ::1], {_F2}, {_F2})'
)


@_compiled.helper
def iv_short_window(phi, xi, y, rows, left, right, h, mu_e, weight, short, res2, weight_e,
                    steps, increments, phi_t, xi_t):  # fmt: skip
    """The short-window statistics of :meth:`~cloe_ros.core.identifier.IvIdentifier.step`,
    in its order: the packed outer products ``xi phi^T h``, ``xi xi^T h`` and ``(phi h)
    phi^T`` into ``increments``, forgotten by ``mu_e`` and added; the residual power; the
    weight's integral and the steps (of the settled: ``weight`` 1 or 0)."""
    _transpose(phi, phi_t)  # (rows * W, N): the loops below run along the vehicles
    _transpose(xi, xi_t)
    for q in range(left.shape[0]):
        pa, pb, xa, xb = phi_t[left[q]], phi_t[right[q]], xi_t[left[q]], xi_t[right[q]]
        cross, gram_xi, gram_phi = increments[0, q], increments[1, q], increments[2, q]
        s0, s1, s2 = short[0, q], short[1, q], short[2, q]
        for n in range(pa.shape[0]):
            cross[n] = xa[n] * pb[n] * h
            gram_xi[n] = xa[n] * xb[n] * h
            gram_phi[n] = pa[n] * h * pb[n]
            s0[n] = s0[n] * mu_e[n] + cross[n]
            s1[n] = s1[n] * mu_e[n] + gram_xi[n]
            s2[n] = s2[n] * mu_e[n] + gram_phi[n]
    n_vehicles = phi.shape[0]
    n_rows = y.shape[1]
    width = phi.shape[1] // n_rows
    for n in range(n_vehicles):
        for p in range(n_rows):
            e = y[n, p] - einsum_dot(rows, n, phi, n, p * width, width)
            res2[n, p] = res2[n, p] * mu_e[n] + e * e * h
        weight_e[n] = weight_e[n] * mu_e[n] + h * weight[n]
        steps[n] += 1 if weight[n] else 0


_IV_LONG = (
    # xi (N, rows * W), y (N, rows), excited (N, rows), mu, h, entries' rows (packed),
    # increments (3, packed, N); in/out: the long statistics (2, packed, N), rhs (N, rows * W);
    # work: the forgetting factors (rows, N)
    f'void({_F2}, {_F2}, boolean[:, ::1], float64, float64, {_I1}, float64[:, :, ::1],'
    f' float64[:, :, ::1], {_F2}, {_F2})'
)


@_compiled.helper
def iv_long_window(xi, y, excited, mu, h, entry_row, increments, long, rhs, forget):
    """The long-window normal equations of :meth:`~cloe_ros.core.identifier.IvIdentifier.step`
    in its order: forgotten by ``mu`` only where the row is excited, ``xi phi^T h`` and ``xi
    xi^T h`` added, and ``b += xi h y``."""
    n_vehicles, n_rows = y.shape
    width = xi.shape[1] // n_rows
    # (rows, N): mu where excited, else 1
    for n in range(n_vehicles):
        for p in range(n_rows):
            forget[p, n] = mu if excited[n, p] else 1.0
    for q in range(entry_row.shape[0]):
        m = forget[entry_row[q]]
        cross, gram_xi = long[0, q], long[1, q]
        add_cross, add_xi = increments[0, q], increments[1, q]
        for n in range(n_vehicles):
            cross[n] = cross[n] * m[n] + add_cross[n]
            gram_xi[n] = gram_xi[n] * m[n] + add_xi[n]
    for n in range(n_vehicles):
        for j in range(xi.shape[1]):
            m = mu if excited[n, j // width] else 1.0
            rhs[n, j] = rhs[n, j] * m + xi[n, j] * h * y[n, j // width]


#: What :func:`iv_step_filter` and :func:`iv_step_long` return: bit flags (any, all) of the
#: vehicles settled and of those due for each periodic update.
ANY_SETTLED, ALL_SETTLED, ANY_DUE, ALL_DUE = 1, 2, 4, 8
ANY_DUE_MODEL, ALL_DUE_MODEL = 16, 32


@_compiled.helper
def _flags(mask, settled):
    """``ANY_DUE | ALL_DUE`` of ``mask`` (N,) restricted to the vehicles ``settled``."""
    any_, all_ = False, True
    for n in range(mask.shape[0]):
        mask[n] = mask[n] and settled[n]
        any_ |= mask[n]
        all_ &= mask[n]
    return (ANY_DUE if any_ else 0) | (ALL_DUE if all_ else 0)


_IV_STEP_FILTER = (
    _IV_FILTER[:-1].replace('void(', 'int64(', 1)
    # the clock (N,), the settling time, the rows active (N, rows), the excitation measures'
    # period in steps, the short window's forgetting; the short window's arguments after phi,
    # xi, y (see iv_short_window); work: settled (N,), mu_e (N,); out: the vehicles due for the
    # excitation measures (N,)
    + f', {_F1}, float64, boolean[:, ::1], int64, float64, {_F2}, {_I1}, {_I1},'
    f' float64[:, :, ::1], {_F2}, {_F1}, int64[::1], float64[:, :, ::1], {_F2}, {_F2},'
    ' boolean[::1], float64[::1], boolean[::1])'
)


@_compiled(_IV_STEP_FILTER)
def iv_step_filter(zeta, r, whole, decay, hist_z, hist_r, hist_active, hist_next, hist_count,
                   aux_ad, aux_bd, x_aux, last_r, aux_shift, fx, cf, df, cd, dd, ad_t, bd,
                   state_scale, reference_scale, phi_c, phi_a, xi_c, xi_a, mask, yf_c, yf_a,
                   yd_c, yd_a, gate, weight, h, f, d, phi, xi, y, u, x_new, fx_new, t, settle,
                   active, every, mu_e_settled, rows, left, right, short, res2, weight_e, steps,
                   increments, phi_t, xi_t, settled, mu_e, due):  # fmt: skip
    """The first part of :meth:`~cloe_ros.core.identifier.IvIdentifier.step` in one call: the
    vehicles settled (``t >= settle``), the rows' gates and weights from ``active``,
    :func:`iv_filter`, and once any vehicle is settled :func:`iv_short_window` and the vehicles
    due for the excitation measures (``due``). Returns :data:`ANY_SETTLED` / :data:`ALL_SETTLED`
    and :data:`ANY_DUE` / :data:`ALL_DUE` flags."""
    n_vehicles, n_rows = active.shape
    any_settled, all_settled = False, True
    for n in range(n_vehicles):
        settled[n] = t[n] >= settle
        any_settled |= settled[n]
        all_settled &= settled[n]
        weight[n] = 1.0 if settled[n] else 0.0
        mu_e[n] = mu_e_settled if settled[n] else 1.0
        every_row = True
        for p in range(n_rows):
            gate[n, p] = 1.0 if active[n, p] else 0.0
            every_row &= active[n, p]
        whole[n] = every_row
    iv_filter(zeta, r, whole, decay, hist_z, hist_r, hist_active, hist_next, hist_count, aux_ad,
              aux_bd, x_aux, last_r, aux_shift, fx, cf, df, cd, dd, ad_t, bd, state_scale,
              reference_scale, phi_c, phi_a, xi_c, xi_a, mask, yf_c, yf_a, yd_c, yd_a, gate,
              weight, h, f, d, phi, xi, y, u, x_new, fx_new)  # fmt: skip
    if not any_settled:
        return 0
    iv_short_window(phi, xi, y, rows, left, right, h, mu_e, weight, short, res2, weight_e, steps,
                    increments, phi_t, xi_t)  # fmt: skip
    for n in range(n_vehicles):
        due[n] = steps[n] % every == 1 or every == 1
    return ANY_SETTLED | (ALL_SETTLED if all_settled else 0) | _flags(due, settled)


_IV_STEP_LONG = (
    # xi, y, the excitation measures (N, rows), the threshold, the rows active (N, rows),
    # settled (N,), mu, h, the entries' rows, the increments, the long statistics, rhs (N, rows
    # * W); work: excited (N, rows), forget (rows, N); the steps (N,), the solve's period in
    # steps; the time since the model's update (N,) (in/out), its period less 1e-9; out: the
    # vehicles due for the solve and for the model's update (N,)
    f'int64({_F2}, {_F2}, {_F2}, float64, boolean[:, ::1], boolean[::1], float64, float64, {_I1},'
    f' float64[:, :, ::1], float64[:, :, ::1], {_F2}, boolean[:, ::1], {_F2}, int64[::1], int64,'
    f' {_F1}, float64, boolean[::1], boolean[::1])'
)


@_compiled(_IV_STEP_LONG)
def iv_step_long(xi, y, excitation, threshold, active, settled, mu, h, entry_row, increments,
                 long, rhs, excited, forget, steps, every, since, period, due, due_model):
    """The second part of :meth:`~cloe_ros.core.identifier.IvIdentifier.step`, after the
    excitation measures: the rows excited (``excitation >= threshold``, active, settled),
    :func:`iv_long_window`, the vehicles due for the solve (``due``), and the settled ones'
    time since the model's update advanced by ``h``, those due for it (``due_model``) set back
    to 0. Returns the solve's :data:`ANY_DUE` / :data:`ALL_DUE` flags and the model's
    :data:`ANY_DUE_MODEL` / :data:`ALL_DUE_MODEL`."""
    n_vehicles, n_rows = excited.shape
    for n in range(n_vehicles):
        for p in range(n_rows):
            excited[n, p] = excitation[n, p] >= threshold and active[n, p] and settled[n]
    iv_long_window(xi, y, excited, mu, h, entry_row, increments, long, rhs, forget)
    for n in range(n_vehicles):
        due[n] = steps[n] % every == 0 or every == 1
    flags = _flags(due, settled)
    any_, all_ = False, True
    for n in range(n_vehicles):
        if settled[n]:
            since[n] += h
        due_model[n] = since[n] >= period
        if due_model[n]:
            since[n] = 0.0
        any_ |= due_model[n]
        all_ &= due_model[n]
    return flags | (ANY_DUE_MODEL if any_ else 0) | (ALL_DUE_MODEL if all_ else 0)


# ------------------------------------------------------------------------------ odometry

_RO = "Array(float64, 1, 'A', readonly=True)"

#: :func:`odometry_state`'s verdicts.
ODOMETRY_OK, NON_FINITE, BAD_QUATERNION, BAD_POSITION, BAD_VELOCITY, BAD_RATE, BAD_TILT = range(7)


@_compiled(f'intp({_RO}, {_RO}, {_RO}, {_RO}, float64, float64, float64, float64, float64,'
           f' {_F1}, {_F1})')
def odometry_state(position, orientation, linear, angular, quaternion_tolerance, max_position,
                   max_speed, max_rate, max_tilt, zeta, detail):  # fmt: skip
    """The checks of an odometry sample, in order, and its state: returns the first problem
    (``NON_FINITE``: a value is not finite; ``BAD_QUATERNION``: ``| ||q|| - 1 |`` beyond the
    tolerance, ``detail[0]`` the norm; ``BAD_POSITION`` / ``BAD_VELOCITY`` / ``BAD_RATE``: a
    component beyond its bound, ``detail[0]`` the largest; ``BAD_TILT``: roll or pitch beyond
    ``max_tilt``, ``detail[:2]`` roll and pitch) or ``ODOMETRY_OK`` with ``zeta`` (12,) the
    state: the arithmetic of :func:`~cloe_ros.core.kinematics.odometry_to_state_one`."""
    for values in (position, orientation, linear, angular):
        for c in range(values.shape[0]):
            if not np.isfinite(values[c]):
                return NON_FINITE
    x, y, z, w = orientation[0], orientation[1], orientation[2], orientation[3]
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > quaternion_tolerance:
        detail[0] = norm
        return BAD_QUATERNION
    for values, bound, verdict in ((position, max_position, BAD_POSITION),
                                   (linear, max_speed, BAD_VELOCITY),
                                   (angular, max_rate, BAD_RATE)):  # fmt: skip
        largest = 0.0
        for c in range(values.shape[0]):
            largest = max(largest, abs(values[c]))
        if largest > bound:
            detail[0] = largest
            return verdict
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(min(1.0, max(-1.0, 2.0 * (w * y - z * x))))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    if max(abs(roll), abs(pitch)) > max_tilt:
        detail[0], detail[1] = roll, pitch
        return BAD_TILT
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    u, v, wv = linear[0], linear[1], linear[2]
    p, q, r = angular[0], angular[1], angular[2]
    s = q * sr + r * cr
    zeta[0] = position[0]
    zeta[1] = cy * cp * u + (cy * sp * sr - sy * cr) * v + (cy * sp * cr + sy * sr) * wv
    zeta[2] = pitch
    zeta[3] = q * cr - r * sr
    zeta[4] = position[1]
    zeta[5] = sy * cp * u + (sy * sp * sr + cy * cr) * v + (sy * sp * cr - cy * sr) * wv
    zeta[6] = roll
    zeta[7] = p + s * np.tan(pitch)
    zeta[8] = yaw
    zeta[9] = s / cp
    zeta[10] = position[2]
    zeta[11] = -sp * u + cp * sr * v + cp * cr * wv
    return ODOMETRY_OK


@_compiled(f'void({_RO}, {_RO}, boolean, {_F1})')
def state_message(zeta, variance, with_variance, out):
    """The 85 doubles of ``cloe/state`` (an Odometry, in field order: position, orientation,
    pose covariance, body velocity, body rates, twist covariance) of the state ``zeta`` (12,)
    and, ``with_variance``, its error ``variance`` (12,) (zeros without): the arithmetic of
    :func:`~cloe_ros.core.kinematics.state_to_odometry` and
    :func:`~cloe_ros.core.covariance.odometry_covariance`."""
    x, vx, pitch, dpitch, y, vy, roll, droll, yaw, dyaw, z, vz = (
        zeta[0], zeta[1], zeta[2], zeta[3], zeta[4], zeta[5], zeta[6], zeta[7], zeta[8],
        zeta[9], zeta[10], zeta[11])  # fmt: skip
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    hr, hp, hy = 0.5 * roll, 0.5 * pitch, 0.5 * yaw
    chr_, shr = np.cos(hr), np.sin(hr)
    chp, shp = np.cos(hp), np.sin(hp)
    chy, shy = np.cos(hy), np.sin(hy)
    out[:] = 0.0
    out[0], out[1], out[2] = x, y, z
    out[3] = shr * chp * chy - chr_ * shp * shy
    out[4] = chr_ * shp * chy + shr * chp * shy
    out[5] = chr_ * chp * shy - shr * shp * chy
    out[6] = chr_ * chp * chy + shr * shp * shy
    # body velocity = R^T v_world, body rates from the Euler rates
    out[43] = cy * cp * vx + sy * cp * vy - sp * vz
    out[44] = (cy * sp * sr - sy * cr) * vx + (sy * sp * sr + cy * cr) * vy + cp * sr * vz
    out[45] = (cy * sp * cr + sy * sr) * vx + (sy * sp * cr - cy * sr) * vy + cp * cr * vz
    out[46] = droll - dyaw * sp
    out[47] = dpitch * cr + dyaw * cp * sr
    out[48] = -dpitch * sr + dyaw * cp * cr
    if not with_variance:
        return
    v = variance
    p_x, v_x, p_pitch, r_pitch, p_y, v_y, p_roll, r_roll, p_yaw, r_yaw, p_z, v_z = (
        v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9], v[10], v[11])
    # R (world from body, ZYX), its rows j weighed by the world-velocity variances v_j
    r00, r01, r02 = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    r10, r11, r12 = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    r20, r21, r22 = -sp, cp * sr, cp * cr
    w00, w01, w02 = r00 * v_x, r01 * v_x, r02 * v_x
    w10, w11, w12 = r10 * v_y, r11 * v_y, r12 * v_y
    w20, w21, w22 = r20 * v_z, r21 * v_z, r22 * v_z
    l00 = w00 * r00 + w10 * r10 + w20 * r20
    l01 = w00 * r01 + w10 * r11 + w20 * r21
    l02 = w00 * r02 + w10 * r12 + w20 * r22
    l11 = w01 * r01 + w11 * r11 + w21 * r21
    l12 = w01 * r02 + w11 * r12 + w21 * r22
    l22 = w02 * r02 + w12 * r12 + w22 * r22
    # T (body rates from Euler rates), its columns weighed by the Euler-rate variances
    t12, t22 = cp * sr, cp * cr
    a00 = r_roll + sp * r_yaw * sp
    a01 = -sp * r_yaw * t12
    a02 = -sp * r_yaw * t22
    a11 = cr * r_pitch * cr + t12 * r_yaw * t12
    a12 = -cr * r_pitch * sr + t12 * r_yaw * t22
    a22 = sr * r_pitch * sr + t22 * r_yaw * t22
    pose = out[7:43]
    pose[0], pose[7], pose[14], pose[21], pose[28], pose[35] = (
        p_x, p_y, p_z, p_roll, p_pitch, p_yaw)  # fmt: skip
    twist = out[49:85]
    twist[0], twist[1], twist[2], twist[6], twist[7], twist[8] = l00, l01, l02, l01, l11, l12
    twist[12], twist[13], twist[14] = l02, l12, l22
    twist[21], twist[22], twist[23], twist[27], twist[28], twist[29] = a00, a01, a02, a01, a11, a12
    twist[33], twist[34], twist[35] = a02, a12, a22


# ------------------------------------------------------------------------------ the observer


@_compiled.helper
def observer_drift(zeta_hat, theta, r, known_c, known_a, regressor_index, block_starts,
                   last_rows, w, phi, grad, rows, f):  # fmt: skip
    """The observer's drift, as numpy computed it in order: ``f = A(Theta) zeta_hat +
    B(Theta) r`` (N, 12), the known rows one product each (``known_a`` times state
    ``known_c``), each block's last row ``Theta_b . phi_b`` summed as ``np.add.reduceat`` sums
    it; fills ``w``, ``phi`` (the regressors), ``grad`` (their products with ``theta``) and
    ``rows``."""
    n_states, n_params = zeta_hat.shape[1], theta.shape[1]
    n_blocks = block_starts.shape[0]
    for n in range(zeta_hat.shape[0]):
        for i in range(n_states):
            w[n, i] = zeta_hat[n, i]
        for i in range(r.shape[1]):
            w[n, n_states + i] = r[n, i]
        for p in range(n_params):
            phi[n, p] = w[n, regressor_index[p]]
            grad[n, p] = theta[n, p] * phi[n, p]
        for i in range(n_states):
            f[n, i] = zeta_hat[n, known_c[i]] * known_a[i]
        for b in range(n_blocks):  # (np.add.reduceat's order: the first term, plus the rest's
            end = block_starts[b + 1] if b + 1 < n_blocks else n_params  # sum, term by term)
            rest = 0.0
            for p in range(block_starts[b] + 1, end):
                rest += grad[n, p]
            rows[n, b] = grad[n, block_starts[b]] + rest
        for i in range(n_states):
            add = 0.0
            for b in range(n_blocks):
                if last_rows[b] == i:
                    add = rows[n, b]
            f[n, i] = f[n, i] + add


@_compiled.helper
def observer_update(zeta_hat, f, gain_l, zeta, h, lambda_, sliding, exponents, e):
    """The observer's step, shared by CLOE, CLOE-SM (:func:`cloe_step`) and cloe_iv
    (:func:`iv_observer`), as numpy computed it, in order: with ``sliding``, the term ``lambda_
    |e|^exponents sign(e)`` added to ``f``; then ``zeta_hat+ = (zeta_hat + h (L zeta + f)) /
    (1 + h L)``, in place."""
    for n in range(zeta_hat.shape[0]):
        for i in range(zeta_hat.shape[1]):
            if sliding:
                term = abs(e[n, i]) ** exponents[n, i]
                term = term * np.sign(e[n, i])
                f[n, i] = f[n, i] + term * lambda_[n, i]
            step = (gain_l[n, i] * zeta[n, i] + f[n, i]) * h
            zeta_hat[n, i] = (zeta_hat[n, i] + step) / (gain_l[n, i] * h + 1.0)


@_compiled(f'void({_F2}, {_F2}, {_F2}, {_F2}, {_F2}, float64, {_F2}, {_F2}, {_F2}, boolean, {_F2},'
           f' {_F2}, boolean, {_I1}, {_F1}, {_I1}, {_I1}, {_I1}, {_I1}, {_F2}, {_F2}, {_F2},'
           f' {_F2}, {_F2}, {_F2}, {_F2})')  # fmt: skip
def cloe_step(zeta_hat, theta, gain_l, zeta, r, h, gamma_theta, gamma_l, lambda_, sliding,
              exponents, gate, gated, known_c, known_a, regressor_index, block_starts, last_rows,
              param_row, e, w, phi, grad, rows, f, tmp):  # fmt: skip
    """:func:`~cloe_ros.core.estimator.cloe_step`, in place: the error ``e = zeta - zeta_hat``;
    the drift (:func:`observer_drift`); the observer's step with, if ``sliding``, the
    sliding-mode term (:func:`observer_update`); then the explicit Euler steps of the identifier
    and of the adaptive gain with the error before the update, in numpy's order of the in-place
    products they replaced: ``grad = ((e_last * phi) * gamma_theta) * h`` (times ``gate`` if
    ``gated``), ``theta += grad``; ``tmp = ((e * e) * gamma_l) * h``, ``gain_l += tmp``."""
    for n in range(zeta.shape[0]):
        for i in range(zeta.shape[1]):
            e[n, i] = zeta[n, i] - zeta_hat[n, i]
    observer_drift(zeta_hat, theta, r, known_c, known_a, regressor_index, block_starts,
                   last_rows, w, phi, grad, rows, f)  # fmt: skip
    observer_update(zeta_hat, f, gain_l, zeta, h, lambda_, sliding, exponents, e)
    for n in range(zeta.shape[0]):
        for p in range(theta.shape[1]):
            g = e[n, param_row[p]] * phi[n, p]
            g = g * gamma_theta[n, p]
            g = g * h
            if gated:
                g = g * gate[n, p]
            grad[n, p] = g
            theta[n, p] = theta[n, p] + g
        for i in range(zeta.shape[1]):
            t = e[n, i] * e[n, i]
            t = t * gamma_l[n, i]
            t = t * h
            tmp[n, i] = t
            gain_l[n, i] = gain_l[n, i] + t


@_compiled(f'void({_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, float64, float64,'
           f' float64, float64, float64, float64, {_I1}, {_I1}, {_F1}, {_I1}, {_I1}, {_F1}, {_I1},'
           f' {_I1}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2}, {_F2})')  # fmt: skip
def iv_observer(zeta, zeta_hat, theta, coupling, r, model_error, gain_l, lambda_, exponents, h,
                gamma_d, l_leak, gamma_l, l_min, l_max, coupled_rows, coupled_cols,
                paper_coupling, unknown, known_c, known_a, regressor_index, block_starts, e, w,
                phi, grad, rows, f):  # fmt: skip
    """:meth:`~cloe_ros.core.cloe_iv.CloeIvEstimator.step`'s observer in its order: the error
    ``e``; the drift of the model ``(theta, coupling)`` (the couplings replacing +-g, the
    extended state ``model_error`` added on the unknown rows, then advanced); the sliding-mode
    observer's step; the bounded adaptive gain."""
    for n in range(zeta.shape[0]):
        for i in range(zeta.shape[1]):
            e[n, i] = zeta[n, i] - zeta_hat[n, i]
    observer_drift(zeta_hat, theta, r, known_c, known_a, regressor_index, block_starts, unknown,
                   w, phi, grad, rows, f)  # fmt: skip
    for n in range(zeta.shape[0]):
        for k in range(coupled_rows.shape[0]):
            row, col = coupled_rows[k], coupled_cols[k]
            f[n, row] = f[n, row] + (coupling[n, k] - paper_coupling[k]) * zeta_hat[n, col]
        for j in range(unknown.shape[0]):
            u = unknown[j]
            f[n, u] = f[n, u] + model_error[n, j]
            model_error[n, j] = model_error[n, j] + h * (gamma_d * e[n, u]
                                                         - l_leak * model_error[n, j])  # fmt: skip
    observer_update(zeta_hat, f, gain_l, zeta, h, lambda_, True, exponents, e)
    for n in range(zeta.shape[0]):
        for i in range(zeta.shape[1]):
            rate = (e[n, i] * e[n, i] * gamma_l - l_leak * (gain_l[n, i] - l_min)) * h
            g = gain_l[n, i] + rate
            if g < l_min:
                g = l_min
            elif g > l_max:
                g = l_max
            gain_l[n, i] = g


# --------------------------------------------------------------------------- the intent's fits


@_compiled('void(float64[:, ::1], float64[::1], float64[:, :, :, ::1])')
def harmonic_basis(t, omegas, basis):
    """``basis`` (V, W, T, 3) = ``1, cos(w t), sin(w t)`` of every series' times ``t`` (V, T)
    and frequency ``omegas`` (W,): :func:`~cloe_ros.core.anticipation.harmonic_fits_batch`'s
    basis (libm's cos and sin, as numpy's baseline loops call them)."""
    n_series, n_times = t.shape
    for v in range(n_series):
        for w in range(omegas.shape[0]):
            omega = omegas[w]
            for i in range(n_times):
                wt = omega * t[v, i]
                basis[v, w, i, 0] = 1.0
                basis[v, w, i, 1] = np.cos(wt)
                basis[v, w, i, 2] = np.sin(wt)


@_compiled('void(float64[:, :, :, ::1], float64[:, :, :, ::1], float64[:, :, ::1],'
           ' float64[:, :, ::1])')  # fmt: skip
def harmonic_residuals(basis, coef, y, resid):
    """``resid`` (V, W, C) = the squared error of the fits ``basis @ coef`` (bases (V, W, T, 3),
    coefficients (V, W, 3, C)) to ``y`` (V, T, C), summed over the times: the numpy code's
    ``np.sum((basis @ coef - y) ** 2, axis=-2)`` in its order (a three-term product added from
    its first term; the sum over the times, a reduction along a strided axis, from the first
    time on: 0 plus the first square is that square)."""
    n_series, n_omegas, n_times, _ = basis.shape
    n_columns = y.shape[2]
    for v in range(n_series):
        for w in range(n_omegas):
            b, c = basis[v, w], coef[v, w]
            for k in range(n_columns):
                total = 0.0
                for i in range(n_times):
                    e = (b[i, 0] * c[0, k] + b[i, 1] * c[1, k]) + b[i, 2] * c[2, k] - y[v, i, k]
                    total += e * e
                resid[v, w, k] = total
