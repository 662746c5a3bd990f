"""A planning horizon: the node time grid and `Horizon`, the linear time-varying dynamics over
it (linear and deputy-aware).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from art_guidance import kernels
from art_guidance.checks import as_finite_array
from art_guidance.dynamics.deputy import (
    DeputyLinearization, _control_deputy, _curvature_slope, _deputy_burn_jacobian,
    along_track_curvature_m, deputy_post_burn, post_burn_batch, post_burn_with,
)
from art_guidance.dynamics.elements import (
    check_oe, mean_arg_latitude, mean_motion, orbital_period_s, propagate_mean_oe,
)
from art_guidance.dynamics.frames import psi_from_latitude
from art_guidance.dynamics.stm import _control, stm_j2
from art_guidance.errors import InputError


# --------------------------------------------------------------------------- horizon
def time_grid_s(chief_a_m: float, n_orbits: float, n_nodes: int) -> np.ndarray:
    """Node epochs [s] from t0 = 0: `n_nodes` evenly spaced over `n_orbits` chief periods."""
    if n_nodes < 2 or not n_orbits > 0:
        raise InputError("time_grid", "need n_nodes >= 2 and n_orbits > 0", (n_orbits, n_nodes))
    return np.linspace(0.0, n_orbits * orbital_period_s(chief_a_m), int(n_nodes))


@dataclass(frozen=True)
class Horizon:
    """Linear time-varying dynamics over a planning horizon.

    `propagate` is the linear model (B at zero separation, the convex problem's); the
    ``*_nonlinear`` methods are the deputy-aware model SCVx* plans with (B at the deputy's own
    state, second-order along-track drift) and its Jacobians (`linearize_nonlinear`), its
    post-burn state `post_burn_at` (one array door; `post_burn_nonlinear` and
    `final_post_burn_nonlinear` adapt it to a trajectory and to its last node).

    Attributes:
        epochs_s: (N,) node epochs from the chief epoch of `chief_oe0` [s].
        chief_oe: (N, 6) mean chief elements at each node.
        stm: (N-1, 6, 6) Phi(t_{k+1}, t_k).
        b: (N, 6, 3) control matrices [s].
        psi: (N, 6, 6) ROE -> RTN maps.
    """

    epochs_s: np.ndarray
    chief_oe: np.ndarray
    stm: np.ndarray
    b: np.ndarray
    psi: np.ndarray

    @classmethod
    def build(cls, chief_oe0: object, epochs_s: object) -> "Horizon":
        """Precompute the STMs, B and Psi at `epochs_s` [s] (strictly increasing)."""
        c0 = check_oe(chief_oe0)
        t = as_finite_array("epochs_s", epochs_s, (None,))
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise InputError("epochs_s", "need >= 2 strictly increasing epochs")
        oes = propagate_mean_oe(c0, t)
        n = mean_motion(c0[0])
        u = mean_arg_latitude(oes)
        stm = np.stack([stm_j2(oes[k], t[k + 1] - t[k]) for k in range(t.size - 1)])
        b = np.stack([_control(uk, n) for uk in u])
        psi = psi_from_latitude(u, n)
        return cls(t, oes, stm, b, psi)

    @property
    def n_nodes(self) -> int:
        """Number of nodes N."""
        return int(self.epochs_s.size)

    def propagate(self, roe0_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Roll out x_{k+1} = Phi_k (x_k + B_k u_k); returns (N, 6) pre-burn ROE [m]."""
        x0 = as_finite_array("roe0_m", roe0_m, (6,))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        out = np.empty((self.n_nodes, 6))
        out[0] = x0
        for k in range(self.n_nodes - 1):
            out[k + 1] = self.stm[k] @ (out[k] + self.b[k] @ u[k])
        return out

    # -------------------------------------------------------------- deputy-aware model
    # `propagate` is the linear model of the convex problem (B at zero separation, first-order
    # relative drift). SCVx* plans with the model below, evaluated along its reference: every
    # burn acts through `control_matrix_deputy` at the deputy's own pre-burn state, and every
    # coast adds the second-order Keplerian along-track drift `along_track_curvature_m`.
    def _deputy_constants(self) -> tuple[np.ndarray, float, float, float]:
        a, inc = float(self.chief_oe[0, 0]), float(self.chief_oe[0, 2])
        return mean_arg_latitude(self.chief_oe), mean_motion(a), a, inc

    def post_burn_at(self, nodes: int | np.ndarray, roe_m: np.ndarray,
                     dv_rtn_mps: np.ndarray) -> np.ndarray:
        """Post-burn ROE ``z = x + B_d(x) u`` [m], the shape of `roe_m`: the array door of the
        deputy's post-burn state (the adapters below, the safety model, the ART rollout).

        Args:
            nodes: the node of every state: an int, or ints broadcast against the leading axes
                of `roe_m` (``np.arange(N)`` for (N, 6) or (K, N, 6) trajectories).
            roe_m: (..., 6) pre-burn a-scaled ROE [m].
            dv_rtn_mps: (..., 3) impulsive delta-v in RTN [m/s].

        Not validated: finite float arrays of matching shapes are the caller's (the rollout
        advances with it at every step; `post_burn_nonlinear` validates a trajectory).
        """
        lat, n, a, inc = self._deputy_constants()
        return post_burn_batch(lat[nodes], n, a, inc, roe_m, dv_rtn_mps)

    # adapters of `post_burn_at`
    def post_burn_nonlinear(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """`post_burn_at` of a validated trajectory: (N, 6) [m] from (N, 6) [m], (N, 3) [m/s]."""
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        return self.post_burn_at(np.arange(self.n_nodes), x, u)

    def final_post_burn_nonlinear(self, roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
        """`post_burn_at` of a trajectory's last node (N, 6) [m], (N, 3) [m/s]: (6,) [m]."""
        return self.post_burn_at(self.n_nodes - 1, np.asarray(roe_m, float)[-1],
                                 np.asarray(dv_rtn_mps, float)[-1])

    def propagate_nonlinear(self, roe0_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Roll out ``x_{k+1} = Phi_k z_k + c_k(z_k)``, ``z_k = x_k + B_d(x_k) u_k``: (N, 6) [m].

        The model SCVx* plans with (see `DeputyLinearization`): B at the deputy's pre-burn
        state (`control_matrix_deputy`) and the second-order along-track drift
        (`along_track_curvature_m`) of the post-burn relative semi-major axis. Flown open loop
        in a two-body + J2 truth, 6-8 m/s plans of this model reach the waypoint within 12-28 m
        where plans of the linear `propagate` model miss by ~200 m.

        Args:
            roe0_m: (6,) initial pre-burn a-scaled ROE [m].
            dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].

        Returns:
            (N, 6) pre-burn ROE [m].
        """
        x0 = as_finite_array("roe0_m", roe0_m, (6,))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        lat, n, a, inc = self._deputy_constants()
        if kernels.compiled():  # the same operations compiled (tested bit for bit)
            from art_guidance.kernels import horizon as kernel

            return kernel.propagate_nonlinear(x0, np.ascontiguousarray(u), lat, n, a, inc,
                                              self._stm_c, self._curvature_m)
        u = u.tolist()
        lat = lat.tolist()
        stm = self._stm_rows
        curv = self._curvature_m.tolist()
        out = [x0.tolist()]
        x = out[0]
        for k in range(self.n_nodes - 1):
            z = deputy_post_burn(lat[k], n, a, inc, x, u[k]) if any(u[k]) else x
            x = [r[0] * z[0] + r[1] * z[1] + r[2] * z[2] + r[3] * z[3] + r[4] * z[4]
                 + r[5] * z[5] for r in stm[k]]
            xi = z[0] / a
            x[1] += curv[k] * ((1.0 + xi) ** -1.5 - 1.0 + 1.5 * xi)
            out.append(x)
        return np.array(out)

    def drift_step(self, node: int, z_m: np.ndarray) -> np.ndarray:
        """Pre-burn ROE at `node + 1` (B, 6) [m] from post-burn ROE `z_m` at `node`
        (`post_burn_at`): the second half of one step of `propagate_nonlinear` for a batch, the
        form the ART rollout advances with (STM and second-order along-track drift; not
        validated)."""
        k = int(node)
        x1 = z_m @ self.stm[k].T  # (B, 6)
        a = self._deputy_constants()[2]
        x1[:, 1] += along_track_curvature_m(a, z_m[:, 0],
                                            self.epochs_s[k + 1] - self.epochs_s[k])
        return x1

    @functools.cached_property
    def _curvature_m(self) -> np.ndarray:
        """(N - 1,) the along-track curvature factor a n dt of each step [m]."""
        _, n, a, _ = self._deputy_constants()
        return a * n * np.diff(self.epochs_s)

    @functools.cached_property
    def _stm_c(self) -> np.ndarray:
        """`stm` C-contiguous (the compiled kernel's input)."""
        return np.ascontiguousarray(self.stm)

    @functools.cached_property
    def _stm_rows(self) -> list:
        """`stm` as nested lists (float arithmetic in `propagate_nonlinear`)."""
        return self.stm.tolist()

    def linearize_nonlinear(self, roe_m: object, dv_rtn_mps: object) -> DeputyLinearization:
        """Jacobians of `propagate_nonlinear` along a reference (N, 6) [m], (N, 3) [m/s]."""
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        lat, n, a, inc = self._deputy_constants()
        b = _control_deputy(lat, n, a, inc, x)
        jac = _deputy_burn_jacobian(lat, n, a, inc, x, u)
        z = post_burn_with(b, x, u)
        e = jac + np.eye(6)
        p = self.stm.copy()
        p[:, 1, 0] += _curvature_slope(a, z[:-1, 0], np.diff(self.epochs_s))
        return DeputyLinearization(e, b, (jac @ x[:, :, None])[:, :, 0], p, z, x)

    def to_rtn(self, roe_m: np.ndarray) -> np.ndarray:
        """(N, 6) ROE [m] -> (N, 6) RTN [m, m/s] by the first-order map at each node."""
        return np.einsum("kij,kj->ki", self.psi, roe_m)
