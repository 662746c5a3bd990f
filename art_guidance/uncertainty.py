"""State uncertainty model of the paper (Sec. "Uncertainty Modeling", Table II), pure numpy.

Three Gaussian, zero-mean error sources, all expressed on the a-scaled ROE state [m]:

* navigation (ARTMS, angles-only): per-axis standard deviation ``s(rho) * rho`` [m], with
  ``rho`` the relative range [m] and ``s`` interpolated linearly between ``s2`` (rho < rho2) and
  ``s1`` (rho > rho1). The paper prints ``rho / a^2 * s s^T``, which is not dimensionally
  consistent; like the authors' code we use ``Diag(s * rho)^2``;
* actuation (Gates model): covariance ``U = R V R^T`` of the executed delta-v [m/s] in RTN,
  mapped to ROE by the control matrix ``B`` [s];
* unmodelled dynamics: constant process noise ``Q = process_noise_m2 * I6`` [m^2].

Covariance recursion (paper eq. "Linearized covariance dynamics"): at every node the filter
delivers a fresh estimate, so the post-burn covariance at ``t_i`` is
``X(t_i) = X_nav(x_i) + B_i U(u_i) B_i^T + Q`` and a free drift propagates it as
``X(t) = Phi(t, t_i) X(t_i) Phi(t, t_i)^T``.
"""
from __future__ import annotations

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import UncertaintyConfig
from art_guidance.dynamics import Horizon
from art_guidance.errors import InputError

# Below this delta-v magnitude [m/s] the burn direction is treated as undefined (see gates).
DV_ZERO_MPS = 1e-12


