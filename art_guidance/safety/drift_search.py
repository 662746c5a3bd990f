"""The certified search of `drift.DriftArcs` (step 3 of that module's docstring): the
refinement of bracketed minima and the splitting of uncertified intervals, over every interval
of every arc of a batch at once (`DriftArcs.minimum` and `DriftArcs.violated` run it).

`IntervalSearch` holds a search's own state (the smallest margin evaluated per arc, the bounds
of the intervals it closed, the points it evaluated); it evaluates the arcs through the
function it is given (`DriftArcs.points`), so this module does not import `drift`.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from art_guidance.safety.drift_bounds import ArcItems, ArcPoints, lower_bound

CERT_TOL = 1e-4     # certified accuracy of the arc minimum [-] (0.1 m on the AE, 2 cm on the KOZ)
CERT_TOL_REL = 1e-3  # ... plus this fraction of |minimum| (no cm accuracy 300 m off the KOZ)
SPLIT = 4           # an uncertified interval is split into this many parts per level
MAX_LEVELS = 8      # at most this many splits (h / 4^8: < 0.01 s for the paper's drift)
MAX_OPEN = 32       # at most this many intervals per arc are split per level (lowest bounds)
REFINE_ITERS = 4    # safeguarded cubic-Hermite steps per bracketed local minimum

# margins and slopes of arcs `item` (I,) of the items at offsets (I, K) [s] (`DriftArcs.points`)
Points = Callable[[ArcItems, np.ndarray, np.ndarray], ArcPoints]


class IntervalSearch:
    """The certified search over the sample intervals of one batch of arcs.

    Built on the arcs' point evaluator (`DriftArcs.points`), the arcs (`ArcItems`, M of them)
    and the smallest margin sampled on each; `run` refines brackets and splits uncertified
    intervals until all are certified, updating this search's own state:

    Attributes:
        best: (M,) the smallest margin evaluated on each arc [-] (the samples', then the
            search's points).
        floor: (M,) the smallest lower bound of the intervals closed [-] (>= best - tolerance
            once certified).
        candidates: the points the search evaluated, in order: one (arc index, offset [s],
            margin, row) tuple of arrays per batch, row False for split points.
        levels: the split levels the run needed (0 before a run).
        sign_only: decide only the sign of every minimum (`drift.DriftArcs.minimum`).
    """

    def __init__(self, points: Points, it: ArcItems, best: np.ndarray,
                 sign_only: bool = False) -> None:
        self._points = points
        self._it = it
        self.sign_only = sign_only
        self.best = np.array(best, dtype=float)
        self.floor = self.best.copy()
        self.candidates: list[tuple[np.ndarray, ...]] = []
        self.levels = 0

    @property
    def margin(self) -> np.ndarray:
        """(M,) the certified lower bound of every arc's minimum margin [-]."""
        return np.minimum(self.floor, self.best)

    def run(self, item: np.ndarray, lo: ArcPoints, hi: ArcPoints) -> IntervalSearch:
        """Refine brackets and split the uncertified intervals [lo, hi] of arcs `item` (I,)
        until all are certified (or MAX_LEVELS splits); returns this search."""
        it, best, floor = self._it, self.best, self.floor
        target = _sign_target if self.sign_only else _target
        refined = np.zeros(item.size, bool)
        for level in range(MAX_LEVELS + 1):
            lb = lower_bound(it, item, lo, hi, target(best)[item], self.sign_only)
            open_ = lb < target(best)[item]
            bracket = open_ & (lo.dm < 0.0) & (hi.dm > 0.0) & ~refined
            if bracket.any():  # a local minimum of m that may matter: refine it
                idx = np.flatnonzero(bracket)
                r_item, r_tau, r_m = refine(self._points, it, item[idx], lo.take(idx),
                                            hi.take(idx))
                self.candidates.append((r_item, r_tau, r_m, np.ones(r_m.size, bool)))
                np.minimum.at(best, r_item, r_m)
                refined = refined | bracket
                open_ = lb < target(best)[item]  # bounds stay valid; the target went down
            if not open_.any() or level == MAX_LEVELS:
                np.minimum.at(floor, item, lb)
                self.levels = level
                return self
            idx = np.flatnonzero(open_)
            if idx.size > MAX_OPEN * best.size:  # degenerate arcs (e.g. through the centre)
                idx = np.sort(idx[np.argpartition(lb[idx], MAX_OPEN * best.size)[
                    :MAX_OPEN * best.size]])
            closed = np.ones(item.size, bool)
            closed[idx] = False
            np.minimum.at(floor, item[closed], lb[closed])
            item, lo, hi, refined = item[idx], lo.take(idx), hi.take(idx), refined[idx]
            frac = np.arange(1, SPLIT) / SPLIT
            taus = lo.tau[:, None] + (hi.tau - lo.tau)[:, None] * frac  # (I, SPLIT-1)
            mid = self._points(it, item, taus)
            self.candidates.append((np.repeat(item, SPLIT - 1), mid.tau.ravel(), mid.m.ravel(),
                                    np.zeros(mid.m.size, bool)))
            np.minimum.at(best, np.repeat(item, SPLIT - 1), mid.m.ravel())
            ends = ArcPoints(*(np.concatenate([getattr(lo, k)[:, None], getattr(mid, k),
                                               getattr(hi, k)[:, None]], axis=1)
                               for k in _FIELDS))  # (I, SPLIT + 1)
            lo, hi = intervals(ends)
            item, refined = np.repeat(item, SPLIT), np.repeat(refined, SPLIT)
        return self  # pragma: no cover - the loop returns at MAX_LEVELS


def refine(points: Points, it: ArcItems, item: np.ndarray, lo: ArcPoints, hi: ArcPoints
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Safeguarded cubic-Hermite bracketing of m' = 0 on brackets with m'(lo) < 0 < m'(hi)
    of arcs `item` of `it`, evaluated by `points` (`DriftArcs.points`).

    Each step evaluates the minimiser of the Hermite cubic through both ends (bisection
    after a step that kept 95 % of the bracket), then keeps the half where m' changes sign.

    Returns the arc index, offset [s] and margin of the best point of every bracket.
    """
    best_tau = np.where(lo.m <= hi.m, lo.tau, hi.tau)
    best_m = np.minimum(lo.m, hi.m)
    bisect = np.zeros(item.size, bool)
    for _ in range(REFINE_ITERS):
        width = hi.tau - lo.tau
        slope = (hi.m - lo.m) / np.where(width > 0, width, 1.0)
        d1 = lo.dm + hi.dm - 3.0 * slope
        d2 = np.sqrt(np.clip(d1 * d1 - lo.dm * hi.dm, 0.0, None))
        den = hi.dm - lo.dm + 2.0 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            t = hi.tau - width * (hi.dm + d2 - d1) / den
        mid = 0.5 * (lo.tau + hi.tau)
        t = np.where(np.isfinite(t) & ~bisect, t, mid)
        t = np.clip(t, lo.tau + 0.05 * width, hi.tau - 0.05 * width)
        p = points(it, item, t[:, None]).take((slice(None), 0))
        better = p.m < best_m
        best_tau, best_m = np.where(better, p.tau, best_tau), np.minimum(best_m, p.m)
        left = p.dm < 0.0
        lo, hi = ArcPoints.where(left, p, lo), ArcPoints.where(left, hi, p)
        bisect = (hi.tau - lo.tau) > 0.95 * width  # slow one-sided progress: bisect next
    return item, best_tau, best_m


def _target(best: np.ndarray) -> np.ndarray:
    """Certification target: ``best - CERT_TOL - CERT_TOL_REL |best|``."""
    return best - CERT_TOL - CERT_TOL_REL * np.abs(best)


def _sign_target(best: np.ndarray) -> np.ndarray:
    """Target of the sign-only search: 0 (capped `_target`) until an evaluated margin is
    negative, then -inf (the arc is decided: violated)."""
    return np.where(best < 0.0, -np.inf, np.minimum(_target(best), 0.0))


_FIELDS = tuple(ArcPoints.__dataclass_fields__)


def intervals(pts: ArcPoints) -> tuple[ArcPoints, ArcPoints]:
    """Flattened (left, right) end points of consecutive points along axis 1 of (I, K) data."""
    left = pts.take((slice(None), slice(0, -1)))
    right = pts.take((slice(None), slice(1, None)))
    flat = [ArcPoints(*(getattr(p, k).reshape(-1) for k in _FIELDS)) for p in (left, right)]
    return flat[0], flat[1]
