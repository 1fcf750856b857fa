"""Compiled kernels of the guard's candidates, the published path and the 95 % radius.

They replace, for one vehicle, the numpy code of
:meth:`~cloe_ros.core.anticipation.Anticipator.combine_steps` (the candidates, the published
combination within the envelope, the scales of the errors), of
:meth:`~cloe_ros.core.anticipation.CoverageRadius.radii` and
:meth:`~cloe_ros.core.anticipation.CoverageRadius.update`, and the radius part of
:meth:`~cloe_ros.core.anticipation.Anticipator.update_steps`: there, a few dozen numpy calls on
arrays of a few hundred entries each, whose cost was the calls'.

Each kernel does the numpy code's floating-point operations in its order, so that under the
golden test's pinned kernels (numpy's baseline loops, OpenBLAS's Nehalem kernels, libm without
its AVX2 and FMA variants) its values are that code's bit for bit (test/core/
test_kernels_combine.py checks it on random and recorded arguments):

* element-wise arithmetic is written in the numpy expression's order and grouping (numba fuses
  no multiply-adds); ``np.sin`` / ``np.cos`` (the turn candidate) are libm's in either;
* the dot products numpy hands to BLAS (``v[:2] @ v[:2]`` of the turn candidate, the norm
  ``sqrt(v0 . v0)`` of :func:`~cloe_ros.core.anticipation.clip_to_envelope`) call numpy's own
  ``ddot`` (:func:`cloe_ros.core.blas.matmul`);
* ``np.einsum('km,mkd->kd', w, paths)`` adds the five products from 0 in the candidates'
  order (its strided sum-of-products loops; measured under the pin for K from 1 to 257);
* ``np.sum(x, axis=-1)`` over the three coordinates adds them in order; the mean over the
  allowed candidates (an outer axis of at most five rows) adds them in order from 0; the
  centroid's ``mean(axis=0)`` over the history's rows is numpy's pairwise sum along that
  strided axis (:func:`pairwise_column`: from 0 below 8 rows, eight accumulators up to 128,
  halves above), divided by the count;
* ``np.sort`` then an index is the order statistic of that rank (NaN last), chosen here
  without sorting; ``np.interp``, ``np.maximum``, ``np.minimum``, ``np.clip`` and
  ``np.maximum.accumulate`` are written out with numpy's NaN rules.

The kernels that call BLAS are defined only where :data:`cloe_ros.core.blas.AVAILABLE`
(:data:`AVAILABLE` says so); the radius's kernels need no BLAS and always are.
"""

from __future__ import annotations

import math

import numpy as np

from cloe_ros.core import blas, kernels
from cloe_ros.core.kernels import Compiler

_compiled = Compiler(__name__, 'cloe_ros.core.kernels_combine')

#: Whether :func:`candidate_paths` and :func:`publish` (they call numpy's BLAS) are defined.
AVAILABLE = blas.AVAILABLE

_F1 = 'float64[::1]'
_F2 = 'float64[:, ::1]'
_A1 = 'float64[:]'
_A2 = 'float64[:, :]'
_I1 = 'int64[::1]'
_N1 = 'intp[:]'

# (anticipation's constants, repeated so that anticipation can import this module)
_POS = (0, 4, 10)  # POSITION
_VEL = (1, 5, 11)  # VELOCITY
SCALE_FLOOR = 0.02
SCALE_GROWTH = 0.05


# ------------------------------------------------------------------------------ sums