def nav_range_m(roe_m: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Relative range rho [m], (N,), from (N, 6) ROE [m] and (N, 6, 6) ROE -> RTN maps."""
    pos_m = np.einsum("kij,kj->ki", psi[:, :3, :], roe_m)  # (N, 3)
    return np.sqrt(np.einsum("ki,ki->k", pos_m, pos_m))


def nav_std_scale(rho_m: np.ndarray, cfg: UncertaintyConfig) -> np.ndarray:
    """ARTMS accuracy coefficients s(rho), (N, 6) [-], for ranges `rho_m` (N,) [m].

    ``s = s1`` for rho > rho1, ``s = s2`` for rho < rho2 and the paper's linear interpolation
    ``(s1 (rho - rho2) + s2 (rho1 - rho)) / (rho1 - rho2)`` in between (continuous at both ends).
    """
    w = np.clip((rho_m - cfg.nav_rho2_m) / (cfg.nav_rho1_m - cfg.nav_rho2_m), 0.0, 1.0)
    s1 = np.asarray(cfg.nav_s1)
    s2 = np.asarray(cfg.nav_s2)
    return w[:, None] * s1 + (1.0 - w[:, None]) * s2


def nav_covariance(roe_m: object, psi: object, cfg: UncertaintyConfig) -> np.ndarray:
    """ARTMS navigation covariance of the a-scaled ROE at each node.

    Args:
        roe_m: (N, 6) a-scaled ROE [m] (the estimate equals the designed mean state).
        psi: (N, 6, 6) first-order ROE -> RTN maps at the same nodes; only the position rows
            are used, to get the range rho = ||D Psi x|| [m].
        cfg: uncertainty model (s1, s2, rho1, rho2).

    Returns:
        (N, 6, 6) diagonal covariance ``Diag(s(rho) * rho)^2`` [m^2].

    Raises:
        InputError: on NaN/inf or shapes that do not match.
    """
    x = as_finite_array("roe_m", roe_m, (None, 6))
    p = as_finite_array("psi", psi, (x.shape[0], 6, 6))
    return _nav_covariance(x, p, cfg)


def _nav_covariance(x: np.ndarray, psi: np.ndarray, cfg: UncertaintyConfig) -> np.ndarray:
    """`nav_covariance` of arrays already checked."""
    rho_m = nav_range_m(x, psi)  # (N,)
    std_m = nav_std_scale(rho_m, cfg) * rho_m[:, None]  # (N, 6)
    out = np.zeros((x.shape[0], 6, 6))
    idx = np.arange(6)
    out[:, idx, idx] = std_m**2
    return out


def gates_covariance(dv_rtn_mps: object, cfg: UncertaintyConfig) -> np.ndarray:
    """Gates actuation-error covariance U of each impulsive burn, in RTN.

    With ``e1 = dv / |dv|`` the burn direction, ``U = R V R^T`` with
    ``V = Diag{sr^2 + dv^2 ss^2, sa^2 + dv^2 sp^2, sa^2 + dv^2 sp^2}`` is written without an
    arbitrary transverse basis as::

        U = sa^2 I + (sr^2 - sa^2) e1 e1^T + ss^2 dv dv^T + sp^2 (|dv|^2 I - dv dv^T)

    Only the ``(sr^2 - sa^2) e1 e1^T`` term needs the direction. At ``|dv| <= DV_ZERO_MPS`` the
    direction is undefined and the limit depends on how dv -> 0; we then return
    ``max(sr^2, sa^2) I``, the smallest isotropic covariance that dominates the limit from every
    direction (conservative). For Table II (sr == sa) that term vanishes, so U is a polynomial in
    dv and exactly continuous at 0 (``U(0) = sa^2 I``).

    Args:
        dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        cfg: uncertainty model (sigma_s, sigma_p [-, rad]; sigma_r, sigma_a [m/s]).

    Returns:
        (N, 3, 3) symmetric positive semi-definite covariance [m^2/s^2].

    Raises:
        InputError: on NaN/inf or a shape other than (N, 3).
    """
    return _gates_covariance(as_finite_array("dv_rtn_mps", dv_rtn_mps, (None, 3)), cfg)


def _gates_covariance(dv: np.ndarray, cfg: UncertaintyConfig) -> np.ndarray:
    """`gates_covariance` of an array already checked."""
    n = dv.shape[0]
    eye = np.eye(3)
    dv2 = np.einsum("ki,ki->k", dv, dv)  # (N,)
    outer = dv[:, :, None] * dv[:, None, :]  # (N, 3, 3)
    ss2, sp2 = cfg.sigma_s**2, cfg.sigma_p**2
    sr2, sa2 = cfg.sigma_r**2, cfg.sigma_a**2
    u = sa2 * eye + ss2 * outer + sp2 * (dv2[:, None, None] * eye - outer)
    if sr2 != sa2:
        moving = dv2 > DV_ZERO_MPS**2
        e1e1 = np.zeros((n, 3, 3))
        e1e1[moving] = outer[moving] / dv2[moving, None, None]
        u = u + (sr2 - sa2) * e1e1
        u[~moving] = max(sr2, sa2) * eye
    return 0.5 * (u + np.swapaxes(u, -1, -2))


def process_noise(cfg: UncertaintyConfig) -> np.ndarray:
    """Process-noise covariance Q = process_noise_m2 * I6, (6, 6) [m^2] (a-scaled ROE)."""
    return cfg.process_noise_m2 * np.eye(6)


def propagate_covariance(x_cov: object, phi: object) -> np.ndarray:
    """Batched ``Phi X Phi^T`` (symmetrised); shapes broadcast over leading axes.

    Args:
        x_cov: (..., n, n) covariance [m^2].
        phi: (..., n, n) state transition matrices (leading axes broadcast against `x_cov`).

    Returns:
        (..., n, n) propagated covariance [m^2].
    """
    x = np.asarray(x_cov, dtype=float)
    f = np.asarray(phi, dtype=float)
    if x.ndim < 2 or f.ndim < 2 or x.shape[-1] != x.shape[-2] or f.shape[-1] != x.shape[-1]:
        raise InputError("x_cov/phi", f"incompatible shapes {x.shape} and {f.shape}")
    out = f @ x @ np.swapaxes(f, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def post_burn_covariance(roe_m: object, dv_rtn_mps: object, b: object, psi: object,
                         cfg: UncertaintyConfig) -> np.ndarray:
    """Post-burn state covariance ``X = X_nav(x) + B U(u) B^T + Q`` of M (state, burn) pairs.

    Args:
        roe_m: (M, 6) pre-burn a-scaled ROE [m].
        dv_rtn_mps: (M, 3) impulsive delta-v in RTN [m/s].
        b: (M, 6, 3) or (6, 3) control matrices [s] of the burns.
        psi: (M, 6, 6) or (6, 6) ROE -> RTN maps at the burns (range for the navigation error).
        cfg: uncertainty model.

    Returns:
        (M, 6, 6) covariance [m^2].

    Raises:
        InputError: on NaN/inf or shapes that do not match.
    """
    x = as_finite_array("roe_m", roe_m, (None, 6))
    m = x.shape[0]
    u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (m, 3))
    b = np.broadcast_to(np.asarray(b, float), (m, 6, 3))
    psi = as_finite_array("psi", np.broadcast_to(np.asarray(psi, float), (m, 6, 6)), (m, 6, 6))
    return post_burn_covariance_checked(x, u, b, psi, cfg)


def post_burn_covariance_checked(x: np.ndarray, u: np.ndarray, b: np.ndarray, psi: np.ndarray,
                                 cfg: UncertaintyConfig) -> np.ndarray:
    """`post_burn_covariance` of finite float arrays already of shapes (M, 6), (M, 3),
    (M, 6, 3) and (M, 6, 6) (broadcast views will do): the same numbers without the checks,
    for the rollout loop, which calls it at every step."""
    act = b @ _gates_covariance(u, cfg) @ np.swapaxes(b, -1, -2)  # (M, 6, 6)
    out = _nav_covariance(x, psi, cfg) + act + process_noise(cfg)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def state_covariance_history(roe_m: object, dv_rtn_mps: object, horizon: Horizon,
                             cfg: UncertaintyConfig | None) -> np.ndarray:
    """Post-burn state error covariance at every node, ``X(t_i) = X_nav + B U B^T + Q``.

    The filter provides a new estimate at each node (paper Sec. "Uncertainty Modeling"), so
    X(t_i) does not accumulate along the plan; it is the covariance at the start of the free
    drift that the passive-safety margin propagates.

    Args:
        roe_m: (N, 6) pre-burn a-scaled ROE [m] at the N horizon nodes.
        dv_rtn_mps: (N, 3) impulsive delta-v in RTN [m/s].
        horizon: the horizon (uses `psi` for the range and `b` for the burn mapping).
        cfg: uncertainty model, or None for the deterministic problem (returns zeros).

    Returns:
        (N, 6, 6) covariance [m^2].

    Raises:
        InputError: on NaN/inf or shapes that do not match the horizon.
    """
    n = horizon.n_nodes
    x = as_finite_array("roe_m", roe_m, (n, 6))
    u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (n, 3))
    if cfg is None:
        return np.zeros((n, 6, 6))
    return post_burn_covariance(x, u, horizon.b, horizon.psi, cfg)
