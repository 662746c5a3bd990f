"""Free-drift arcs in closed form and the certified minimum of the passive-safety margin on them.

Closed form. After a contingency at node ``t_i`` the servicer drifts from its post-burn ROE
``z`` [m]; its ellipsoid-normalised RTN position at ``t_i + tau`` (first-order maps, mean J2
dynamics) is ``y(tau) = P^{1/2} D Psi(u(tau)) Phi(t_i + tau, t_i) z`` [-], with
``u(tau) = u_i + udot tau`` the chief's mean argument of latitude. The position rows of Psi are
``Psi_0 + cos u Psi_c + sin u Psi_s`` and the J2 STM is exactly ``sum_b s_b(tau) Phi_b`` with
``s = (1, tau, cos wdot tau, sin wdot tau, tau cos wdot tau, tau sin wdot tau)``
(`dynamics.stm_j2_terms`). Hence, with the 18 products ``b_k(tau) = {1, cos u, sin u} x s``,

    y(tau) = sum_k b_k(tau) G_k z,      G_k = P^{1/2} Psi_a Phi_b  (3, 6), precomputed per node,

exact at every tau (no interpolation between the drift samples), and so are its derivatives.
The margin is ``m(tau) = d - 1 - q sigma`` with ``d = |y|`` and, for the chance constraint,
``sigma = |v| / d``, ``v = X^{1/2} Mt^T y``, ``Mt(tau) = sum_k b_k G_k`` (the standard deviation
of the linearised distance with the post-burn covariance X propagated to tau; ``|v|^2 =
w^T X w``, ``w = Mt^T y``).

Why a fly-by between samples cannot hide. Samples alone see a dip only if it is wider than
their spacing: a 1.2 m/s pass at 200 m lasts ~170 s, the 20 samples are 290 s apart. A bound on
the number of extrema per interval does not help: a trig/secular drift can have a close pair of
critical points anywhere. Instead every interval of the arc ends up either split finely around
an evaluated minimum or carrying a *certified lower bound* of the margin over the whole interval,
built from the sampled values and slopes and bounds on higher derivatives that hold for every
trajectory. The reported margin is the smallest such bound (never above the true minimum) and
is within ``CERT_TOL + CERT_TOL_REL |m|`` of the smallest margin actually evaluated:

1. Derivative bounds. Every ``b_k`` and its derivatives up to order 4 are bounded on
   ``[0, T]`` by constants (``|cos|, |sin| <= 1``, ``|sin wdot tau| <= |wdot| T``,
   ``|tau| <= T``, one factor ``udot`` or ``wdot`` per derivative, Leibniz rule), so
   ``|y^(r)| <= Y_r = sum_k beta_k^(r) |G_k z|`` and, with ``K_k = X^{1/2} G_k^T`` (``v = K y``),
   ``||K^(r)|| <= A_r = sum_k beta_k^(r) ||K_k||_F``.
2. Interval bounds, in stages (each only where the previous one is not enough):
   0. ``|d'| <= Y_1`` gives ``d >= (d_a + d_b - Y_1 h) / 2``; ``sigma <= ||K|| <= A_0``.
   1. ``F = d^2`` lies within ``h^4/384 sup|F^(4)|`` of its cubic Hermite interpolant through
      the sampled ``F, F'`` (``|F^(4)| <= 2 (Y_0 Y_4 + 4 Y_1 Y_3 + 3 Y_2^2)``, ``Y_0`` local);
      the cubic's exact minimum gives ``d_lo``.
   2. (chance) the same interpolant bound on ``W = |v|^2`` from above gives ``sigma <=
      sqrt(W_up) / d_lo``, hence ``m >= d_lo - 1 - q sigma_up``.
   3. (chance) stage 2 bounds d and sigma at different instants, which loses O(h). The chord
      bound pairs them: ``g = d - q sigma`` is bounded below at N_SUB + 1 sub-grid points by
      the interpolant bounds at the *same* point, and ``g'' >= -C`` with ``-d'' <= |y''|`` and
      ``sigma'' <= |u''| + |u'|^2 / sigma_lo`` (``u = K y / |y|``) bounds it between them by
      the chord minus ``C dt^2 / 8``.
3. Search. The samples (values and exact slopes) are evaluated. Every interval whose bound is
   below the target (best margin found minus the tolerance) and whose slope changes sign from
   - to + (a local minimum of m, e.g. around every sampled local minimum; the arc ends are
   samples) is refined by safeguarded cubic-Hermite bracketing on the closed form; every
   interval still below target is split in SPLIT parts (new samples) and re-bounded, up to
   MAX_LEVELS times (MAX_OPEN intervals per arc and level: only degenerate arcs, e.g. through
   the target centre where sigma is 0/0, reach that cap; they keep a finite, lower bound).
   Converged plans need 1-3 levels, on the few intervals around each node's minimum.
   (`drift_bounds`: the bounds of step 2; `drift_search.IntervalSearch`: this search, which
   evaluates the arcs through `DriftArcs.points`.)

A fast fly-by between two coarse samples has a small d while both neighbouring samples are
far: its interval's bound is low, so it is split until the dip is sampled and refined. Only an
interval whose bound is provably above the target is left unexamined, so no trajectory can hide
a deeper point (tests: a constructed fly-by; dense 1 s evaluation of converged plans; the
bounds against dense minima on random intervals).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from math import comb

import numpy as np

from art_guidance import kernels
from art_guidance.safety.drift_bounds import N_ORDERS, ArcItems, ArcPoints, lower_bound
from art_guidance.safety.drift_search import (  # noqa: F401 (the search's constants, here too)
    CERT_TOL, CERT_TOL_REL, MAX_LEVELS, MAX_OPEN, REFINE_ITERS, SPLIT, IntervalSearch, intervals,
)
from art_guidance.dynamics import (
    j2_secular_rates, mean_arg_latitude, psi_from_latitude, stm_basis_orders, stm_j2_terms,
)

N_TERMS = 18        # 3 latitude functions x 6 STM time functions
_D_FLOOR = 1e-12    # ellipsoidal distances below this are treated as zero when dividing


def _psi_position_terms() -> np.ndarray:
    """(3, 3, 6): ``D Psi(u) = T[0] + cos u T[1] + sin u T[2]`` (position rows, any n)."""
    p0, p_half, p_pi = (psi_from_latitude(u, 1.0)[:3] for u in (0.0, 0.5 * np.pi, np.pi))
    const = 0.5 * (p0 + p_pi)
    return np.stack([const, 0.5 * (p0 - p_pi), p_half - const]).round(12)


@dataclass(frozen=True)
class ArcMinimum:
    """Certified minimum of the margin on every arc, and the points examined on the way.

    Attributes:
        margin: (M,) certified lower bound of the minimum margin over [0, T_safety] [-], at
            most CERT_TOL + CERT_TOL_REL |minimum| below it.
        tau_s: (M,) drift offset of the smallest margin evaluated, t* - t_i [s].
        margin_at_t_star: (M,) the margin at t* [-] (>= `margin`, within the tolerance).
        cand_item, cand_tau_s, cand_margin: (C,) the drift samples and refined local minima
            other than t* (the candidate linearisation instants; split points excluded: they
            crowd around t*): arc index, offset [s] and margin.
        levels: number of split levels that were needed (-1: not counted, the compiled
            search).
        top: (M, S) `top_k`'s offsets precomputed by the compiled search (the candidates are
            then not kept: empty), or None.
    """

    margin: np.ndarray
    tau_s: np.ndarray
    margin_at_t_star: np.ndarray
    cand_item: np.ndarray
    cand_tau_s: np.ndarray
    cand_margin: np.ndarray
    levels: int
    top: np.ndarray | None = None

    def top_k(self, k: int) -> np.ndarray:
        """(M, k) drift offsets [s]: t*, then the k - 1 smallest-margin candidates of the arc.

        Every arc has at least S - 1 candidates (its samples other than t*), k <= S.
        """
        if self.top is not None:
            return self.top[:, :k]
        order = np.lexsort((self.cand_margin, self.cand_item))
        item = self.cand_item[order]
        first = np.searchsorted(item, np.arange(self.margin.size))
        rest = self.cand_tau_s[order][first[:, None] + np.arange(k - 1)]
        return np.column_stack([self.tau_s, rest])


class DriftArcs:
    """Closed-form drift arcs from every node of a horizon (see the module docstring).

    Attributes:
        n_nodes: N; n_samples: S; t_safety_s: T [s]; tau_s: (S,) sample offsets [s].
        maps: (N, 18, 18) ``G_k = P^{1/2} Psi_a Phi_b`` per node [1/m], (3 x 6) flattened.
    """

    def __init__(self, chief_oe: np.ndarray, semi_axes_m: np.ndarray, t_safety_s: float,
                 n_samples: int) -> None:
        """Precompute G_k per node, the sample basis and the derivative bounds.

        Args:
            chief_oe: (N, 6) mean chief elements at the nodes.
            semi_axes_m: (N, 3) active ellipsoid semi-axes [m].
            t_safety_s: drift duration T [s] (0: only the node itself).
            n_samples: number of samples S (1 when T = 0).
        """
        n = chief_oe.shape[0]
        terms = np.empty((n, 6, 6, 6))
        self._wdot, self._udot = np.empty(n), np.empty(n)
        for k, oe in enumerate(chief_oe):
            terms[k], self._wdot[k] = stm_j2_terms(oe)
            _, argp_dot, m_dot = j2_secular_rates(oe)
            self._udot[k] = argp_dot + m_dot
        self._u0 = mean_arg_latitude(chief_oe)
        g = np.einsum("ni,aij,nbjk->nabik", 1.0 / semi_axes_m, _psi_position_terms(), terms)
        self.maps = g.reshape(n, N_TERMS, 18)
        self.n_nodes, self.n_samples, self.t_safety_s = n, int(n_samples), float(t_safety_s)
        self.tau_s = np.linspace(0.0, self.t_safety_s, self.n_samples)
        nodes = np.arange(n)
        b0, b1 = self.basis(nodes, np.broadcast_to(self.tau_s, (n, self.n_samples)))
        self._grid = (b0, b1, b0 @ self.maps, b1 @ self.maps)  # bases, M~ and M~' at samples
        self._sup = self._sup_bounds()

    # ------------------------------------------------------------------ basis
    def basis(self, node: np.ndarray, tau_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """b(tau) and b'(tau), each (M, K, 18), for arcs `node` (M,) at offsets (M, K) [s].

        ``b = {1, cos u, sin u} x s`` with s the STM time functions (`dynamics.stm_basis`) and
        ``b' = {0, -udot sin u, udot cos u} x s + {1, cos u, sin u} x s'``, written into the
        output without intermediate stacks (this runs a few times per arc minimum).
        """
        udot = self._udot[node][:, None]
        u = self._u0[node][:, None] + udot * tau_s
        cu, su = np.cos(u), np.sin(u)
        wdot = self._wdot[node][:, None]
        s0, s1 = stm_basis_orders(wdot, tau_s, (0, 1))  # (M, K, 6)
        shape = u.shape
        b0 = np.empty(shape + (3, 6))
        b0[..., 0, :] = s0
        np.multiply(cu[..., None], s0, out=b0[..., 1, :])
        np.multiply(su[..., None], s0, out=b0[..., 2, :])
        b1 = np.empty(shape + (3, 6))
        b1[..., 0, :] = s1
        np.multiply((-udot * su)[..., None], s0, out=b1[..., 1, :])
        b1[..., 1, :] += cu[..., None] * s1
        np.multiply((udot * cu)[..., None], s0, out=b1[..., 2, :])
        b1[..., 2, :] += su[..., None] * s1
        return b0.reshape(shape + (N_TERMS,)), b1.reshape(shape + (N_TERMS,))

    def _sup_bounds(self) -> np.ndarray:
        """(N, 5, 18): sup over [0, T] of |b_k^(r)|, r = 0..4 (module docstring, step 1).

        Per factor: ``|d^r cos u| <= udot^r``; with ``wt = min(|wdot| T, 1) >= |sin wdot tau|``,
        ``|c^(r)| <= w^r`` (times wt for odd r), ``|s^(r)| <= w^r`` (times wt for even r),
        ``|(tau f)^(r)| <= T |f^(r)| + r |f^(r-1)|``; products by the Leibniz rule.
        """
        t, orders = self.t_safety_s, N_ORDERS
        w, v = np.abs(self._wdot)[:, None], np.abs(self._udot)[:, None]
        wt = np.minimum(w * t, 1.0)
        r = np.arange(orders)[None, :]
        lat = np.stack([(r == 0) * np.ones_like(v), v**r, v**r], axis=-1)  # (N, R, 3)
        c = np.where(r % 2 == 1, w**r * wt, w**r)
        sn = np.where(r % 2 == 0, w**r * wt, w**r)
        prev = np.concatenate([np.zeros_like(w), c[:, :-1]], axis=1)
        prev_s = np.concatenate([np.zeros_like(w), sn[:, :-1]], axis=1)
        one = (r == 0) * np.ones_like(w)
        lin = np.where(r == 0, t, np.where(r == 1, 1.0, 0.0)) * np.ones_like(w)
        stm = np.stack([one, lin, c, sn, t * c + r * prev, t * sn + r * prev_s], axis=-1)
        out = np.zeros((w.size, orders, 3, 6))
        for order in range(orders):
            for k in range(order + 1):
                out[:, order] += comb(order, k) * lat[:, k, :, None] * stm[:, order - k, None, :]
        return out.reshape(w.size, orders, N_TERMS)

    # ------------------------------------------------------------------ items and points
    def items(self, node: np.ndarray, z_m: np.ndarray, x_cov: np.ndarray | None,
              q: float) -> ArcItems:
        """Arcs of post-burn states `z_m` (M, 6) [m] from nodes `node` (M,), covariance or None."""
        m = node.size
        maps = _take(self.maps, node)  # (M, 18, 18)
        g = maps.reshape(m, N_TERMS, 3, 6)
        coef = g @ z_m[:, None, :, None]  # (M, 18, 3, 1)
        coef = coef[..., 0]
        sup = _take(self._sup, node)  # (M, 5, 18)
        y_sup = np.einsum("mrk,mk->mr", sup, np.linalg.norm(coef, axis=-1))
        if x_cov is None:
            return ArcItems(node, coef, None, None, 0.0, y_sup, None)
        gx = (g.reshape(m, 3 * N_TERMS, 6) @ x_cov).reshape(m, N_TERMS, 3, 6)
        k_norm = np.sqrt(np.clip(np.einsum("mkci,mkci->mk", gx, g), 0.0, None))
        k_sup = np.einsum("mrk,mk->mr", sup, k_norm)
        return ArcItems(node, coef, maps, x_cov, float(q), y_sup, k_sup)

    def points(self, it: ArcItems, sel: np.ndarray, tau_s: np.ndarray,
               grid: bool = False) -> ArcPoints:
        """Margins and slopes of arcs `sel` (M',) at offsets `tau_s` (M', K) [s] (`grid`: the
        drift samples, whose bases and maps are precomputed)."""
        if grid:
            node = _take(it.node, sel)
            b0, b1, mt, dmt = (_take(g, node) for g in self._grid)
        else:
            b0, b1 = self.basis(it.node[sel], tau_s)
            mt = dmt = None
        coef = _take(it.coef, sel)
        y, dy = b0 @ coef, b1 @ coef  # (M', K, 3)
        f = np.einsum("mkc,mkc->mk", y, y)
        df = 2.0 * np.einsum("mkc,mkc->mk", y, dy)
        d = np.maximum(np.sqrt(f), _D_FLOOR)
        dd = 0.5 * df / d
        if it.maps is None:
            zero = np.zeros_like(f)
            return ArcPoints(tau_s, np.sqrt(f) - 1.0, dd, f, df, zero, zero)
        w, dw = self._w(it, sel, b0, b1, y, dy, mt, dmt)
        xw = w @ _take(it.x_cov, sel)  # (M', K, 6)
        big_w = np.clip(np.einsum("mki,mki->mk", xw, w), 0.0, None)
        dbig_w = 2.0 * np.einsum("mki,mki->mk", xw, dw)
        v = np.sqrt(big_w)
        dv = np.divide(0.5 * dbig_w, v, out=np.zeros_like(v), where=v > 0)
        sigma, dsigma = v / d, dv / d - v * dd / (d * d)
        return ArcPoints(tau_s, np.sqrt(f) - 1.0 - it.q * sigma, dd - it.q * dsigma, f, df,
                         big_w, dbig_w)

    @staticmethod
    def _w(it: ArcItems, sel: np.ndarray, b0: np.ndarray, b1: np.ndarray, y: np.ndarray,
           dy: np.ndarray, mt: np.ndarray | None = None, dmt: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
        """``w = Mt^T y`` (M', K, 6) and its derivative (`mt`, `dmt`: precomputed maps)."""
        if mt is None:
            maps = _take(it.maps, sel)
            mt, dmt = b0 @ maps, b1 @ maps
        mt = mt.reshape(b0.shape[:2] + (3, 6))
        dmt = dmt.reshape(b0.shape[:2] + (3, 6))
        w = np.einsum("mkci,mkc->mki", mt, y)
        dw = np.einsum("mkci,mkc->mki", dmt, y)
        dw += np.einsum("mkci,mkc->mki", mt, dy)
        return w, dw

    def gradient(self, it: ArcItems, tau_s: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At offsets (M, k) [s]: distance d (M, k), gradient ``g = Mt^T y / d`` (M, k, 6)
        [1/m] of d with respect to z, and ``sigma = sqrt(g^T X g)`` (M, k) [-]."""
        sel = np.arange(it.node.size)
        b0, b1 = self.basis(it.node, tau_s)
        y = b0 @ it.coef
        d = np.sqrt(np.einsum("mkc,mkc->mk", y, y))
        maps = _take(self.maps, it.node)
        mt = (b0 @ maps).reshape(b0.shape[:2] + (3, 6))
        g = np.einsum("mkci,mkc->mki", mt, y) / np.maximum(d, _D_FLOOR)[..., None]
        if it.x_cov is None:
            return d, g, np.zeros_like(d)
        var = np.einsum("mki,mki->mk", g @ it.x_cov[sel], g)
        return d, g, np.sqrt(np.clip(var, 0.0, None))

    # ------------------------------------------------------------------ certified minimum
    def minimum(self, it: ArcItems, sign_only: bool = False) -> ArcMinimum:
        """Certified minimum of the margin on every arc of `it` (module docstring, step 3).

        `sign_only`: decide only whether each minimum is below zero (the violation indicator),
        which needs far fewer evaluations near the ellipsoid: an arc stops at its first
        evaluated point with a negative margin, and an interval is closed once its bound is
        >= 0. The returned margins then carry only their sign (the same as the full search's,
        except for minima within the certification tolerance of zero); t* and the candidates
        are those of the shortened search.
        """
        if kernels.compiled():
            return self._minimum_compiled(it, sign_only)
        m_items = it.node.size
        sel = np.arange(m_items)
        grid = self.points(it, sel, np.broadcast_to(self.tau_s, (m_items, self.n_samples)),
                           grid=True)
        search = IntervalSearch(self.points, it, grid.m.min(axis=1), sign_only)
        if self.n_samples > 1:
            search.run(np.repeat(sel, self.n_samples - 1), *intervals(grid))
        cands = [(np.repeat(sel, self.n_samples), grid.tau.ravel(), grid.m.ravel(),
                  np.ones(grid.m.size, bool)), *search.candidates]
        c_item, c_tau, c_m, c_row = (np.concatenate(c) for c in zip(*cands))
        order = np.lexsort((c_m, c_item))
        first = order[np.searchsorted(c_item[order], sel)]
        row = c_row & (c_tau != c_tau[first][c_item])  # row candidates other than t*
        return ArcMinimum(search.margin, c_tau[first], c_m[first], c_item[row], c_tau[row],
                          c_m[row], search.levels)

    def violated(self, it: ArcItems) -> np.ndarray:
        """(M,) bool: whether the minimum margin of each arc is below zero.

        The same decision as ``minimum(it, sign_only=True).margin < 0`` (its oracle, tested):
        the arcs a drift sample already shows inside are decided by the samples, the search
        runs over the others' intervals only, and neither t* nor the candidates are kept (the
        rollout's C update needs the sign alone, at every step).
        """
        m_items = it.node.size
        grid = self.points(it, np.arange(m_items),
                           np.broadcast_to(self.tau_s, (m_items, self.n_samples)), grid=True)
        best = grid.m.min(axis=1)
        undecided = np.flatnonzero(best >= 0.0)
        if self.n_samples == 1 or undecided.size == 0:
            return best < 0.0
        search = IntervalSearch(self.points, it, best, sign_only=True)
        search.run(np.repeat(undecided, self.n_samples - 1), *intervals(grid.take(undecided)))
        return search.margin < 0.0

    def violated_at(self, node: np.ndarray, z_m: np.ndarray, x_cov: np.ndarray | None,
                    q: float) -> np.ndarray:
        """(M,) bool: `violated` of the arcs of post-burn states `z_m` (M, 6) [m] from nodes
        `node` (M,), with covariances `x_cov` (M, 6, 6) [m^2] or None: one compiled call
        (`kernels.drift.violated`) where the compiled numerics are in use, else the numpy
        oracle `violated(items(...))`."""
        if not kernels.compiled():
            return self.violated(self.items(node, z_m, x_cov, q))
        from art_guidance.kernels import drift as kernel

        chance = x_cov is not None
        cov = np.ascontiguousarray(x_cov) if chance else np.zeros((node.size, 6, 6))
        return kernel.violated(np.ascontiguousarray(node, dtype=np.int64),
                               np.ascontiguousarray(z_m, dtype=float), cov, float(q), chance,
                               self.maps, self._sup, self._u0, self._udot, self._wdot,
                               self.tau_s, *self._grid_c)

    def _minimum_compiled(self, it: ArcItems, sign_only: bool) -> ArcMinimum:
        """`minimum` by the compiled kernel (`kernels.drift.minimum`, arc by arc)."""
        from art_guidance.kernels import drift as kernel

        m, chance = it.node.size, it.maps is not None
        c = np.ascontiguousarray
        margin, t_star, m_star, top = kernel.minimum(
            c(it.node, dtype=np.int64), c(it.coef), c(it.x_cov) if chance else
            np.zeros((m, 6, 6)), float(it.q), chance, c(it.y_sup),
            c(it.k_sup) if chance else np.zeros((m, 5)), bool(sign_only), self.maps, self._u0,
            self._udot, self._wdot, self.tau_s, *self._grid_c)
        empty = np.empty(0)
        return ArcMinimum(margin, t_star, m_star, empty.astype(int), empty, empty, -1, top)

    @functools.cached_property
    def _grid_c(self) -> tuple[np.ndarray, ...]:
        """`_grid` as C-contiguous (N, S, 18) arrays (the compiled kernel's input)."""
        n, s = self.n_nodes, self.n_samples
        return tuple(np.ascontiguousarray(g.reshape(n, s, N_TERMS)) for g in self._grid)

    lower_bound = staticmethod(lower_bound)


def _take(arr: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``arr[idx]``, without the copy when idx is 0 .. len(arr) - 1 (every node, in order)."""
    n = arr.shape[0]
    if n > 32 and idx.size == n and idx[0] == 0 and idx[-1] == n - 1 \
            and np.all(np.diff(idx) == 1):
        return arr  # below 33 rows the copy costs less than the check
    return arr[idx]