@_compiled(f'float64({_A2}, intp, intp, intp)')  # (recursive: typed ahead)
def pairwise_column(x, column, start, n):
    """numpy's pairwise sum (``pairwise_sum_DOUBLE``) of ``x[start:start + n, column]``: from
    0 in order below 8 terms; up to 128, eight accumulators seeded with the first eight terms,
    added as ``((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))``, then the rest in order;
    above, the sums of two halves (the first a multiple of 8 long). What ``np.sum`` /
    ``np.mean`` add along an axis of that array."""
    if n < 8:
        res = 0.0
        for i in range(start, start + n):
            res += x[i, column]
        return res
    if n <= 128:
        r0, r1 = x[start, column], x[start + 1, column]
        r2, r3 = x[start + 2, column], x[start + 3, column]
        r4, r5 = x[start + 4, column], x[start + 5, column]
        r6, r7 = x[start + 6, column], x[start + 7, column]
        i = 8
        while i < n - n % 8:
            j = start + i
            r0 += x[j, column]
            r1 += x[j + 1, column]
            r2 += x[j + 2, column]
            r3 += x[j + 3, column]
            r4 += x[j + 4, column]
            r5 += x[j + 5, column]
            r6 += x[j + 6, column]
            r7 += x[j + 7, column]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += x[start + i, column]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    first = pairwise_column(x, column, start, n2)
    return first + pairwise_column(x, column, start + n2, n - n2)


# ---------------------------------------------------------------------------- radius


@_compiled.helper
def order_statistic(row, rank, work):
    """``np.sort(row)[rank]`` (NaN sorted last), without sorting: the finite and infinite
    entries are gathered into ``work`` (at least ``len(row)`` long) and the one of that rank
    selected (by as many passes for the largest, or the smallest, entries as it is from that
    end, when a few; else by Hoare's selection); NaN if ``rank`` is beyond them. Equal entries
    are equal bits here (the radius's scores are never -0), so which of them is taken does not
    matter."""
    m = 0
    for i in range(row.shape[0]):
        if not np.isnan(row[i]):
            work[m] = row[i]
            m += 1
    if rank >= m:
        return np.nan
    above = m - 1 - rank  # entries ranked after it
    if above <= 8:  # (the radius's level is near 1: its rank is near the top)
        for p in range(above + 1):  # the largest to the end, then the next ...
            end = m - 1 - p
            best = end
            for i in range(end):
                if work[i] > work[best]:
                    best = i
            work[best], work[end] = work[end], work[best]
        return work[rank]
    if rank <= 8:
        for p in range(rank + 1):
            best = p
            for i in range(p + 1, m):
                if work[i] < work[best]:
                    best = i
            work[best], work[p] = work[p], work[best]
        return work[rank]
    low, high = 0, m - 1
    while low < high:
        pivot = work[(low + high) >> 1]
        i, j = low, high
        while i <= j:
            while work[i] < pivot:
                i += 1
            while work[j] > pivot:
                j -= 1
            if i <= j:
                work[i], work[j] = work[j], work[i]
                i += 1
                j -= 1
        if rank <= j:
            high = j
        elif rank >= i:
            low = i
        else:
            break
    return work[rank]


@_compiled.helper
def interp_one(xp, fp, x):
    """``np.interp(x, xp, fp)`` of one ``x`` (the default ``left`` and ``right``): numpy's
    search (the last ``xp`` at or below ``x``; ``xp`` increasing) and arithmetic, with its
    fall-backs where the slope gives NaN."""
    n = xp.shape[0]
    if np.isnan(x):
        return x
    if x > xp[n - 1]:
        return fp[n - 1]
    if x < xp[0]:
        return fp[0]
    j = kernels._count_not_after(xp, x) - 1  # the last xp[j] <= x
    if j == n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    res = slope * (x - xp[j]) + fp[j]
    if np.isnan(res):
        res = slope * (x - xp[j + 1]) + fp[j + 1]
        if np.isnan(res) and fp[j] == fp[j + 1]:
            res = fp[j]
    return res


