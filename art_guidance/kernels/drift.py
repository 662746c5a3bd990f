"""Compiled form of `safety.drift.DriftArcs.violated`: the sign-only certified search of the
passive-safety margin on drift arcs, one arc at a time.

The numpy oracle (`safety/drift.py`, `drift_bounds.py` and `drift_search.py`, whose
docstrings hold the mathematics) runs the search vectorised over every interval of every arc of
a batch: ~650 numpy calls of 1-5 us per rollout step over arrays of 8 x ~40. Here the same steps
run in one compiled call per batch, arc by arc, with scalar arithmetic: the drift samples, the
staged lower bounds (Lipschitz, the Hermite interpolants of d^2 and |v|^2, the chord bound), the
safeguarded cubic-Hermite refinement of bracketed minima, and the splitting of uncertified
intervals. Only the decision (minimum margin below zero or not) is returned.

What differs from the oracle: sums are taken in another order (rounding: a decision can differ
only where the certified minimum is within rounding of zero), and the cap on intervals split
per level is per arc (MAX_OPEN of its own) where the oracle caps the batch at MAX_OPEN times the
number of arcs (so an arc's result there could depend on its batch-mates; only degenerate arcs,
e.g. through the ellipsoid's centre, reach either cap).

The staged lower bound of one interval is `drift_bounds.lower_bound`. Imports only numpy, numba
and the package's own kernels.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from art_guidance.kernels.drift_bounds import (  # noqa: F401 (N_SUB: the oracle's, tested)
    DF, DM, DW, F, M, N_SUB, TAU, W, lower_bound,
)

N_TERMS = 18
CERT_TOL = 1e-4
CERT_TOL_REL = 1e-3
SPLIT = 4
MAX_LEVELS = 8
MAX_OPEN = 32
REFINE_ITERS = 4
D_FLOOR = 1e-12
WS_SIZE = 84  # work array of `_point`

_JIT = dict(cache=True, nogil=True)


@njit(**_JIT)
def _point(tau, coef, maps, x_cov, q, chance, u0, udot, wdot, out, ws):
    """The margin and certificate quantities of one arc at offset `tau` [s] into `out` (7,)
    (`DriftArcs.points` for one point); `ws`: a work array (WS_SIZE,)."""
    u = u0 + udot * tau
    cu, su = math.cos(u), math.sin(u)
    c, s = math.cos(wdot * tau), math.sin(wdot * tau)
    b0 = ws[0:18]
    b1 = ws[18:36]
    s0 = (1.0, tau, c, s, tau * c, tau * s)
    s1 = (0.0, 1.0, -wdot * s, wdot * c, c - wdot * tau * s, s + wdot * tau * c)
    for j in range(6):
        b0[j] = s0[j]
        b0[6 + j] = cu * s0[j]
        b0[12 + j] = su * s0[j]
        b1[j] = s1[j]
        b1[6 + j] = -udot * su * s0[j] + cu * s1[j]
        b1[12 + j] = udot * cu * s0[j] + su * s1[j]
    mt = ws[36:54]
    dmt = ws[54:72]
    if chance:
        for r in range(18):
            acc0 = 0.0
            acc1 = 0.0
            for k in range(N_TERMS):
                acc0 += b0[k] * maps[k, r]
                acc1 += b1[k] * maps[k, r]
            mt[r] = acc0
            dmt[r] = acc1
    _point_at(tau, b0, b1, mt, dmt, coef, x_cov, q, chance, out, ws)


@njit(**_JIT)
def _point_at(tau, b0, b1, mt, dmt, coef, x_cov, q, chance, out, ws):
    """`_point` from the basis b0, b1 (18,) and (chance) ``Mt = b0 @ G``, ``b1 @ G`` (18,)."""
    y0 = y1 = y2 = dy0 = dy1 = dy2 = 0.0
    for k in range(N_TERMS):
        y0 += b0[k] * coef[k, 0]
        y1 += b0[k] * coef[k, 1]
        y2 += b0[k] * coef[k, 2]
        dy0 += b1[k] * coef[k, 0]
        dy1 += b1[k] * coef[k, 1]
        dy2 += b1[k] * coef[k, 2]
    f = y0 * y0 + y1 * y1 + y2 * y2
    df = 2.0 * (y0 * dy0 + y1 * dy1 + y2 * dy2)
    d = max(math.sqrt(f), D_FLOOR)
    dd = 0.5 * df / d
    out[TAU] = tau
    out[F] = f
    out[DF] = df
    if not chance:
        out[M] = math.sqrt(f) - 1.0
        out[DM] = dd
        out[W] = 0.0
        out[DW] = 0.0
        return
    w = ws[72:78]
    dw = ws[78:84]
    for i in range(6):
        w[i] = mt[i] * y0 + mt[6 + i] * y1 + mt[12 + i] * y2
        dw[i] = (dmt[i] * y0 + dmt[6 + i] * y1 + dmt[12 + i] * y2
                 + mt[i] * dy0 + mt[6 + i] * dy1 + mt[12 + i] * dy2)
    big_w = 0.0
    dbig_w = 0.0
    for i in range(6):
        xw = 0.0
        for j in range(6):
            xw += w[j] * x_cov[j, i]
        big_w += xw * w[i]
        dbig_w += xw * dw[i]
    big_w = max(big_w, 0.0)
    dbig_w *= 2.0
    v = math.sqrt(big_w)
    dv = 0.5 * dbig_w / v if v > 0.0 else 0.0
    sigma = v / d
    dsigma = dv / d - v * dd / (d * d)
    out[M] = math.sqrt(f) - 1.0 - q * sigma
    out[DM] = dd - q * dsigma
    out[W] = big_w
    out[DW] = dbig_w


@njit(**_JIT)
def _target(best, sign_only):
    """`drift_search._target` (the full search) or `_sign_target` (the sign-only one)."""
    full = best - CERT_TOL - CERT_TOL_REL * abs(best)
    if not sign_only:
        return full
    if best < 0.0:
        return -math.inf
    return min(full, 0.0)


@njit(**_JIT)
def _refine(lo0, hi0, coef, maps, x_cov, q, chance, u0, udot, wdot, ws):
    """(offset [s], margin) of the best point found by safeguarded cubic-Hermite bracketing of
    m' = 0 on one bracket (`safety.drift_search.refine`)."""
    lo = lo0.copy()
    hi = hi0.copy()
    best_tau = lo[TAU] if lo[M] <= hi[M] else hi[TAU]
    best_m = min(lo[M], hi[M])
    bisect = False
    p = np.empty(7)
    for _ in range(REFINE_ITERS):
        width = hi[TAU] - lo[TAU]
        slope = (hi[M] - lo[M]) / (width if width > 0.0 else 1.0)
        d1 = lo[DM] + hi[DM] - 3.0 * slope
        d2 = math.sqrt(max(d1 * d1 - lo[DM] * hi[DM], 0.0))
        den = hi[DM] - lo[DM] + 2.0 * d2
        t = hi[TAU] - width * (hi[DM] + d2 - d1) / den if den != 0.0 else math.nan
        if not math.isfinite(t) or bisect:
            t = 0.5 * (lo[TAU] + hi[TAU])
        t = min(max(t, lo[TAU] + 0.05 * width), hi[TAU] - 0.05 * width)
        _point(t, coef, maps, x_cov, q, chance, u0, udot, wdot, p, ws)
        if p[M] < best_m:
            best_tau = p[TAU]
            best_m = p[M]
        if p[DM] < 0.0:
            lo[:] = p
        else:
            hi[:] = p
        bisect = (hi[TAU] - lo[TAU]) > 0.95 * width
    return best_tau, best_m


