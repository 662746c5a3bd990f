"""Compiled form of `safety.drift_bounds.lower_bound` for one interval of one arc: the
certified lower bound of the passive-safety margin from the interval's end points (values and
slopes) and the arc's derivative bounds, in the oracle's stages (Lipschitz, the cubic Hermite
interpolants of d^2 and |v|^2 with their h^4 / 384 error bounds, the chord bound), with the
cubic helpers they use. Called by `drift` (the search).

numba's on-disk cache checks only the file of the function it compiled: after an edit here,
the cached `drift.violated` and `drift.minimum` keep the old code until kernels/drift.py
changes too or the cache is removed (the `__pycache__` folders, or NUMBA_CACHE_DIR).

Imports only numpy and numba.
"""
from __future__ import annotations

import math

from numba import njit

N_SUB = 32  # sub-grid of the chord bound (`safety.drift_bounds.N_SUB`)
# an evaluated point (7,): tau, m, dm, f, df, big_w, dbig_w
TAU, M, DM, F, DF, W, DW = range(7)

_JIT = dict(cache=True, nogil=True)


@njit(**_JIT)
def _cubic(f0, f1, g0, g1, h):
    """(c2, c3, crit0, crit1) of the cubic Hermite interpolant on [0, h] (`_Cubic`)."""
    hh = h if h > 0.0 else 1.0
    slope = (f1 - f0) / hh
    c2 = (3.0 * slope - 2.0 * g0 - g1) / hh
    c3 = (g0 + g1 - 2.0 * slope) / (hh * hh)
    disc = max(c2 * c2 - 3.0 * c3 * g0, 0.0)
    qq = -(c2 + (1.0 if c2 >= 0.0 else -1.0) * math.sqrt(disc))
    crit0 = qq / (3.0 * c3) if c3 != 0.0 else math.nan
    crit1 = g0 / qq if qq != 0.0 else math.nan
    if not math.isfinite(crit0):
        crit0 = 0.0
    if not math.isfinite(crit1):
        crit1 = 0.0
    return c2, c3, min(max(crit0, 0.0), h), min(max(crit1, 0.0), h)


@njit(**_JIT)
def _cubic_at(f0, g0, c2, c3, s):
    return f0 + s * (g0 + s * (c2 + s * c3))


@njit(**_JIT)
def _cubic_min(f0, f1, g0, c2, c3, k0, k1):
    return min(min(f0, f1), min(_cubic_at(f0, g0, c2, c3, k0), _cubic_at(f0, g0, c2, c3, k1)))


@njit(**_JIT)
def _cubic_max(f0, f1, g0, c2, c3, k0, k1):
    return max(max(f0, f1), max(_cubic_at(f0, g0, c2, c3, k0), _cubic_at(f0, g0, c2, c3, k1)))


@njit(**_JIT)
def _hermite_error(a0, a1, a2, a3, a4, h):
    return 2.0 * (a0 * a4 + 4.0 * a1 * a3 + 3.0 * a2 * a2) * h ** 4 / 384.0


@njit(**_JIT)
def _sigma_up(w_up, d_lo, k0):
    if d_lo > 0.0:
        return min(math.sqrt(max(w_up, 0.0)) / d_lo, k0)
    return k0


@njit(**_JIT)
def lower_bound(lo, hi, ys, ks, q, chance, target, sign_only):
    """`safety.drift_bounds.lower_bound(..., target, sign_only)` for one interval: the
    interval's end points `lo`, `hi` (7,) (the layout above), the arc's derivative bounds
    `ys`, `ks` (5,), the search's `target` [-]."""
    h = hi[TAU] - lo[TAU]
    k0 = ks[0] if chance else 0.0
    lb = max(0.5 * (math.sqrt(lo[F]) + math.sqrt(hi[F]) - ys[1] * h), 0.0) - 1.0 - q * k0
    if not lb < target:
        return lb
    y0 = min(math.sqrt(max(lo[F], hi[F])) + 0.5 * h * ys[1], ys[0])
    e_f = _hermite_error(y0, ys[1], ys[2], ys[3], ys[4], h)
    c2, c3, k_0, k_1 = _cubic(lo[F], hi[F], lo[DF], hi[DF], h)
    d_lo = math.sqrt(max(_cubic_min(lo[F], hi[F], lo[DF], c2, c3, k_0, k_1) - e_f, 0.0))
    if not chance:
        return max(lb, d_lo - 1.0)
    lb = max(lb, d_lo - 1.0 - q * ks[0])  # never above stage 2's: the same result
    if sign_only and not lb < max(target, 0.0):
        return lb
    # stage 2: sigma from the interpolant of W = |v|^2
    yl = (y0, ys[1], ys[2], ys[3], ys[4])
    vs0 = ks[0] * yl[0]
    vs1 = ks[0] * yl[1] + ks[1] * yl[0]
    vs2 = ks[0] * yl[2] + 2.0 * ks[1] * yl[1] + ks[2] * yl[0]
    vs3 = ks[0] * yl[3] + 3.0 * ks[1] * yl[2] + 3.0 * ks[2] * yl[1] + ks[3] * yl[0]
    vs4 = (ks[0] * yl[4] + 4.0 * ks[1] * yl[3] + 6.0 * ks[2] * yl[2] + 4.0 * ks[3] * yl[1]
           + ks[4] * yl[0])
    v0 = min(math.sqrt(max(lo[W], hi[W])) + 0.5 * h * vs1, vs0)
    e_w = _hermite_error(v0, vs1, vs2, vs3, vs4, h)
    w2, w3, j_0, j_1 = _cubic(lo[W], hi[W], lo[DW], hi[DW], h)
    w_up = _cubic_max(lo[W], hi[W], lo[DW], w2, w3, j_0, j_1) + e_w
    lb = max(lb, d_lo - 1.0 - q * _sigma_up(w_up, d_lo, ks[0]))
    if not lb < target:
        return lb
    # stage 3: the chord bound on g = d - q sigma
    g_min = math.inf
    for j in range(N_SUB + 1):
        s = h * j / N_SUB
        f_pt = max(_cubic_at(lo[F], lo[DF], c2, c3, s) - e_f, 0.0)
        w_pt = _cubic_at(lo[W], lo[DW], w2, w3, s) + e_w
        g = math.sqrt(f_pt) - q * _sigma_up(w_pt, math.sqrt(f_pt), ks[0])
        g_min = min(g_min, g)
    f_hi = _cubic_max(lo[F], hi[F], lo[DF], c2, c3, k_0, k_1) + e_f
    w_lo = max(_cubic_min(lo[W], hi[W], lo[DW], w2, w3, j_0, j_1) - e_w, 0.0)
    if not (d_lo > 0.0 and f_hi > 0.0):
        return lb
    sig_lo = math.sqrt(w_lo / f_hi)
    if not sig_lo > 0.0:
        return lb
    e1 = ys[1] / d_lo
    e2 = 2.0 * ys[2] / d_lo + 5.0 * e1 * e1
    u1 = ks[1] + ks[0] * e1
    u2 = ks[2] + 2.0 * ks[1] * e1 + ks[0] * e2
    curv = ys[2] + q * (u2 + u1 * u1 / sig_lo)
    chord = g_min - 1.0 - curv * (h / N_SUB) ** 2 / 8.0
    if math.isfinite(chord):
        lb = max(lb, chord)
    return lb