@_compiled(f'void({_F2}, {_I1}, {_F1}, {_F1}, {_F1}, int64, {_F1}, {_F1})')
def coverage_radii(errors, count, level, prior, offsets, min_errors, scales, out):
    """``out`` (K,) = :meth:`~cloe_ros.core.anticipation.CoverageRadius.radii` ``(scales)``,
    m, of a radius whose scores are ``errors`` (K, W) (its ``_errors``, NaN unfilled), ``count``
    (K,) (``_count``), ``level`` (K,), ``prior`` (K,) m, ``offsets`` (K,) s and ``min_errors``:
    the prior where no horizon has ``min_errors`` scores; else each such horizon's score of
    rank ``min(ceil(level n), n) - 1`` (clipped at 0; ``n`` its scores, at most W) among its
    sorted scores, the later horizons the last one's, the others (and the non-finite)
    interpolated over the offsets, times ``scales`` (K,), at least 1e-3 m, then the running
    maximum (numpy's NaN rules throughout)."""
    k_max, window = errors.shape
    last = -1
    have = 0
    for k in range(k_max):
        if count[k] >= min_errors:
            last = k
            have += 1
    if have == 0:
        for k in range(k_max):
            out[k] = prior[k]
        return
    work = np.empty(window)
    xp, fp = np.empty(have), np.empty(have)
    q = 0
    for k in range(k_max):
        if count[k] >= min_errors:
            n = min(count[k], window)
            pos = min(math.ceil(level[k] * n), n) - 1
            out[k] = order_statistic(errors[k], max(pos, 0), work)
            xp[q], fp[q] = offsets[k], out[k]
            q += 1
        else:
            out[k] = np.nan
    for k in range(last + 1, k_max):
        out[k] = out[last]
    for k in range(k_max):
        if not np.isfinite(out[k]):
            out[k] = interp_one(xp, fp, offsets[k])
    running = 0.0
    for k in range(k_max):
        y = out[k] * scales[k]
        if not (y >= 1e-3 or np.isnan(y)):  # np.maximum(y, 1e-3)
            y = 1e-3
        if k == 0 or not (running >= y or np.isnan(running)):  # np.maximum.accumulate
            running = y
        out[k] = running


@_compiled.helper
def coverage_update(ks, errors, radii_then, scales, scores, count, level, gain, coverage):
    """:meth:`~cloe_ros.core.anticipation.CoverageRadius.update` ``(ks, errors, radii_then,
    scales)`` of a radius whose scores are ``scores`` (K, W) (its ``_errors``), ``count`` (K,)
    (``_count``) and ``level`` (K,), with its ``gain`` and ``coverage``, in place: each scored
    error (m) over its scale into the slot ``count % W`` of its horizon, the count raised by 1,
    the level moved by ``gain (miss - (1 - coverage))`` and clipped to [0, 1]. As numpy's
    fancy assignments do it: every value read before any is written, so a horizon twice in
    ``ks`` is counted once and keeps the last of its writes."""
    n = ks.shape[0]
    window = scores.shape[1]
    cols = np.empty(n, np.int64)
    counts = np.empty(n, np.int64)
    levels = np.empty(n)
    hit = 1.0 - coverage
    for i in range(n):
        k = ks[i]
        cols[i] = count[k] % window
        counts[i] = count[k] + 1
        miss = 1.0 if errors[i] > radii_then[i] else 0.0
        x = level[k] + gain * (miss - hit)
        if not np.isnan(x):  # np.clip(x, 0.0, 1.0)
            if x < 0.0:
                x = 0.0
            elif x > 1.0:
                x = 1.0
        levels[i] = x
    for i in range(n):
        scores[ks[i], cols[i]] = errors[i] / scales[i]
    for i in range(n):
        count[ks[i]] = counts[i]
    for i in range(n):
        level[ks[i]] = levels[i]