@njit(**_JIT)
def _record(cands, n_c, tau, m, row):
    """Append a candidate (tau, m, row) to `cands` (C, 3); returns the new count."""
    if n_c < cands.shape[0]:
        cands[n_c, 0] = tau
        cands[n_c, 1] = m
        cands[n_c, 2] = 1.0 if row else 0.0
        return n_c + 1
    return n_c


@njit(**_JIT)
def _arc_search(coef, maps, x_cov, q, chance, y_sup, k_sup, u0, udot, wdot, tau_grid,
                grid_b0, grid_b1, grid_mt, grid_dmt, ws, sign_only, decide, cands):
    """The certified search of one arc (`DriftArcs.minimum` / `violated` for one arc; grid_*:
    (S, 18) the basis and maps at the drift samples of the arc's node).

    Returns (certified lower bound of the minimum margin, number of candidates recorded in
    `cands` (C, 3): tau [s], margin, 1 for a row candidate (samples and refined minima), 0
    for split points, in the order the oracle appends them). `decide`: `violated`'s form
    (sign-only, an arc a drift sample shows inside is decided by it; nothing recorded)."""
    n_s = tau_grid.size
    pts = np.empty((n_s, 7))
    n_c = 0
    for j in range(n_s):
        _point_at(tau_grid[j], grid_b0[j], grid_b1[j], grid_mt[j], grid_dmt[j], coef, x_cov,
                  q, chance, pts[j], ws)
        if not decide:
            n_c = _record(cands, n_c, pts[j, TAU], pts[j, M], True)
    best = pts[0, M]
    for j in range(1, n_s):
        best = min(best, pts[j, M])
    if n_s == 1 or (decide and best < 0.0):
        return best, n_c
    floor = best
    lo = pts[:-1].copy()
    hi = pts[1:].copy()
    refined = np.zeros(n_s - 1, np.bool_)
    for level in range(MAX_LEVELS + 1):
        n_i = lo.shape[0]
        lb = np.empty(n_i)
        target = _target(best, sign_only)
        for i in range(n_i):
            lb[i] = lower_bound(lo[i], hi[i], y_sup, k_sup, q, chance, target, sign_only)
        any_bracket = False
        for i in range(n_i):
            if lb[i] < target and lo[i, DM] < 0.0 and hi[i, DM] > 0.0 and not refined[i]:
                tau_r, m_r = _refine(lo[i], hi[i], coef, maps, x_cov, q, chance, u0, udot,
                                     wdot, ws)
                if not decide:
                    n_c = _record(cands, n_c, tau_r, m_r, True)
                best = min(best, m_r)
                refined[i] = True
                any_bracket = True
        if any_bracket:
            target = _target(best, sign_only)
        n_open = 0
        for i in range(n_i):
            if lb[i] < target:
                n_open += 1
        if n_open == 0 or level == MAX_LEVELS:
            for i in range(n_i):
                floor = min(floor, lb[i])
            return min(floor, best), n_c
        keep = np.zeros(n_i, np.bool_)
        if n_open > MAX_OPEN:  # the MAX_OPEN lowest bounds of this arc
            order = np.argsort(lb, kind="mergesort")
            for r in range(MAX_OPEN):
                keep[order[r]] = True
            n_open = MAX_OPEN
        else:
            for i in range(n_i):
                keep[i] = lb[i] < target
        for i in range(n_i):
            if not keep[i]:
                floor = min(floor, lb[i])
        new_lo = np.empty((n_open * SPLIT, 7))
        new_hi = np.empty((n_open * SPLIT, 7))
        new_ref = np.zeros(n_open * SPLIT, np.bool_)
        ends = np.empty((SPLIT + 1, 7))
        r = 0
        for i in range(n_i):
            if not keep[i]:
                continue
            ends[0] = lo[i]
            ends[SPLIT] = hi[i]
            span = hi[i, TAU] - lo[i, TAU]
            for j in range(1, SPLIT):
                _point(lo[i, TAU] + span * (j / SPLIT), coef, maps, x_cov, q, chance, u0,
                       udot, wdot, ends[j], ws)
                best = min(best, ends[j, M])
                if not decide:
                    n_c = _record(cands, n_c, ends[j, TAU], ends[j, M], False)
            for j in range(SPLIT):
                new_lo[r] = ends[j]
                new_hi[r] = ends[j + 1]
                new_ref[r] = refined[i]
                r += 1
        lo, hi, refined = new_lo, new_hi, new_ref
    return min(floor, best), n_c  # not reached: the loop returns at MAX_LEVELS


