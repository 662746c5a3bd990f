"""Thruster faults in the closed loop and the truth check of the free drift that follows.

Faults (`Fault`), applied by `sim.closed_loop.ClosedLoop` at the K-th burn opportunity of the
flown trajectory (node K = the K-th plan node the simulator reaches, counting from 0; zero-size
burns count):

* ``loss``: no burn from node K on, K included. The run stops at t_K and the deputy drifts.
  The design covers K >= 1 (control lost *after* a burn); K = 0 is the initial state, which no
  plan has made safe.
* ``missed``: burn K is not executed; control resumes at the next node, where the guidance sees
  the navigated state and replans when it deviates from the plan (its replan policy).

The check (`free_drift_check`) is independent of the planner's linear drift model: from a truth
state (both spacecraft inertial) the two-body + J2 truth (`simulator`'s DOP853 integrator, dense
output) drifts for `duration_s`, sampled every <= DRIFT_STEP_S, and the signed Euclidean
distance to the ellipsoid in force (`ellipsoid_distance_m`: metres outside, negative inside) is
minimised over the samples and then refined to REFINE_TOL_S on the dense interpolant around
every local minimum that could be the lowest. An *entry* is any distance below zero.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import orbital_period_s
from art_guidance.errors import InputError
from art_guidance.sim.truth import integrate_truth, rtn_from_eci_batch

FAULT_KINDS = ("loss", "missed")
ZONES = ("approach_ellipsoid", "keep_out_zone")
DRIFT_STEP_S = 5.0         # largest sample spacing of the drift check [s]
REFINE_TOL_S = 1e-3        # time tolerance of the refined minimum [s]
REFINE_SLACK_M = 25.0      # refine every local minimum within this of the sampled one [m]
BISECTIONS = 80            # bisection steps of the ellipsoid projection (2^-80 of the bracket)


@dataclass(frozen=True)
class Fault:
    """A thruster fault injected at the `node`-th burn opportunity of a run.

    Attributes:
        kind: "loss" or "missed" (module docstring).
        node: K, >= 0.
    """

    kind: str
    node: int

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise InputError("fault", f"must be one of {FAULT_KINDS}", self.kind)
        if isinstance(self.node, bool) or int(self.node) != self.node or self.node < 0:
            raise InputError("fault_node", "must be an integer >= 0", self.node)

    @staticmethod
    def parse(kind: str, node: int) -> "Fault | None":
        """The fault of the run parameters `fault` ("" or "none" = no fault) and `fault_node`.

        Raises:
            InputError: on an unknown kind or a negative node.
        """
        if kind in ("", "none"):
            return None
        return Fault(str(kind), int(node))


@dataclass(frozen=True)
class DriftCheck:
    """The truth free drift from one state and its closest approach to the ellipsoid in force.

    Attributes:
        t0_s: sim time the drift starts [s].
        zone: "approach_ellipsoid" or "keep_out_zone".
        semi_axes_m: (3,) the ellipsoid's RTN semi-axes [m].
        min_margin_m: smallest signed distance to the ellipsoid [m] (negative inside).
        t_closest_s: sim time of that minimum [s].
        closest_rtn_m: (3,) RTN position at that minimum [m].
        entered: True when the drift enters the ellipsoid.
        t_s: (S,) sample times [s] (sim time).
        rtn: (S, 6) truth RTN states along the drift [m, m/s].
    """

    t0_s: float
    zone: str
    semi_axes_m: np.ndarray
    min_margin_m: float
    t_closest_s: float
    closest_rtn_m: np.ndarray
    entered: bool
    t_s: np.ndarray
    rtn: np.ndarray

    def to_json(self) -> dict:
        """The summary fields (no arrays but the closest position)."""
        return {"zone": self.zone, "t0_s": self.t0_s, "min_margin_m": self.min_margin_m,
                "t_closest_s": self.t_closest_s, "entered": self.entered,
                "closest_rtn_m": self.closest_rtn_m.tolist()}


def zone_semi_axes_m(scenario: ScenarioConfig, zone: str) -> np.ndarray:
    """(3,) RTN semi-axes [m] of "approach_ellipsoid" or "keep_out_zone"."""
    if zone not in ZONES:
        raise InputError("zone", f"must be one of {ZONES}", zone)
    axes = scenario.ae_semi_axes_m if zone == ZONES[0] else scenario.koz_semi_axes_m
    return np.asarray(axes, dtype=float)


def ellipsoid_distance_m(pos_m: object, semi_axes_m: object) -> np.ndarray:
    """Signed Euclidean distance [m] of RTN positions to an axis-aligned ellipsoid at the origin.

    Positive outside, negative inside (minus the distance to the surface), 0 on it. The closest
    surface point is ``q_i = a_i^2 p_i / (a_i^2 + lam)`` with ``lam`` the root of
    ``sum (a_i p_i / (a_i^2 + lam))^2 = 1`` in ``(-min a^2, inf)`` (monotone there; found by
    bisection). Inside, where that root does not exist (the point lies on the plane of the
    smallest axis), the distance along the smallest axis is used, an upper bound of the depth.

    Args:
        pos_m: (..., 3) positions [m].
        semi_axes_m: (3,) semi-axes [m], > 0.

    Returns:
        (...,) signed distances [m].
    """
    p = np.asarray(pos_m, dtype=float)
    a = as_finite_array("semi_axes_m", semi_axes_m, (3,))
    if np.any(a <= 0):
        raise InputError("semi_axes_m", "must be > 0", a)
    flat = p.reshape(-1, 3)
    d_ell = np.sqrt(np.sum((flat / a) ** 2, axis=1))
    if np.ptp(a) == 0.0:  # a sphere
        return (np.linalg.norm(flat, axis=1) - a[0]).reshape(p.shape[:-1])
    a2 = a * a
    lo = np.full(flat.shape[0], -a2.min())
    hi = np.maximum(np.linalg.norm(flat, axis=1) * a.max(), 1e-9)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        f = np.sum(_ratio(a * flat, a2 + mid[:, None]) ** 2, axis=1) - 1.0
        inside = f > 0  # root lies above mid
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    lam = 0.5 * (lo + hi)
    q = _ratio(a2 * flat, a2 + lam[:, None])
    dist = np.linalg.norm(flat - q, axis=1)
    degenerate = (d_ell < 1.0) & (lam <= -a2.min() * (1 - 1e-9))
    k = int(np.argmin(a))
    depth = np.where(degenerate, a[k] - np.abs(flat[:, k]), dist)
    return np.where(d_ell >= 1.0, dist, -depth).reshape(p.shape[:-1])


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den, 0 where num is 0 (a zero coordinate at the bracket's end)."""
    return np.divide(num, den, out=np.zeros_like(num), where=num != 0.0)