@_compiled(f'void({_N1}, {_N1}, {_A2}, {_F2}, {_F2}, {_F2}, {_I1}, {_F1}, float64, float64)')
def coverage_scored(slots, horizons, squared, radii, scales, scores, count, level, gain,
                    coverage):  # fmt: skip
    """The radius part of :meth:`~cloe_ros.core.anticipation.Anticipator.update_steps`: the
    scored poses (a :class:`~cloe_ros.core.anticipation.Scores`' ``slots`` (n,), ``horizons``
    (n,) and ``squared`` (n, M), its last column the published path's squared error, m^2),
    their errors ``sqrt(squared[:, -1])`` against the radii and scales published with their
    prediction (``radii``, ``scales``: the anticipator's ``_radii`` and ``_scales`` (P, K)),
    given to :func:`coverage_update` (the radius's state ``scores``, ``count``, ``level``,
    ``gain``, ``coverage``) at once when no horizon is scored twice, else prediction by
    prediction (each run of one slot)."""
    n = horizons.shape[0]
    if n == 0:
        return
    last = squared.shape[1] - 1
    errors, radii_then, scales_then = np.empty(n), np.empty(n), np.empty(n)
    seen = np.zeros(scores.shape[0], np.bool_)
    unique = True
    for i in range(n):
        errors[i] = np.sqrt(squared[i, last])
        radii_then[i] = radii[slots[i], horizons[i]]
        scales_then[i] = scales[slots[i], horizons[i]]
        if seen[horizons[i]]:
            unique = False
        seen[horizons[i]] = True
    if unique:
        coverage_update(horizons, errors, radii_then, scales_then, scores, count, level, gain,
                        coverage)  # fmt: skip
        return
    a = 0
    for b in range(1, n + 1):
        if b == n or slots[b] != slots[b - 1]:
            coverage_update(horizons[a:b], errors[a:b], radii_then[a:b], scales_then[a:b],
                            scores, count, level, gain, coverage)  # fmt: skip
            a = b


# ---------------------------------------------------------------------- the candidates