@njit(**_JIT)
def _items(maps, sup, z, x_cov, chance, coef, y_sup, k_sup):
    """One arc's `DriftArcs.items`: ``coef = G_k z`` (18, 3) and the bounds y_sup, k_sup (5,),
    written into the arrays given (maps (18, 18), sup (5, 18) of its node)."""
    norm = np.empty(N_TERMS)
    knorm = np.empty(N_TERMS)
    for k in range(N_TERMS):
        acc = 0.0
        for c in range(3):
            v = 0.0
            for i in range(6):
                v += maps[k, 6 * c + i] * z[i]
            coef[k, c] = v
            acc += v * v
        norm[k] = math.sqrt(acc)
        if chance:
            kk = 0.0
            for c in range(3):
                for j in range(6):
                    gx = 0.0
                    for i in range(6):
                        gx += maps[k, 6 * c + i] * x_cov[i, j]
                    kk += gx * maps[k, 6 * c + j]
            knorm[k] = math.sqrt(max(kk, 0.0))
    for r in range(5):
        a = 0.0
        b = 0.0
        for k in range(N_TERMS):
            a += sup[r, k] * norm[k]
            if chance:
                b += sup[r, k] * knorm[k]
        y_sup[r] = a
        k_sup[r] = b


@njit(**_JIT)
def violated(node, z, x_cov, q, chance, maps, sup, u0, udot, wdot, tau_grid, grid_b0,
             grid_b1, grid_mt, grid_dmt):
    """(M,) bool: whether the certified minimum margin of the drift arc of each post-burn
    state is below zero (`DriftArcs.violated` of `DriftArcs.items(node, z, x_cov, q)`).

    Args:
        node: (M,) int node of each arc; z: (M, 6) post-burn ROE [m]; x_cov: (M, 6, 6)
            post-burn covariance [m^2] (chance; any (M, 6, 6) array otherwise).
        q: confidence multiplier [-]; chance: the chance-constrained margin.
        maps: (N, 18, 18) ``G_k`` [1/m]; sup: (N, 5, 18) derivative bounds of the basis;
        u0, udot, wdot: (N,) chief latitude [rad] and rates [rad/s] at the nodes.
        tau_grid: (S,) drift sample offsets [s]; grid_b0, grid_b1, grid_mt, grid_dmt:
            (N, S, 18) the basis, its derivative and the maps at the samples.
    """
    n = node.size
    out = np.empty(n, np.bool_)
    ws = np.empty(WS_SIZE)
    coef = np.empty((N_TERMS, 3))
    y_sup = np.empty(5)
    k_sup = np.empty(5)
    cands = np.empty((0, 3))
    for i in range(n):
        k = node[i]
        _items(maps[k], sup[k], z[i], x_cov[i], chance, coef, y_sup, k_sup)
        low, _ = _arc_search(coef, maps[k], x_cov[i], q, chance, y_sup, k_sup, u0[k],
                             udot[k], wdot[k], tau_grid, grid_b0[k], grid_b1[k], grid_mt[k],
                             grid_dmt[k], ws, True, True, cands)
        out[i] = low < 0.0
    return out