def free_drift_check(chief_eci: object, deputy_eci: object, t0_s: float, duration_s: float,
                     scenario: ScenarioConfig, zone: str,
                     step_s: float = DRIFT_STEP_S) -> DriftCheck:
    """Drift both spacecraft freely in truth and find the closest approach to the ellipsoid.

    Args:
        chief_eci, deputy_eci: (6,) inertial states [m, m/s] at the start of the drift.
        t0_s: sim time of that start [s] (only labels the result).
        duration_s: drift duration [s], > 0 (the scenario's T_safety: one orbit).
        scenario: the ellipsoids' semi-axes.
        zone: the ellipsoid in force ("approach_ellipsoid" or "keep_out_zone").
        step_s: largest sample spacing [s], > 0.

    Returns:
        The `DriftCheck`.

    Raises:
        InputError: on non-finite states, a non-positive duration or step, an unknown zone.
    """
    c = as_finite_array("chief_eci", chief_eci, (6,))
    d = as_finite_array("deputy_eci", deputy_eci, (6,))
    for name, value in (("duration_s", duration_s), ("step_s", step_s)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(name, "must be finite and > 0 [s]", value)
    axes = zone_semi_axes_m(scenario, zone)
    sol = integrate_truth(np.concatenate([c, d]), float(duration_s), dense=True)
    tau = np.linspace(0.0, float(duration_s), int(np.ceil(duration_s / step_s)) + 1)

    def rtn_at(times: np.ndarray) -> np.ndarray:
        y = sol.sol(np.atleast_1d(times))  # (12, S)
        return rtn_from_eci_batch(y[:6].T, y[6:].T)

    rtn = rtn_at(tau)
    margin = ellipsoid_distance_m(rtn[:, :3], axes)
    best_tau, best = float(tau[np.argmin(margin)]), float(margin.min())
    interior = np.flatnonzero((margin[1:-1] <= margin[:-2]) & (margin[1:-1] <= margin[2:])) + 1
    for j in interior[margin[interior] <= best + REFINE_SLACK_M]:
        res = minimize_scalar(
            lambda s: float(ellipsoid_distance_m(rtn_at(s)[0, :3], axes)),
            bounds=(tau[j - 1], tau[j + 1]), method="bounded",
            options={"xatol": REFINE_TOL_S})
        if res.fun < best:
            best_tau, best = float(res.x), float(res.fun)
    closest = rtn_at(best_tau)[0, :3]
    return DriftCheck(float(t0_s), zone, axes, best, float(t0_s) + best_tau, closest, best < 0.0,
                      float(t0_s) + tau, rtn)


def safety_duration_s(scenario: ScenarioConfig, chief_a_m: float) -> float:
    """T_safety [s]: `t_safety_orbits` periods of a chief of semi-major axis `chief_a_m`."""
    return float(scenario.t_safety_orbits * orbital_period_s(float(chief_a_m)))