if blas.AVAILABLE:

    @_compiled.helper
    def dot_self(x):
        """``x @ x`` of a 1-D ``x`` (numpy's ``ddot`` on a contiguous copy, as ``np.linalg.norm``
        takes it), through :func:`cloe_ros.core.blas.matmul`."""
        n = x.shape[0]
        v = np.empty((1, n))
        for i in range(n):
            v[0, i] = x[i]
        out = np.empty((1, 1))
        blas.matmul(v, v.T, out)
        return out[0, 0]

    @_compiled(f'void({_A1}, {_A1}, {_F1}, {_A2}, {_A2}, float64[:, :, ::1])')
    def candidate_paths(measured, coupling, poses, recent, model, paths):
        """``paths[0:5]`` (each (K, 3), m) as :meth:`~cloe_ros.core.anticipation.Anticipator.
        combine_steps` fills them, from the ``measured`` state (12,), the model's ``coupling``
        (2,), the pose offsets ``poses`` (K,) s, the history's ``recent`` rows (T, 12) (its
        measured states of the last ``centroid_window``) and the closed loop's ``model``
        positions (K, 3): the model; :func:`~cloe_ros.core.anticipation.turn_positions`;
        constant velocity ``p + np.outer(poses, v)``; hold; the centroid of the recent
        positions (``mean(axis=0)``: their pairwise sum over the count), or the measured
        position when there are none."""
        k_max = poses.shape[0]
        px, py, pz = measured[_POS[0]], measured[_POS[1]], measured[_POS[2]]
        vx, vy, vz = measured[_VEL[0]], measured[_VEL[1]], measured[_VEL[2]]
        for k in range(k_max):
            for d in range(3):
                paths[0, k, d] = model[k, d]
        # turn_positions
        a0 = coupling[0] * measured[2]
        a1 = coupling[1] * measured[6]
        for k in range(k_max):
            paths[1, k, 2] = pz + poses[k] * vz
        vxy = np.empty(2)
        vxy[0], vxy[1] = vx, vy
        speed2 = dot_self(vxy)
        omega = (vx * a1 - vy * a0) / speed2 if speed2 > 1e-4 else 0.0
        if abs(omega) * poses[k_max - 1] < 1e-3:
            for k in range(k_max):
                paths[1, k, 0] = px + poses[k] * vx
                paths[1, k, 1] = py + poses[k] * vy
        else:
            for k in range(k_max):
                wt = omega * poses[k]
                s, c = np.sin(wt), np.cos(wt)
                paths[1, k, 0] = px + (s * vx - (1.0 - c) * vy) / omega
                paths[1, k, 1] = py + ((1.0 - c) * vx + s * vy) / omega
        # constant velocity, hold
        for k in range(k_max):
            paths[2, k, 0] = px + poses[k] * vx
            paths[2, k, 1] = py + poses[k] * vy
            paths[2, k, 2] = pz + poses[k] * vz
            paths[3, k, 0], paths[3, k, 1], paths[3, k, 2] = px, py, pz
        # the centroid
        t = recent.shape[0]
        if t:
            cx = pairwise_column(recent, _POS[0], 0, t) / t
            cy = pairwise_column(recent, _POS[1], 0, t) / t
            cz = pairwise_column(recent, _POS[2], 0, t) / t
        else:
            cx, cy, cz = px, py, pz
        for k in range(k_max):
            paths[4, k, 0], paths[4, k, 1], paths[4, k, 2] = cx, cy, cz

    @_compiled(f'void({_A2}, float64[:, :, ::1], {_A1}, {_A1}, {_F1}, float64, float64,'
               f' boolean[:], {_F1})')  # fmt: skip
    def publish(w, paths, p0, v0, poses, max_speed, max_acceleration, allowed, scales):
        """The published path into ``paths[5]`` and the scales of its errors into ``scales``
        (K,), m, as :meth:`~cloe_ros.core.anticipation.Anticipator.combine_steps` makes them
        from the weights ``w`` (K, 5) of the candidates ``paths[:5]`` (each (K, 3), m):
        ``np.einsum('km,mkd->kd', w, paths[:-1])`` (the products added from 0 in the
        candidates' order), moved into the envelope of a quadrotor at ``p0`` (3,) moving at
        ``v0`` (3,) (:func:`~cloe_ros.core.anticipation.clip_to_envelope`, its ``np.linalg.norm``
        numpy's ``ddot``; ``poses`` (K,) s, ``max_speed`` m/s, ``max_acceleration`` m/s^2);
        then the spread of the ``allowed`` (5,) candidates about it (the root of the mean over
        them of the squared distances; fewer than 8 candidates, so numpy's pairwise sum over
        them is in order) plus ``SCALE_FLOOR + SCALE_GROWTH * poses``."""
        k_max = poses.shape[0]
        n_candidates = w.shape[1]
        pub = paths[n_candidates]
        for k in range(k_max):
            for d in range(3):
                s = 0.0
                for m in range(n_candidates):
                    s += w[k, m] * paths[m, k, d]
                pub[k, d] = s
        # clip_to_envelope
        norm = np.sqrt(dot_self(v0))
        speed = max_speed if max_speed < norm else norm  # min(norm, max_speed)
        half_acceleration = 0.5 * max_acceleration
        for k in range(k_max):
            h = poses[k]
            a = speed * h + half_acceleration * (h * h)
            b = max_speed * h
            reach = a if (a <= b or np.isnan(a)) else b  # np.minimum
            d0, d1, d2 = pub[k, 0] - p0[0], pub[k, 1] - p0[1], pub[k, 2] - p0[2]
            dist = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
            scale = 1.0
            if dist > reach:
                floor = dist if (dist >= 1e-300 or np.isnan(dist)) else 1e-300  # np.maximum
                scale = reach / floor
            pub[k, 0] = p0[0] + d0 * scale
            pub[k, 1] = p0[1] + d1 * scale
            pub[k, 2] = p0[2] + d2 * scale
        # the scales: the allowed candidates' spread about the published path, plus a floor
        n_allowed = 0
        for m in range(n_candidates):
            if allowed[m]:
                n_allowed += 1
        for k in range(k_max):
            total = 0.0
            for m in range(n_candidates):
                if allowed[m]:
                    g0 = paths[m, k, 0] - pub[k, 0]
                    g1 = paths[m, k, 1] - pub[k, 1]
                    g2 = paths[m, k, 2] - pub[k, 2]
                    total += (g0 * g0 + g1 * g1) + g2 * g2
            spread = np.sqrt(total / n_allowed)
            scales[k] = (spread + SCALE_FLOOR) + SCALE_GROWTH * poses[k]
