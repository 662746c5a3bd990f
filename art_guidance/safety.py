"""Passive (free-drift) safety with state uncertainty: keep-out ellipsoids, t*, linearisation.

Paper Sec. "Safety Constraints with State Uncertainty" (after Guffanti & D'Amico, JGCD 2023).
A contingency at node ``t_i`` leaves the servicer drifting from its post-burn state
``z_i = x_i + B_i u_i`` (a-scaled ROE [m]). The drift is sampled at ``tau_j = linspace(0,
T_safety, n_safety)`` (``tau_0 = 0`` is the node itself) and the RTN position there is
``p_ij = M_ij z_i`` with ``M_ij = D Psi(t_i + tau_j) Phi(t_i + tau_j, t_i)``, (3, 6). The
servicer must stay outside the active ellipsoid ``P_i = Diag(1/r^2)`` (approach ellipsoid before
node ``ae_to_koz_node``, keep-out zone from it on), i.e. the ellipsoidal distance
``d_ij = sqrt(p_ij^T P_i p_ij)`` must be >= 1.

Uncertainty: with the post-burn covariance ``X_i`` (`uncertainty.state_covariance_history`) the
q-sigma margin uses the standard deviation of the linearised distance,
``sigma_ij = sqrt(g_ij^T X_i g_ij)`` with ``g_ij = M_ij^T P_i p_ij / d_ij`` the gradient of
``d_ij`` with respect to ``z_i``. This is exactly the paper's ``||X(t*)^{1/2} a||`` written
frame-consistently: with ``X_ij = Phi_ij X_i Phi_ij^T`` the drift covariance at the sample and
``h_ij = Psi^T D^T P_i p_ij / d_ij`` the gradient with respect to the ROE *at the sample time*,
``g_ij = Phi_ij^T h_ij`` and ``g_ij^T X_i g_ij = h_ij^T X_ij h_ij``. (Pairing ``X_ij`` with the
t_i-gradient ``g_ij`` would apply the drift STM twice.)

Linearisation (paper eqs. a_ps, b_ps, beta, divided by b_ps so that it is well scaled): at the
reference, ``a_i = g_{i,t*} = a_ps / b_ps`` and the convex constraint is
``a_i @ z_i >= 1 + q sigma_{i,t*}``. Since ``a_i @ z = (P^{1/2} p_ref)^T (P^{1/2} p(z)) / d_ref
<= d(z)`` (Cauchy-Schwarz), the linear constraint implies ``d_{i,t*}(z) >= 1 + q sigma``: it is
conservative, and exact (tangent) at the reference since ``d`` is homogeneous of degree one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import (
    Horizon, mean_arg_latitude, mean_motion, orbital_period_s, propagate_mean_oe,
    psi_from_latitude, stm_j2,
)
from art_guidance.errors import InputError
from art_guidance.uncertainty import propagate_covariance, state_covariance_history

# Ellipsoidal distances below this are treated as zero when normalising the gradient.
_D_FLOOR = 1e-12


@dataclass(frozen=True)
class SafetyLinearization:
    """Linearised passive-safety (chance) constraint ``a[i] @ z_i >= rhs[i]`` at every node.

    Attributes:
        a: (N, 6) normalised gradient [1/m] with respect to the post-burn ROE z_i [m].
        rhs: (N,) right-hand side ``1 + beta`` [-].
        beta: (N,) normalised q-sigma margin ``q sigma_{i,t*}`` [-] (0 when deterministic).
        t_star_idx: (N,) index j of the drift sample used (t* = t_i + tau_j).
        dist: (N,) ellipsoidal distance of the reference at t* [-].
    """

    a: np.ndarray
    rhs: np.ndarray
    beta: np.ndarray
    t_star_idx: np.ndarray
    dist: np.ndarray


@dataclass(frozen=True)
class SafetyEvaluation:
    """Nonlinear passive-safety check of a trajectory.

    Attributes:
        margin: (N,) normalised margin ``min_j (d_ij - 1 - q sigma_ij)`` [-]; >= 0 is safe.
        margin_m: (N,) the same times the smallest semi-axis of the active ellipsoid [m].
        violation: (N,) int 0/1, the paper's binary constraint-violation metric (1 = violated,
            i.e. margin < 0).
        constraint_to_go: (N,) int, C(t_i) = sum_{j >= i} violation_j.
        t_star_idx: (N,) index of the drift sample with the smallest margin.
    """

    margin: np.ndarray
    margin_m: np.ndarray
    violation: np.ndarray
    constraint_to_go: np.ndarray
    t_star_idx: np.ndarray


class PassiveSafety:
    """Free-drift passive safety over a horizon; all drift maps are precomputed at construction.

    Attributes:
        horizon: the planning horizon.
        uncertainty: the uncertainty model, or None (deterministic, zero covariance).
        q_sigma: confidence multiplier q [-] (0 when deterministic).
        n_nodes: number of nodes N.
        n_samples: number of drift samples S.
        tau_s: (S,) drift sample offsets [s], tau_0 = 0.
        ellipsoid_p: (N, 3, 3) ellipsoid matrices Diag(1/r^2) [1/m^2].
        semi_axes_m: (N, 3) active ellipsoid semi-axes [m].
        drift_stms: (N, S, 6, 6) Phi(t_i + tau_j, t_i).
        drift_pos_maps: (N, S, 3, 6) D Psi(t_i + tau_j) Phi(t_i + tau_j, t_i) [-] (ROE -> RTN
            position).
    """

    def __init__(self, horizon: Horizon, scenario: ScenarioConfig,
                 uncertainty: UncertaintyConfig | None,
                 t_safety_s: float | None = None, n_safety: int | None = None) -> None:
        """Precompute the drift samples, STMs, position maps and ellipsoids.

        Args:
            horizon: planning horizon (chief elements, B and Psi at the N nodes).
            scenario: scenario (ellipsoid semi-axes [m], AE -> KOZ switch node, defaults).
            uncertainty: uncertainty model, or None for the deterministic problem.
            t_safety_s: free-drift duration [s]; None -> ``scenario.t_safety_orbits`` chief
                periods; 0 -> plain collision avoidance (single sample tau = 0).
            n_safety: number of drift samples; None -> ``scenario.n_safety``. Ignored (1) when
                the drift duration is 0.

        Raises:
            InputError: on a negative/non-finite duration or a sample count < 1.
        """
        self.horizon = horizon
        self.uncertainty = uncertainty
        self.q_sigma = 0.0 if uncertainty is None else float(uncertainty.q_sigma)
        period_s = orbital_period_s(float(horizon.chief_oe[0, 0]))
        t_safe = scenario.t_safety_orbits * period_s if t_safety_s is None else t_safety_s
        t_safe = float(t_safe)
        if not (np.isfinite(t_safe) and t_safe >= 0):
            raise InputError("t_safety_s", "must be finite and >= 0 [s]", t_safety_s)
        n_s = scenario.n_safety if n_safety is None else n_safety
        if int(n_s) != n_s or n_s < 1:
            raise InputError("n_safety", "must be an integer >= 1", n_safety)
        n_s = 1 if t_safe == 0 else int(n_s)
        self.n_nodes = horizon.n_nodes
        self.n_samples = n_s
        self.tau_s = np.linspace(0.0, t_safe, n_s)
        self._build_ellipsoids(scenario)
        self._build_drift_maps()

    # ------------------------------------------------------------------ construction
    def _build_ellipsoids(self, scenario: ScenarioConfig) -> None:
        koz = np.arange(self.n_nodes) >= scenario.ae_to_koz_node  # (N,)
        axes = np.where(koz[:, None], np.asarray(scenario.koz_semi_axes_m),
                        np.asarray(scenario.ae_semi_axes_m))  # (N, 3) [m]
        self.semi_axes_m = axes
        self._p_diag = 1.0 / axes**2  # (N, 3) [1/m^2]
        self.ellipsoid_p = np.zeros((self.n_nodes, 3, 3))
        self.ellipsoid_p[:, np.arange(3), np.arange(3)] = self._p_diag
        self._min_axis_m = axes.min(axis=1)  # (N,)

    def _build_drift_maps(self) -> None:
        n, s = self.n_nodes, self.n_samples
        stms = np.empty((n, s, 6, 6))
        pos = np.empty((n, s, 3, 6))
        n_mot = mean_motion(float(self.horizon.chief_oe[0, 0]))
        for i in range(n):
            oe_i = self.horizon.chief_oe[i]
            drifted = propagate_mean_oe(oe_i, self.tau_s)  # (S, 6)
            stms[i] = stm_j2(oe_i, self.tau_s)  # (S, 6, 6)
            psi_pos = psi_from_latitude(mean_arg_latitude(drifted), n_mot)[:, :3]  # (S, 3, 6)
            pos[i] = psi_pos @ stms[i]
        self.drift_stms = stms
        self.drift_pos_maps = pos
        self._pos_flat = pos.reshape(n, s * 3, 6)  # (N, 3S, 6) for one batched matmul

    # ------------------------------------------------------------------ public API
    def post_burn(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn ROE ``z_i = x_i + B_i u_i`` [m], (N, 6), where a contingency drift starts.

        Args:
            roe_m: (N, 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        """
        x, u = self._check(roe_m, dv_rtn_mps)
        return x + np.einsum("kij,kj->ki", self.horizon.b, u)

    def covariance(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn state covariance X_i [m^2], (N, 6, 6); zeros when deterministic."""
        x, u = self._check(roe_m, dv_rtn_mps)
        return state_covariance_history(x, u, self.horizon, self.uncertainty)

    def drift_covariance(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Drift covariance ``X_ij = Phi_ij X_i Phi_ij^T`` [m^2] at every sample, (N, S, 6, 6)."""
        return propagate_covariance(self.covariance(roe_m, dv_rtn_mps)[:, None],
                                    self.drift_stms)

    def linearize(self, roe_m: object, dv_rtn_mps: object) -> SafetyLinearization:
        """Linearise the passive-safety chance constraint around a reference trajectory.

        For node i, t* is the drift sample with the smallest margin ``d_ij - 1 - q sigma_ij``
        (the most violated one). Deterministically this is the paper's minimum-distance
        sample; with a covariance it can differ, and the most violated sample is the one the
        chance constraint must protect. A reference with ``d = 0`` (through the target centre)
        has no defined gradient and yields ``a_i = 0`` (the constraint is then infeasible and
        must be absorbed by the optimiser's slack).

        Args:
            roe_m: (N, 6) reference pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) reference impulsive delta-v in RTN [m/s].

        Returns:
            SafetyLinearization with ``a[i] @ z_i >= rhs[i]`` for the post-burn ROE z_i [m].
        """
        d, g, sigma, margin = self._samples(roe_m, dv_rtn_mps)
        rows = np.arange(self.n_nodes)
        t_star = np.argmin(margin, axis=1)
        beta = self.q_sigma * sigma[rows, t_star]
        return SafetyLinearization(a=g[rows, t_star], rhs=1.0 + beta, beta=beta,
                                   t_star_idx=t_star, dist=d[rows, t_star])

    def linearize_samples(self, roe_m: object, dv_rtn_mps: object, k: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Linearise at the `k` most violated drift samples of every node (k = 1: `linearize`).

        Constraining several samples per node keeps the convex model valid when t* moves to a
        neighbouring sample between SCP iterations; each row is conservative on its own.

        Args:
            roe_m: (N, 6) reference pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) reference impulsive delta-v in RTN [m/s].
            k: samples per node, 1 <= k <= n_samples.

        Returns:
            a (N, k, 6), rhs (N, k) with ``a[i, m] @ z_i >= rhs[i, m]``, and the sample
            indices (N, k), most violated first.
        """
        k = int(min(max(k, 1), self.n_samples))
        d, g, sigma, margin = self._samples(roe_m, dv_rtn_mps)
        idx = np.argsort(margin, axis=1, kind="stable")[:, :k]  # (N, k)
        rows = np.arange(self.n_nodes)[:, None]
        return g[rows, idx], 1.0 + self.q_sigma * sigma[rows, idx], idx

    def evaluate(self, roe_m: object, dv_rtn_mps: object) -> SafetyEvaluation:
        """Evaluate the nonlinear passive-safety chance constraint along a trajectory.

        Args:
            roe_m: (N, 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].

        Returns:
            SafetyEvaluation (margins, binary violation metric, constraint-to-go).
        """
        _, _, _, margin_ij = self._samples(roe_m, dv_rtn_mps)
        rows = np.arange(self.n_nodes)
        t_star = np.argmin(margin_ij, axis=1)
        margin = margin_ij[rows, t_star]
        violation = (margin < 0.0).astype(int)
        ctg = np.cumsum(violation[::-1])[::-1].copy()
        return SafetyEvaluation(margin=margin, margin_m=margin * self._min_axis_m,
                                violation=violation, constraint_to_go=ctg, t_star_idx=t_star)

    # ------------------------------------------------------------------ internals
    def _check(self, roe_m: object, dv_rtn_mps: object) -> tuple[np.ndarray, np.ndarray]:
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        return x, u

    def _samples(self, roe_m: object, dv_rtn_mps: object
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Distances d (N, S), gradients g (N, S, 6), sigmas (N, S) and margins (N, S)."""
        x, u = self._check(roe_m, dv_rtn_mps)
        n, s = self.n_nodes, self.n_samples
        z = x + (self.horizon.b @ u[:, :, None])[:, :, 0]  # (N, 6)
        p = (self._pos_flat @ z[:, :, None]).reshape(n, s, 3)  # (N, S, 3) [m]
        pp = p * self._p_diag[:, None, :]  # (N, S, 3) P p
        d = np.sqrt(np.einsum("nsi,nsi->ns", p, pp))  # (N, S)
        g = np.einsum("nsij,nsi->nsj", self.drift_pos_maps, pp)  # (N, S, 6)
        g /= np.maximum(d, _D_FLOOR)[:, :, None]
        if self.uncertainty is None:
            sigma = np.zeros((n, s))
        else:
            x_cov = state_covariance_history(x, u, self.horizon, self.uncertainty)
            var = np.einsum("nsj,nsj->ns", g @ x_cov, g)  # g^T X_i g, (N, S)
            sigma = np.sqrt(np.clip(var, 0.0, None))
        return d, g, sigma, d - 1.0 - self.q_sigma * sigma
