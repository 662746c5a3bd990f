"""Certified lower bounds of the passive-safety margin on intervals of a drift arc.

Step 2 of `art_guidance.safety.drift` (see its docstring for the closed form and the search). On an
interval ``[a, a + h]`` of an arc with sampled values and slopes at both ends (`ArcPoints`) and
the derivative bounds ``Y_r``, ``A_r`` of its `ArcItems`, `lower_bound` returns a number that
the margin ``m = d - 1 - q sigma`` cannot go below anywhere in the interval, in stages of
increasing cost and tightness: Lipschitz in d; the cubic Hermite interpolant of ``F = d^2``
with its ``h^4 / 384`` error bound; the same for ``W = |v|^2`` (sigma); and the chord bound that
pairs d and sigma at common sub-grid points. Pure numpy, vectorised over intervals.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

N_ORDERS = 5        # derivative bounds of orders 0..4 (the Hermite error needs the 4th)
N_SUB = 32          # sub-grid of the chord bound for the chance margin (no basis evaluations)


@dataclass(frozen=True)
class ArcItems:
    """M (node, post-burn state[, covariance]) pairs whose drift arcs are examined together.

    Attributes:
        node: (M,) node index of each arc.
        coef: (M, 18, 3) ``G_k z`` [-]: ``y(tau) = b(tau) @ coef``.
        maps: (M, 18, 18) ``G_k`` flattened (3 x 6) [1/m], or None (deterministic).
        x_cov: (M, 6, 6) post-burn covariance [m^2], or None.
        q: confidence multiplier [-].
        y_sup: (M, 5) bounds on ``|y^(r)|`` over the arc, r = 0..4 [1/s^r].
        k_sup: (M, 5) bounds on ``||K^(r)||`` [1/s^r], or None.
    """

    node: np.ndarray
    coef: np.ndarray
    maps: np.ndarray | None
    x_cov: np.ndarray | None
    q: float
    y_sup: np.ndarray
    k_sup: np.ndarray | None


@dataclass(frozen=True)
class ArcPoints:
    """Margin and certificate quantities at points of the arcs, all (P,) or (M', K).

    tau [s], m = d - 1 - q sigma [-] and dm [1/s], f = d^2 and df, big_w = |v|^2 and dbig_w.
    """

    tau: np.ndarray
    m: np.ndarray
    dm: np.ndarray
    f: np.ndarray
    df: np.ndarray
    big_w: np.ndarray
    dbig_w: np.ndarray

    def take(self, idx: object) -> "ArcPoints":
        """Select / flatten (numpy indexing on every field)."""
        return ArcPoints(*(getattr(self, k)[idx] for k in self.__dataclass_fields__))

    @staticmethod
    def where(mask: np.ndarray, a: "ArcPoints", b: "ArcPoints") -> "ArcPoints":
        """Field-wise ``np.where(mask, a, b)``."""
        return ArcPoints(*(np.where(mask, getattr(a, k), getattr(b, k))
                           for k in a.__dataclass_fields__))


def lower_bound(it: ArcItems, item: np.ndarray, lo: ArcPoints, hi: ArcPoints,
                target: np.ndarray | None = None, sign_only: bool = False) -> np.ndarray:
    """Certified lower bounds (I,) of the margin on intervals [lo.tau, hi.tau] of arcs `item`.

    Staged (module docstring, step 2); each stage only runs where the bound so far is below
    `target` (None: all stages everywhere), so the result is the best bound computed:
    0. ``|d'| <= Y_1``: ``d >= (d_a + d_b - Y_1 h) / 2``, and ``sigma <= A_0``;
    1. d from the Hermite interpolant of F with its h^4 error bound, ``sigma <= A_0``;
    2. (chance) sigma from the interpolant of W = |v|^2 and the d bound of stage 1;
    3. (chance) the chord bound, pairing d and sigma at N_SUB + 1 sub-grid points.

    `sign_only` (the sign-only search, for which a bound matters only as below `target` or
    not, and as below zero or not): stage 1 first with ``sigma <= A_0``; stages 2 and 3 only
    where that is below max(target, 0). Where it is not, the smaller stage-1 bound is returned,
    which decides the same way.
    """
    target = np.full(item.size, np.inf) if target is None else target
    h = hi.tau - lo.tau
    k0 = 0.0 if it.k_sup is None else it.k_sup[item, 0]
    d_a, d_b = np.sqrt(lo.f), np.sqrt(hi.f)
    lb = np.maximum(0.5 * (d_a + d_b - it.y_sup[item, 1] * h), 0.0) - 1.0 - it.q * k0
    idx = np.flatnonzero(lb < target)
    if idx.size == 0:
        return lb
    if sign_only and it.k_sup is not None:
        first = _Bounds(it, item[idx], lo.take(idx), hi.take(idx), stage1_only=True)
        lb[idx] = np.maximum(lb[idx], first.lb)
        idx = idx[lb[idx] < np.maximum(target[idx], 0.0)]
        if idx.size == 0:
            return lb
    b = _Bounds(it, item[idx], lo.take(idx), hi.take(idx))
    lb[idx] = np.maximum(lb[idx], b.lb)
    if it.k_sup is not None:
        sel = np.flatnonzero(lb[idx] < target[idx])
        if sel.size:
            lb[idx[sel]] = np.maximum(lb[idx[sel]], b.chord(sel))
    return lb


class _Bounds:
    """Stages 1 and 2 of `lower_bound` on I intervals, and stage 3 on demand."""

    def __init__(self, it: ArcItems, item: np.ndarray, lo: ArcPoints, hi: ArcPoints,
                 stage1_only: bool = False) -> None:
        """`stage1_only`: the chance margin's bound from stage 1 and ``sigma <= A_0`` alone
        (no stage 2; `chord` is then not available)."""
        self.q, self.h = it.q, hi.tau - lo.tau
        h = self.h
        ys = it.y_sup[item]  # (I, 5)
        y0 = np.minimum(np.sqrt(np.maximum(lo.f, hi.f)) + 0.5 * h * ys[:, 1], ys[:, 0])
        self.ys = ys
        self.e_f = _hermite_error(y0, ys[:, 1], ys[:, 2], ys[:, 3], ys[:, 4], h)
        self.cub_f = _Cubic(lo.f, hi.f, lo.df, hi.df, h)
        self.d_lo = np.sqrt(np.clip(self.cub_f.minimum() - self.e_f, 0.0, None))
        if it.k_sup is None:
            self.lb = self.d_lo - 1.0
            return
        ks = self.ks = it.k_sup[item]
        if stage1_only:
            self.lb = self.d_lo - 1.0 - it.q * ks[:, 0]
            return
        yl = np.column_stack([y0, ys[:, 1:]])
        vs = np.stack([sum(comb(r, j) * ks[:, j] * yl[:, r - j] for j in range(r + 1))
                       for r in range(N_ORDERS)], axis=1)  # bounds on |v^(r)|, v = K y
        v0 = np.minimum(np.sqrt(np.maximum(lo.big_w, hi.big_w)) + 0.5 * h * vs[:, 1], vs[:, 0])
        self.e_w = _hermite_error(v0, vs[:, 1], vs[:, 2], vs[:, 3], vs[:, 4], h)
        self.cub_w = _Cubic(lo.big_w, hi.big_w, lo.dbig_w, hi.dbig_w, h)
        w_up = self.cub_w.maximum() + self.e_w
        self.lb = self.d_lo - 1.0 - it.q * _sigma_up(w_up, self.d_lo, ks[:, 0])

    def chord(self, sel: np.ndarray) -> np.ndarray:
        """Stage 3 on intervals `sel`: ``g = d - q sigma`` is above its chord through lower
        bounds at sub-grid points minus ``C dt^2 / 8``, ``C >= -g''`` (module docstring)."""
        h, ys, ks, d_lo = self.h[sel], self.ys[sel], self.ks[sel], self.d_lo[sel]
        e_f, e_w = self.e_f[sel, None], self.e_w[sel, None]
        cub_f, cub_w = self.cub_f.take(sel), self.cub_w.take(sel)
        s = h[:, None] * np.arange(N_SUB + 1) / N_SUB  # (I, J + 1)
        f_pts = np.clip(cub_f(s) - e_f, 0.0, None)
        g_pts = np.sqrt(f_pts) - self.q * _sigma_up(cub_w(s) + e_w, np.sqrt(f_pts), ks[:, :1])
        f_hi = cub_f.maximum() + e_f[:, 0]
        w_lo = np.clip(cub_w.minimum() - e_w[:, 0], 0.0, None)
        with np.errstate(divide="ignore", invalid="ignore"):
            sig_lo = np.sqrt(w_lo / f_hi)
            e1 = ys[:, 1] / d_lo  # |e'|, e = y / d
            e2 = 2.0 * ys[:, 2] / d_lo + 5.0 * e1 * e1
            u1 = ks[:, 1] + ks[:, 0] * e1  # |u'|, u = K e, sigma = |u|
            u2 = ks[:, 2] + 2.0 * ks[:, 1] * e1 + ks[:, 0] * e2
            curv = ys[:, 2] + self.q * (u2 + u1 * u1 / sig_lo)  # >= -g''
            lb = g_pts.min(axis=1) - 1.0 - curv * (h / N_SUB) ** 2 / 8.0
        ok = (d_lo > 0.0) & (sig_lo > 0.0) & np.isfinite(lb)
        return np.where(ok, lb, -np.inf)


def _hermite_error(a0: np.ndarray, a1: np.ndarray, a2: np.ndarray, a3: np.ndarray,
                   a4: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Error bound of the cubic Hermite interpolant of ``|a|^2`` on intervals of length h.

    With ``|a^(r)| <= a_r``, the 4th derivative of ``|a|^2`` is ``2 (a.a^(4) + 4 a'.a^(3) +
    3 a''.a'')`` and the interpolation error is at most ``h^4 / 384`` times its bound.
    """
    return 2.0 * (a0 * a4 + 4.0 * a1 * a3 + 3.0 * a2 * a2) * h**4 / 384.0


def _sigma_up(w_up: np.ndarray, d_lo: np.ndarray, k0: np.ndarray) -> np.ndarray:
    """Upper bound of sigma = |v| / d from |v|^2 <= w_up, d >= d_lo and sigma <= ||K|| <= k0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.sqrt(np.clip(w_up, 0.0, None)) / d_lo
    return np.where(d_lo > 0.0, np.minimum(sigma, k0), k0)


class _Cubic:
    """Cubic Hermite interpolant on [0, h] of (f0, g0) at 0 and (f1, g1) at h, (I,) each.

    ``H(s) = f0 + g0 s + c2 s^2 + c3 s^3``; its extrema on [0, h] are at the ends or at the
    real roots of H' inside (stable quadratic formula).
    """

    def __init__(self, f0: np.ndarray, f1: np.ndarray, g0: np.ndarray, g1: np.ndarray,
                 h: np.ndarray) -> None:
        hh = np.where(h > 0, h, 1.0)
        slope = (f1 - f0) / hh
        self.f0, self.f1, self.g0, self.h = f0, f1, g0, h
        self.c2 = (3.0 * slope - 2.0 * g0 - g1) / hh
        self.c3 = (g0 + g1 - 2.0 * slope) / (hh * hh)
        disc = np.clip(self.c2 * self.c2 - 3.0 * self.c3 * g0, 0.0, None)
        q = -(self.c2 + np.where(self.c2 >= 0, 1.0, -1.0) * np.sqrt(disc))
        with np.errstate(divide="ignore", invalid="ignore"):
            crit = np.stack([q / (3.0 * self.c3), g0 / q], axis=-1)
        # roots outside [0, h] (or spurious ones when disc < 0) are clipped to the ends, where
        # H is evaluated anyway; so the extrema below are exact
        self._crit = np.clip(np.where(np.isfinite(crit), crit, 0.0), 0.0, h[:, None])

    def take(self, sel: np.ndarray) -> "_Cubic":
        """The interpolants of intervals `sel`."""
        out = object.__new__(_Cubic)
        for k in ("f0", "f1", "g0", "h", "c2", "c3", "_crit"):
            setattr(out, k, getattr(self, k)[sel])
        return out

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """H at offsets s (I, J) [s]."""
        c = [a[:, None] for a in (self.f0, self.g0, self.c2, self.c3)]
        return c[0] + s * (c[1] + s * (c[2] + s * c[3]))

    def minimum(self) -> np.ndarray:
        """(I,) exact minimum of H on [0, h]."""
        return np.minimum(np.minimum(self.f0, self.f1), self(self._crit).min(axis=1))

    def maximum(self) -> np.ndarray:
        """(I,) exact maximum of H on [0, h]."""
        return np.maximum(np.maximum(self.f0, self.f1), self(self._crit).max(axis=1))