@njit(**_JIT)
def minimum(node, coef, x_cov, q, chance, y_sup, k_sup, sign_only, maps, u0, udot, wdot,
            tau_grid, grid_b0, grid_b1, grid_mt, grid_dmt):
    """`DriftArcs.minimum` of M arcs given as `DriftArcs.items` gives them: the certified
    lower bound of each arc's minimum margin (M,), t* (M,) [s], the margin at t* (M,), and
    (M, S) offsets [s]: t*, then the S - 1 row candidates other than t* by increasing margin
    (`ArcMinimum.top_k`; ties in the oracle's order).

    Args: node (M,) int; coef (M, 18, 3); x_cov (M, 6, 6) (chance; any otherwise); q;
    chance; y_sup, k_sup (M, 5); sign_only: the sign-only search; the node tables as
    `violated` takes them.
    """
    n = node.size
    n_s = tau_grid.size
    margin = np.empty(n)
    t_star = np.empty(n)
    m_star = np.empty(n)
    top = np.empty((n, n_s))
    ws = np.empty(WS_SIZE)
    cap = n_s + (MAX_LEVELS + 1) * (max(n_s - 1, MAX_OPEN * SPLIT) + (SPLIT - 1) * MAX_OPEN)
    cands = np.empty((cap, 3))
    for i in range(n):
        k = node[i]
        low, n_c = _arc_search(coef[i], maps[k], x_cov[i], q, chance, y_sup[i], k_sup[i],
                               u0[k], udot[k], wdot[k], tau_grid, grid_b0[k], grid_b1[k],
                               grid_mt[k], grid_dmt[k], ws, sign_only, False, cands)
        first = 0
        for c in range(1, n_c):
            if cands[c, 1] < cands[first, 1]:
                first = c
        margin[i] = low
        t_star[i] = cands[first, 0]
        m_star[i] = cands[first, 1]
        top[i, 0] = t_star[i]
        rows = np.empty(n_c, np.int64)
        n_r = 0
        for c in range(n_c):
            if cands[c, 2] > 0.0 and cands[c, 0] != t_star[i]:
                rows[n_r] = c
                n_r += 1
        order = np.argsort(cands[rows[:n_r], 1], kind="mergesort")
        for r in range(1, n_s):
            top[i, r] = cands[rows[order[min(r - 1, n_r - 1)]], 0] if n_r else t_star[i]
    return margin, t_star, m_star, top


def warm_up() -> None:
    """Compile (or load from the cache) `violated` for the argument types the doors pass."""
    n_s = 3
    node = np.zeros(1, np.int64)
    z = np.zeros((1, 6))
    z[0, 0] = 1.0
    maps = np.zeros((1, N_TERMS, 18))
    maps[0, 0, 0] = 2.0  # an arc outside the ellipsoid: the search runs
    x_cov = np.zeros((1, 6, 6))
    sup = np.zeros((1, 5, N_TERMS))
    one = np.zeros(1)
    grid = np.zeros((1, n_s, N_TERMS))
    tau = np.linspace(0.0, 100.0, n_s)
    coef = np.zeros((1, N_TERMS, 3))
    coef[0, 0, 0] = 2.0
    bounds = np.zeros((1, 5))
    for chance in (True, False):
        violated(node, z, x_cov, 3.0, chance, maps, sup, one, one, one, tau, grid, grid, grid,
                 grid)
        for sign_only in (True, False):
            minimum(node, coef, x_cov, 3.0, chance, bounds, bounds, sign_only, maps, one, one,
                    one, tau, grid, grid, grid, grid)
