"""A plan and a navigation fix as geometry in the chief's RTN frame (no ROS).

The numbers behind the node's visualisation topics (`ros/visualization.py`) and the bag
rendering. Frame `chief_rtn` (FRAME_RTN): origin at the chief, x = R (radial, away from the
Earth), y = T (along-track), z = N (orbit normal), metres; a right-handed frame rotating with
the chief's orbit. The deputy is a point in it.

A plan's view: node positions and post-burn velocities (the planner's first-order map of its
mean ROE), the burns, and for every node the one-orbit free drift from its post-burn state (the
planner's linear drift model, `Horizon` post-burn map and STM) with the node's passive-safety
margin (`PassiveSafety.evaluate`: continuous minimum over the arc, metres of the ellipsoid in
force, negative inside; the chance-constrained margin includes the q-sigma term).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.dynamics import (
    mean_arg_latitude, mean_motion, orbital_period_s, propagate_mean_oe, psi_from_latitude,
    psi_matrix, stm_j2,
)

FRAME_RTN = "chief_rtn"
DRIFT_SAMPLES = 24  # per drift arc (one orbit): a smooth curve, cheap to publish and record
ZONES = ("approach_ellipsoid", "keep_out_zone")


@dataclass(frozen=True)
class PlanView:
    """A plan in the chief's RTN frame.

    Attributes:
        epochs_s: (N,) node epochs from the plan's t0 [s].
        position_m: (N, 3) RTN node positions [m] (the plan's predicted `rtn`).
        velocity_post_mps: (N, 3) RTN velocity after each burn [m/s].
        dv_rtn_mps: (N, 3) burns [m/s].
        drift_m: (N, S, 3) RTN positions along each node's one-orbit free drift [m].
        drift_tau_s: (S,) drift time of the samples from the node [s].
        margin_m: (N,) passive-safety margin of each node's drift [m] (negative inside).
        zone: (N,) index into ZONES: the ellipsoid in force at each node.
        semi_axes_m: {zone: (3,) RTN semi-axes [m]}.
    """

    epochs_s: np.ndarray
    position_m: np.ndarray
    velocity_post_mps: np.ndarray
    dv_rtn_mps: np.ndarray
    drift_m: np.ndarray
    drift_tau_s: np.ndarray
    margin_m: np.ndarray
    zone: np.ndarray
    semi_axes_m: dict


def drift_rtn(chief_oe0: object, epochs_s: object, roe_post_m: object, duration_s: float,
              n_samples: int = DRIFT_SAMPLES) -> np.ndarray:
    """Linear free-drift arcs (K, S, 6) RTN [m, m/s] from post-burn ROE (K, 6) [m] at node
    epochs (K,) [s] of a chief whose mean elements are `chief_oe0` at epoch 0 (first-order
    map Psi, J2 STM), sampled at `n_samples` times over [0, duration_s]."""
    oe0 = as_finite_array("chief_oe0", chief_oe0, (6,))
    t = as_finite_array("epochs_s", epochs_s, (None,))
    z = as_finite_array("roe_post_m", roe_post_m, (t.size, 6))
    tau = np.linspace(0.0, float(duration_s), int(n_samples))
    n = mean_motion(oe0[0])
    out = np.zeros((t.size, tau.size, 6))
    for k in range(t.size):
        oe_k = propagate_mean_oe(oe0, t[k])
        psi = psi_from_latitude(mean_arg_latitude(propagate_mean_oe(oe_k, tau)), n)
        out[k] = np.einsum("sij,sjk,k->si", psi, stm_j2(oe_k, tau), z[k])
    return out


def plan_view(result: object, safety: object, scenario: object,
              n_samples: int = DRIFT_SAMPLES) -> PlanView:
    """The view of a `PlanResult` with the `PassiveSafety` model it was planned with and the
    scenario (ellipsoid semi-axes)."""
    horizon = safety.horizon
    roe, dv = np.asarray(result.roe_m, float), np.asarray(result.dv_rtn_mps, float)
    post = horizon.post_burn_nonlinear(roe, dv)
    rtn = np.asarray(result.rtn, float)
    velocity_post = rtn[:, 3:] + (horizon.to_rtn(post) - horizon.to_rtn(roe))[:, 3:]
    duration = float(safety.tau_s[-1]) or scenario.t_safety_orbits * orbital_period_s(
        horizon.chief_oe[0, 0])
    tau = np.linspace(0.0, duration, int(n_samples))
    drift = drift_rtn(horizon.chief_oe[0], horizon.epochs_s, post, duration, n_samples)
    margin = safety.evaluate(roe, dv).margin_m
    koz = np.asarray(scenario.koz_semi_axes_m, float)
    ae = np.asarray(scenario.ae_semi_axes_m, float)
    zone = np.all(np.isclose(safety.semi_axes_m, koz), axis=1) & ~np.allclose(ae, koz)
    return PlanView(np.asarray(result.epochs_s, float), rtn[:, :3], velocity_post, dv,
                    drift[:, :, :3], tau, np.asarray(margin, float), zone.astype(int),
                    {ZONES[0]: ae, ZONES[1]: koz})


def nav_position(chief_oe: object, roe_m: object, cov_m2: object
                 ) -> tuple[np.ndarray, np.ndarray]:
    """RTN position (3,) [m] and its covariance (3, 3) [m^2] of a navigation fix in ROE
    (first-order map Psi at the chief's mean argument of latitude)."""
    psi = psi_matrix(chief_oe)[:3]
    x = as_finite_array("roe_m", roe_m, (6,))
    cov = as_finite_array("cov_m2", cov_m2, (6, 6))
    return psi @ x, psi @ cov @ psi.T


def ellipsoid_of(cov_m2: np.ndarray, n_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (3,) [m] and orientation quaternion (x, y, z, w) of the n-sigma ellipsoid of
    a (3, 3) covariance (axes along its eigenvectors, a right-handed rotation)."""
    w, v = np.linalg.eigh(0.5 * (cov_m2 + cov_m2.T))
    if np.linalg.det(v) < 0:
        v[:, 2] = -v[:, 2]
    return n_sigma * np.sqrt(np.clip(w, 0.0, None)), quaternion_of(v)


def quaternion_of(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (3, 3)."""
    m = rot
    tr = float(np.trace(m))
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


def margin_rgb(margin_m: float, full_m: float = 50.0) -> tuple[float, float, float]:
    """Colour of a passive-safety margin: red inside (< 0), from yellow at 0 to green at
    `full_m` metres and beyond."""
    if margin_m < 0:
        return 1.0, 0.0, 0.0
    f = min(float(margin_m) / full_m, 1.0)
    return 1.0 - f, 0.8 + 0.2 * f, 0.0
