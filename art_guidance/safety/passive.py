"""Passive (free-drift) safety with state uncertainty: keep-out ellipsoids, t*, linearisation.

Paper Sec. "Safety Constraints with State Uncertainty" (after Guffanti & D'Amico, JGCD 2023).
A contingency at node ``t_i`` leaves the servicer drifting from its post-burn state
``z_i = x_i + B_d(x_i) u_i`` (a-scaled ROE [m]; B_d: the burn acts at the deputy's own state,
`dynamics.Horizon.post_burn_at`) for ``T_safety``. Its RTN position at
``t_i + tau`` is ``p_i(tau) = M_i(tau) z_i`` with ``M_i(tau) = D Psi(t_i + tau) Phi(t_i + tau,
t_i)``, (3, 6). The servicer must stay outside the active ellipsoid ``P_i = Diag(1/r^2)``
(approach ellipsoid before node ``ae_to_koz_node``, keep-out zone from it on), i.e. the
ellipsoidal distance ``d_i(tau) = sqrt(p^T P_i p)`` must be >= 1 for *every* tau in
``[0, T_safety]``, not only at the ``n_safety`` samples ``tau_j = linspace(0, T_safety,
n_safety)`` (a 1.2 m/s fly-by passes a 200 m zone between two samples 290 s apart).

Uncertainty: with the post-burn covariance ``X_i`` (`uncertainty.state_covariance_history`) the
q-sigma margin uses the standard deviation of the linearised distance,
``sigma_i(tau) = sqrt(g^T X_i g)`` with ``g = M_i(tau)^T P_i p / d`` the gradient of ``d_i(tau)``
with respect to ``z_i``. This is the paper's ``||X(t*)^{1/2} a||`` written frame-consistently:
with ``X(tau) = Phi X_i Phi^T`` the covariance propagated along the drift and ``h = Psi^T D^T
P p / d`` the gradient with respect to the ROE at ``t_i + tau``, ``g = Phi^T h`` and ``g^T X_i g
= h^T X(tau) h``. The margin is ``m_i(tau) = d - 1 - q sigma``.

Continuous t*. ``t*_i = t_i + tau*`` minimises ``m_i`` over the whole arc: `drift.DriftArcs`
writes the drift in closed form and returns the certified minimum (every sample interval is
either refined or carries a lower bound above it; see that module for why a fast fly-by between
samples cannot hide). Every public method here uses that one evaluation, through two array
doors over (state, burn) pairs at any nodes: `minimum`, the margins and t* (and hence, through
its trajectory adapter `evaluate`, C(t_i), the dataset's constraint-to-go, the post hoc E_C and
the plan's `constraint_margin_m`; and the linearisation points of SCVx*), and `violated`, the
sign alone (the transformer's C updates and the ranking of its candidates: the same search,
stopped once the sign is decided).

Linearisation (paper eqs. a_ps, b_ps, beta, divided by b_ps so that it is well scaled): at the
reference, ``a_i = g_i(tau*) = a_ps / b_ps`` and the convex constraint is
``a_i @ z_i >= 1 + q sigma_i(tau*)``. Since ``a_i @ z = (P^{1/2} p_ref)^T (P^{1/2} p(z)) / d_ref
<= d(z)`` (Cauchy-Schwarz), the linear constraint implies ``d_i(tau*)(z) >= 1 + q sigma``: it is
conservative, and exact (tangent) at the reference since ``d`` is homogeneous of degree one.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.safety.drift import ArcItems, ArcMinimum, DriftArcs
from art_guidance.safety.results import (  # noqa: F401 (also imported from here)
    SafetyEvaluation, SafetyLinearization,
)
from art_guidance.dynamics import (
    Horizon, mean_arg_latitude, mean_motion, orbital_period_s, propagate_mean_oe,
    psi_from_latitude, stm_j2,
)
from art_guidance.errors import InputError
from art_guidance.uncertainty import (
    post_burn_covariance_checked, propagate_covariance, state_covariance_history,
)

ROW_DIP = 2.5e-3        # largest dip of the margin between linearisation rows around t* [-]
ROW_DELTA_MIN_S = 1.0   # smallest spacing of those rows [s]


class PassiveSafety:
    """Free-drift passive safety over a horizon; all drift maps are precomputed at construction.

    Attributes:
        horizon: the planning horizon.
        uncertainty: the uncertainty model, or None (deterministic, zero covariance).
        q_sigma: confidence multiplier q [-] (0 when deterministic).
        n_nodes: number of nodes N.
        n_samples: number of drift samples S (the search grid of the continuous minimum).
        tau_s: (S,) drift sample offsets [s], tau_0 = 0.
        arcs: the closed-form drift arcs (`drift.DriftArcs`).
        ellipsoid_p: (N, 3, 3) ellipsoid matrices Diag(1/r^2) [1/m^2].
        semi_axes_m: (N, 3) active ellipsoid semi-axes [m].
        drift_stms: (N, S, 6, 6) Phi(t_i + tau_j, t_i) (built on first use).
        drift_pos_maps: (N, S, 3, 6) D Psi(t_i + tau_j) Phi(t_i + tau_j, t_i) [-] (ROE -> RTN
            position; built on first use).
    """

    def __init__(self, horizon: Horizon, scenario: ScenarioConfig,
                 uncertainty: UncertaintyConfig | None,
                 t_safety_s: float | None = None, n_safety: int | None = None,
                 koz_switch_node: int | None = None) -> None:
        """Precompute the drift samples, STMs, position maps and ellipsoids.

        Args:
            horizon: planning horizon (chief elements, B and Psi at the N nodes).
            scenario: scenario (ellipsoid semi-axes [m], AE -> KOZ switch node, defaults).
            uncertainty: uncertainty model, or None for the deterministic problem.
            t_safety_s: free-drift duration [s]; None -> ``scenario.t_safety_orbits`` chief
                periods; 0 -> plain collision avoidance (single sample tau = 0).
            n_safety: number of drift samples; None -> ``scenario.n_safety``. Ignored (1) when
                the drift duration is 0.
            koz_switch_node: first node of this horizon guarded by the keep-out zone (0: all,
                >= N: none); None -> ``scenario.ae_to_koz_node`` (a fresh plan). A replan over
                the remaining horizon passes the switch's node in its own grid.

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
        switch = scenario.ae_to_koz_node if koz_switch_node is None else int(koz_switch_node)
        if switch < 0:
            raise InputError("koz_switch_node", "must be >= 0", koz_switch_node)
        self._build_ellipsoids(scenario, switch)
        self.arcs = DriftArcs(horizon.chief_oe, self.semi_axes_m, t_safe, n_s)
        self._cache: tuple | None = None

    # ------------------------------------------------------------------ construction
    def _build_ellipsoids(self, scenario: ScenarioConfig, koz_switch_node: int) -> None:
        koz = np.arange(self.n_nodes) >= koz_switch_node  # (N,)
        axes = np.where(koz[:, None], np.asarray(scenario.koz_semi_axes_m),
                        np.asarray(scenario.ae_semi_axes_m))  # (N, 3) [m]
        self.semi_axes_m = axes
        self._p_diag = 1.0 / axes**2  # (N, 3) [1/m^2]
        self.ellipsoid_p = np.zeros((self.n_nodes, 3, 3))
        self.ellipsoid_p[:, np.arange(3), np.arange(3)] = self._p_diag
        self._min_axis_m = axes.min(axis=1)  # (N,)

    @cached_property
    def _drift_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(drift_stms, drift_pos_maps), built on first use: the planner's margins come from
        `DriftArcs`, so only the sampled checks read these (half the construction time)."""
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
        return stms, pos

    @property
    def drift_stms(self) -> np.ndarray:
        """(N, S, 6, 6) Phi(t_i + tau_j, t_i) at the drift samples (built on first use)."""
        return self._drift_maps[0]

    @property
    def drift_pos_maps(self) -> np.ndarray:
        """(N, S, 3, 6) D Psi(t_i + tau_j) Phi(t_i + tau_j, t_i), ROE -> RTN position at the
        drift samples (built on first use)."""
        return self._drift_maps[1]

    # ------------------------------------------------------------------ array doors
    def minimum(self, nodes: object, roe_m: object, dv_rtn_mps: object,
                sign_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Certified minimum of the margin on the drift arcs of (state, burn) pairs.

        Each arc is its own (the covariance of its own state and burn, chance-constrained, or
        none); only the cap on intervals split per level of degenerate arcs (`drift.MAX_OPEN`
        per arc on average) is shared by the pairs of one call.

        Args:
            nodes: the node of every pair: an int, or ints broadcast against the leading axes
                of `roe_m` (``np.arange(N)`` for (N, 6) or (K, N, 6) trajectories).
            roe_m: (..., 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (..., 3) impulsive delta-v in RTN [m/s].
            sign_only: decide only the sign of every minimum (`violated`'s oracle): the
                margins then carry only their sign, the same as the full search's except for
                minima within the certification tolerance of zero, and t* no more than that.

        Returns:
            margin [-] (>= 0 is safe) and t* - t_i [s], each of the leading shape of `roe_m`
            (arrays of their own: the minimum of the last pairs is cached, `_minimum_at`).

        Raises:
            InputError: on a bad node index, NaN/inf or shapes that do not match.
        """
        node, x, u, lead = self._pairs(nodes, roe_m, dv_rtn_mps)
        res = self._minimum_at(node, x, u, sign_only)[1]
        return res.margin.reshape(lead).copy(), res.tau_s.reshape(lead).copy()

    def violated(self, nodes: object, roe_m: object, dv_rtn_mps: object,
                 z_m: np.ndarray | None = None) -> np.ndarray:
        """Whether the certified minimum margin of each pair's drift arc is below zero: bool,
        of the leading shape of `roe_m`.

        Decided by the rollout's search (`DriftArcs.violated_at`: the arcs a drift sample
        already shows inside are decided by the samples, no minimum or candidate instants are
        kept; compiled where the compiled numerics are in use), the decision of
        ``minimum(..., sign_only=True)[0] < 0`` (its oracle, tested): what the transformer's C
        update and ranking candidates by their C(t_1) need.

        Args:
            nodes, roe_m, dv_rtn_mps: as `minimum`.
            z_m: the post-burn states (..., 6) [m] where the caller has them
                (`Horizon.post_burn_at`, the rollout's loop): the arrays are then taken as
                they are, not validated (finite by construction there).
        """
        if z_m is None:
            node, x, u, lead = self._pairs(nodes, roe_m, dv_rtn_mps)
            z_m = self.horizon.post_burn_at(node, x, u)
        else:
            lead = roe_m.shape[:-1]
            node = int(nodes) if np.ndim(nodes) == 0 else np.broadcast_to(nodes, lead).ravel()
            x, u = roe_m.reshape(-1, 6), dv_rtn_mps.reshape(-1, 3)
        return self._violated_at(node, x, u, z_m.reshape(-1, 6)).reshape(lead)

    # ------------------------------------------------------------------ trajectories, SCVx*
    def post_burn(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn ROE ``z_i = x_i + B_d(x_i) u_i`` [m], (N, 6), where the free drift starts.

        B_d is the control matrix at the deputy's pre-burn state (`Horizon.post_burn_at`, the
        post-burn state of the plans SCVx* makes); every margin here starts from it.

        Args:
            roe_m: (N, 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        """
        x, u = self._check(roe_m, dv_rtn_mps)
        return self.horizon.post_burn_nonlinear(x, u)

    def covariance(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn state covariance X_i [m^2], (N, 6, 6); zeros when deterministic."""
        x, u = self._check(roe_m, dv_rtn_mps)
        return state_covariance_history(x, u, self.horizon, self.uncertainty)

    def drift_covariance(self, roe_m: object, dv_rtn_mps: object,
                         tau_s: object | None = None) -> np.ndarray:
        """Covariance propagated along the drift, ``Phi(t_i + tau_i, t_i) X_i Phi^T`` [m^2].

        Args:
            roe_m: (N, 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
            tau_s: (N,) drift offsets [s]; None -> the continuous t* of `evaluate`.

        Returns:
            (N, 6, 6) covariance at ``t_i + tau_i``.
        """
        tau = self._arc(roe_m, dv_rtn_mps)[1].tau_s if tau_s is None else as_finite_array(
            "tau_s", tau_s, (self.n_nodes,))
        phi = np.stack([self.drift_maps(i, tau[i:i + 1])[0][0] for i in range(self.n_nodes)])
        return propagate_covariance(self.covariance(roe_m, dv_rtn_mps), phi)

    def drift_maps(self, i: int, tau_s: object) -> tuple[np.ndarray, np.ndarray]:
        """STMs (K, 6, 6) and RTN position maps ``D Psi Phi`` (K, 3, 6) of node i's drift.

        Computed directly from `dynamics.stm_j2` and `dynamics.psi_from_latitude` at the offsets
        `tau_s` (K,) [s] (independent of the closed form used for the minimum).
        """
        tau = as_finite_array("tau_s", tau_s, (None,))
        oe_i = self.horizon.chief_oe[int(i)]
        n_mot = mean_motion(float(oe_i[0]))
        stm = stm_j2(oe_i, tau)
        psi_pos = psi_from_latitude(mean_arg_latitude(propagate_mean_oe(oe_i, tau)), n_mot)[:, :3]
        return stm, psi_pos @ stm

    def linearize(self, roe_m: object, dv_rtn_mps: object) -> SafetyLinearization:
        """Linearise the passive-safety chance constraint around a reference trajectory.

        For node i, t* is the continuous minimiser of the margin ``d - 1 - q sigma`` over the
        drift arc (the most violated instant). Deterministically this is the paper's
        minimum-distance instant; with a covariance it can differ, and the most violated
        instant is the one the chance constraint must protect. A reference with ``d = 0``
        (through the target centre) has no defined gradient and yields ``a_i = 0`` (the
        constraint is then infeasible and must be absorbed by the optimiser's slack).

        Args:
            roe_m: (N, 6) reference pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) reference impulsive delta-v in RTN [m/s].

        Returns:
            SafetyLinearization with ``a[i] @ z_i >= rhs[i]`` for the post-burn ROE z_i [m].
        """
        items, res = self._arc(roe_m, dv_rtn_mps)
        d, g, sigma = self.arcs.gradient(items, res.tau_s[:, None])
        beta = self.q_sigma * sigma[:, 0]
        return SafetyLinearization(a=g[:, 0], rhs=1.0 + beta, beta=beta, t_star_s=res.tau_s,
                                   dist=d[:, 0])

    def linearize_samples(self, roe_m: object, dv_rtn_mps: object, k: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Linearise at `k` instants of every node's drift: t*, its neighbours, other minima.

        Rows, in order: t*; then ``t* - delta`` and ``t* + delta`` (k >= 3) with
        ``delta = sqrt(8 ROW_DIP / m''(t*))`` clipped to [ROW_DELTA_MIN_S, h / 2] (h the sample
        spacing), so that a margin with the reference's curvature cannot dip by more than
        ROW_DIP between the rows when t* moves during an SCP step (the row at t* alone is
        exact only to first order: the minimum of the new iterate is elsewhere); then the
        other refined local minima and drift samples by increasing margin. Each row is
        conservative on its own (Cauchy-Schwarz at its instant).

        Args:
            roe_m: (N, 6) reference pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) reference impulsive delta-v in RTN [m/s].
            k: rows per node, 1 <= k <= n_samples.

        Returns:
            a (N, k, 6), rhs (N, k) with ``a[i, m] @ z_i >= rhs[i, m]``, and the drift offsets
            (N, k) [s] of the rows.
        """
        k = int(min(max(k, 1), self.n_samples))
        items, res = self._arc(roe_m, dv_rtn_mps)
        tau = res.top_k(k)
        if k >= 3:
            tau = np.column_stack([tau[:, :1], self._neighbours(items, res.tau_s),
                                   tau[:, 1:k - 2]])
        _, g, sigma = self.arcs.gradient(items, tau)
        return g, 1.0 + self.q_sigma * sigma, tau

    def _neighbours(self, items: ArcItems, t_star_s: np.ndarray) -> np.ndarray:
        """(N, 2) offsets ``t* -/+ delta`` [s] (see `linearize_samples`)."""
        t_end = float(self.tau_s[-1])
        eps = 1e-2 * ROW_DELTA_MIN_S
        probe = np.clip(t_star_s[:, None] + np.array([-eps, eps]), 0.0, t_end)
        dm = self.arcs.points(items, np.arange(self.n_nodes), probe).dm
        curv = (dm[:, 1] - dm[:, 0]) / np.maximum(probe[:, 1] - probe[:, 0], 1e-12)
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.sqrt(8.0 * ROW_DIP / curv)
        h_half = 0.5 * t_end / max(self.n_samples - 1, 1)
        delta = np.clip(np.where(np.isfinite(delta), delta, h_half), ROW_DELTA_MIN_S, h_half)
        return np.clip(t_star_s[:, None] + delta[:, None] * np.array([-1.0, 1.0]), 0.0, t_end)

    # ------------------------------------------------------------------ adapters
    # shapes of the doors the callers have; the rest are test oracles (test/helpers/oracles.py)
    def evaluate(self, roe_m: object, dv_rtn_mps: object) -> SafetyEvaluation:
        """`minimum` of one trajectory, (N, 6) [m] and (N, 3) [m/s], with the binary violation
        metric and the constraint-to-go (cached with its arcs: `linearize` of the same iterate
        reuses them)."""
        res = self._arc(roe_m, dv_rtn_mps)[1]
        margin = res.margin
        violation = (margin < 0.0).astype(int)
        ctg = np.cumsum(violation[::-1])[::-1].copy()
        return SafetyEvaluation(margin=margin, margin_m=margin * self._min_axis_m,
                                violation=violation, constraint_to_go=ctg, t_star_s=res.tau_s)

    def violations_batch(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """`violated` of K trajectories, (K, N, 6) [m] and (K, N, 3) [m/s]: (K, N) bool."""
        n = self.n_nodes
        x = as_finite_array("roe_m", roe_m, (None, n, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (x.shape[0], n, 3))
        return self.violated(np.arange(n), x, u)

    # ------------------------------------------------------------------ internals
    def _pairs(self, nodes: object, roe_m: object, dv_rtn_mps: object) -> tuple:
        """Validated pairs as flat arcs: (node: an int or (M,) ints, pre-burn states (M, 6) [m],
        burns (M, 3) [m/s], the leading shape of `roe_m`)."""
        x = as_finite_array("roe_m", roe_m, (None,) * (np.ndim(roe_m) - 1) + (6,))
        lead = x.shape[:-1]
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, lead + (3,))
        node = np.asarray(nodes)
        try:
            ok = node.dtype.kind in "iuf" and bool(np.all(node == np.trunc(node)))
            node = np.broadcast_to(node, lead) if node.ndim else node
        except ValueError:  # not broadcast against the pairs
            ok = False
        if not ok or np.any((node < 0) | (node >= self.n_nodes)):
            raise InputError("nodes", f"must be node indices in [0, {self.n_nodes}) broadcast "
                             f"against the pairs {lead}", nodes)
        node = int(node) if node.ndim == 0 else node.astype(np.int64).ravel()
        return node, x.reshape(-1, 6), u.reshape(-1, 3), lead

    def _items_at(self, i: int | np.ndarray, x: np.ndarray, u: np.ndarray, z: np.ndarray
                  ) -> ArcItems:
        """Drift arcs of B post-burn states `z` at node i, or at nodes i (B,) (pre-burn `x`,
        burns `u`)."""
        return self.arcs.items(*self._arcs_at(i, x, u, z), self.q_sigma)

    def _violated_at(self, i: int | np.ndarray, x: np.ndarray, u: np.ndarray, z: np.ndarray
                     ) -> np.ndarray:
        """(B,) bool: the violation indicator of the arcs of `_items_at` (`DriftArcs.
        violated_at`: compiled where the compiled numerics are in use)."""
        return self.arcs.violated_at(*self._arcs_at(i, x, u, z), self.q_sigma)

    def _arcs_at(self, i: int | np.ndarray, x: np.ndarray, u: np.ndarray, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(nodes (B,), post-burn states (B, 6) [m], post-burn covariances (B, 6, 6) [m^2] or
        None) of B (state, burn) pairs at node i or nodes i (B,)."""
        m = x.shape[0]
        x_cov = None
        if self.uncertainty is not None:
            b, psi = self.horizon.b[i], self.horizon.psi[i]
            x_cov = post_burn_covariance_checked(
                x, u, np.broadcast_to(b, (m, 6, 3)), np.broadcast_to(psi, (m, 6, 6)),
                self.uncertainty)
        return np.broadcast_to(i, (m,)).copy(), z, x_cov

    def _check(self, roe_m: object, dv_rtn_mps: object) -> tuple[np.ndarray, np.ndarray]:
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        return x, u

    def _arc(self, roe_m: object, dv_rtn_mps: object) -> tuple[ArcItems, ArcMinimum]:
        """The arcs and certified arc minima of a trajectory, (N, 6) [m] and (N, 3) [m/s]:
        `minimum`'s at every node (`_minimum_at`)."""
        x, u = self._check(roe_m, dv_rtn_mps)
        return self._minimum_at(np.arange(self.n_nodes), x, u)

    def _minimum_at(self, node: int | np.ndarray, x: np.ndarray, u: np.ndarray,
                    sign_only: bool = False) -> tuple[ArcItems, ArcMinimum]:
        """The drift arcs of validated pairs (`_pairs`: node an int or (M,) ints, pre-burn
        states (M, 6) [m], burns (M, 3) [m/s]) and their certified minima, the body of
        `minimum` and of the trajectory adapters. The last one is cached (SCVx* evaluates and
        then linearises the same iterate): the cached arrays are shared, never to be written."""
        key = (node if isinstance(node, int) else node.tobytes(), x.tobytes(), u.tobytes(),
               bool(sign_only))
        cached = self._cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        items = self._items_at(node, x, u, self.horizon.post_burn_at(node, x, u))
        res = self.arcs.minimum(items, sign_only=sign_only)
        self._cache = (key, items, res)
        return items, res
