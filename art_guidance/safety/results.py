"""What `passive.PassiveSafety` returns: the nonlinear evaluation of a trajectory and the
linearisation of its chance constraint for SCVx*."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SafetyLinearization:
    """Linearised passive-safety (chance) constraint ``a[i] @ z_i >= rhs[i]`` at every node.

    Attributes:
        a: (N, 6) normalised gradient [1/m] with respect to the post-burn ROE z_i [m].
        rhs: (N,) right-hand side ``1 + beta`` [-].
        beta: (N,) normalised q-sigma margin ``q sigma_i(tau*)`` [-] (0 when deterministic).
        t_star_s: (N,) drift offset tau* = t* - t_i of the continuous minimum [s].
        dist: (N,) ellipsoidal distance of the reference at t* [-].
    """

    a: np.ndarray
    rhs: np.ndarray
    beta: np.ndarray
    t_star_s: np.ndarray
    dist: np.ndarray


@dataclass(frozen=True)
class SafetyEvaluation:
    """Nonlinear passive-safety check of a trajectory.

    Attributes:
        margin: (N,) normalised margin ``min_tau (d - 1 - q sigma)`` over the continuous drift
            arc [-] (certified to `drift.CERT_TOL`); >= 0 is safe.
        margin_m: (N,) the same times the smallest semi-axis of the active ellipsoid [m].
        violation: (N,) int 0/1, the paper's binary constraint-violation metric (1 = violated,
            i.e. margin < 0).
        constraint_to_go: (N,) int, C(t_i) = sum_{j >= i} violation_j.
        t_star_s: (N,) drift offset tau* of the smallest margin [s].
    """

    margin: np.ndarray
    margin_m: np.ndarray
    violation: np.ndarray
    constraint_to_go: np.ndarray
    t_star_s: np.ndarray
