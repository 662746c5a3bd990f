"""The deputy-aware model SCVx* plans with: B at the deputy's own state and the second-order
along-track drift of its own mean motion, with their Jacobians.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from art_guidance.dynamics.elements import check_oe, mean_arg_latitude, mean_motion
from art_guidance.errors import InputError


def control_matrix_deputy(chief_oe: object, roe_m: object) -> np.ndarray:
    """Control matrix of a burn *at the deputy*: d(roe_m) = B @ dv_rtn_mps, (6, 3) or (K, 6, 3).

    `control_matrix` is the Gauss variational equations (GVE) of a near-circular orbit evaluated
    at the chief (zero separation). A burn acts on the deputy's own elements: with
    ``x = roe_m / a``, ``rho = a / a_d = 1 / (1 + x_0)``, the deputy's mean motion
    ``n_d = n rho^1.5`` and argument of latitude ``u_d = u + du``, ``du = x_1 - x_5 cot i``
    (``dlambda - dRAAN cos i``), the near-circular GVE in chief-a-scaled ROE read

        d(a dda)  = 2 dv_T / n_d                       (da_d = 2 dv_T / n_d)
        d(a ddl)  = -2 rho dv_R / n_d                  (du_d = -2 dv_R / (n_d a_d); O(di) dropped)
        d(a dde)  = rho / n_d (sin u_d dv_R + 2 cos u_d dv_T, -cos u_d dv_R + 2 sin u_d dv_T)
        d(a ddi)  = rho / n_d (cos u_d, sin u_d sin i / sin i_d) dv_N

    with (dv_R, dv_T, dv_N) in the *deputy's* RTN frame, rotated by ``du`` about N from the
    chief's frame in which burns are commanded. At zero separation this is `control_matrix`.
    The difference is first order in the separation: the da response of a 2.2 m/s burn at
    a dda = -10 km changes by 0.2 % (9 m), the frame rotation mixes dv_R and dv_T by du. Terms of
    order e (chief and deputy eccentricity) are neglected as in `control_matrix`.

    Args:
        chief_oe: (6,) mean chief elements at the burn.
        roe_m: (6,) or (K, 6) pre-burn a-scaled ROE of the deputy [m].

    Returns:
        (6, 3) or (K, 6, 3) [s].
    """
    c = check_oe(chief_oe)
    x = np.asarray(roe_m, dtype=float)
    if x.shape[-1:] != (6,) or x.ndim > 2 or not np.all(np.isfinite(x)):
        raise InputError("roe_m", "must be a finite (6,) or (K, 6) array [m]", x.shape)
    return _control_deputy(float(mean_arg_latitude(c)), mean_motion(c[0]), c[0], c[2], x)


def _control_deputy(lat_rad: float | np.ndarray, n: float, a_m: float, inc_rad: float,
                    roe_m: np.ndarray) -> np.ndarray:
    """`control_matrix_deputy` at chief latitude(s) `lat_rad` (broadcast), (..., 6, 3) [s]."""
    x = roe_m / a_m
    rho = 1.0 / (1.0 + x[..., 0])
    n_d = n * rho**1.5
    du = x[..., 1] - x[..., 5] / np.tan(inc_rad)
    u_d = lat_rad + du
    su, cu = np.sin(u_d), np.cos(u_d)
    b = np.zeros(x.shape[:-1] + (6, 3))
    b[..., 0, 1] = 2.0
    b[..., 1, 0] = -2.0 * rho
    b[..., 2, 0], b[..., 2, 1] = rho * su, 2.0 * rho * cu
    b[..., 3, 0], b[..., 3, 1] = -rho * cu, 2.0 * rho * su
    b[..., 4, 2] = rho * cu
    b[..., 5, 2] = rho * su * np.sin(inc_rad) / np.sin(inc_rad + x[..., 4])
    b /= n_d[..., None, None]
    rot = np.zeros(x.shape[:-1] + (3, 3))  # chief RTN -> deputy RTN
    cd, sd = np.cos(du), np.sin(du)
    rot[..., 0, 0], rot[..., 0, 1], rot[..., 1, 0], rot[..., 1, 1] = cd, sd, -sd, cd
    rot[..., 2, 2] = 1.0
    return b @ rot


def _deputy_burn_jacobian(lat_rad: np.ndarray, n: float, a_m: float, inc_rad: float,
                          roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
    """d(B_d(x) u)/dx, (K, 6, 6) [s/m * m/s = -]: how the burn's ROE change moves with x.

    With ``f = rho / n_d = (1 + x_0)^0.5 / n``, ``g = 1 / n_d = (1 + x_0)^1.5 / n``, the burn in
    the deputy frame ``(v_R, v_T, v_N)`` and ``s = sin i / sin(i + x_4)`` (``x = roe_m / a``),
    ``B_d u = (2 g v_T, -2 f v_R, f (s_d v_R + 2 c_d v_T), f (-c_d v_R + 2 s_d v_T),
    f c_d v_N, f s_d s v_N)`` with ``(c_d, s_d) = (cos, sin)(u + du)``. It depends on x_0
    (through f, g), on ``du = x_1 - x_5 cot i`` (``dv_R/d du = v_T``, ``dv_T/d du = -v_R``) and
    on x_4 (through s).
    """
    x = roe_m / a_m
    u = dv_rtn_mps
    one_x = 1.0 + x[:, 0]
    f = np.sqrt(one_x) / n
    g = one_x**1.5 / n
    du = x[:, 1] - x[:, 5] / np.tan(inc_rad)
    cd, sd = np.cos(du), np.sin(du)
    v_r = cd * u[:, 0] + sd * u[:, 1]
    v_t = -sd * u[:, 0] + cd * u[:, 1]
    v_n = u[:, 2]
    ud = lat_rad + du
    su, cu = np.sin(ud), np.cos(ud)
    sin_ratio = np.sin(inc_rad) / np.sin(inc_rad + x[:, 4])
    dz = np.stack([2 * g * v_t, -2 * f * v_r, f * (su * v_r + 2 * cu * v_t),
                   f * (-cu * v_r + 2 * su * v_t), f * cu * v_n, f * su * sin_ratio * v_n], -1)
    d_x0 = dz / one_x[:, None] * np.array([1.5, 0.5, 0.5, 0.5, 0.5, 0.5])
    d_du = np.stack([-2 * g * v_r, -2 * f * v_t, -f * (cu * v_r + su * v_t),
                     f * (-su * v_r + cu * v_t), -f * su * v_n, f * cu * sin_ratio * v_n], -1)
    jac = np.zeros((x.shape[0], 6, 6))
    jac[:, :, 0] = d_x0
    jac[:, :, 1] = d_du
    jac[:, :, 5] = -d_du / np.tan(inc_rad)
    jac[:, 5, 4] = -dz[:, 5] / np.tan(inc_rad + x[:, 4])
    return jac / a_m


def along_track_curvature_m(a_m: float, da_m: float | np.ndarray,
                            tau_s: float | np.ndarray) -> float | np.ndarray:
    """Second-order Keplerian along-track drift a*dlambda [m] the linear STM leaves out.

    The deputy's mean motion is ``n_d = n (1 + da/a)^-1.5``; the STM keeps its first-order part
    ``-3/2 n da/a``, so over `tau_s` the along-track ROE drifts in addition by
    ``a n tau ((1 + da/a)^-1.5 - 1 + 3/2 da/a) ~ 15/8 n tau da^2 / a`` (175 m per orbit at
    a*da = -10 km, 1.7 m at 1 km).

    Args:
        a_m: chief semi-major axis [m].
        da_m: a-scaled relative semi-major axis a*da [m] (post-burn), any shape.
        tau_s: elapsed time [s], broadcast against `da_m`.
    """
    xi = np.asarray(da_m, float) / a_m
    return a_m * mean_motion(a_m) * np.asarray(tau_s) * ((1.0 + xi) ** -1.5 - 1.0 + 1.5 * xi)


def _curvature_slope(a_m: float, da_m: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
    """d(along_track_curvature_m)/d(da_m) [-]."""
    xi = da_m / a_m
    return mean_motion(a_m) * tau_s * 1.5 * (1.0 - (1.0 + xi) ** -2.5)


@dataclass(frozen=True)
class DeputyLinearization:
    """Jacobians of the deputy-aware dynamics (`Horizon.propagate_nonlinear`) at a reference.

    With the post-burn state ``z_k = x_k + B_d(x_k) u_k`` and ``x_{k+1} = Phi_k z_k +
    c_k(z_k)`` (c: `along_track_curvature_m` on dlambda), to first order about (xbar, ubar):
    ``z_k = e[k] x_k + b[k] u_k - jx[k]`` and ``x_{k+1} = p[k] z_k + (xbar_{k+1} - p[k] zbar_k)``.

    Attributes:
        e: (N, 6, 6) dz/dx = I + d(B_d(x) ubar)/dx [-].
        b: (N, 6, 3) dz/du = B_d(xbar) [s].
        jx: (N, 6) ``d(B_d(x) ubar)/dx @ xbar`` [m] (so that the linear z is exact at xbar).
        p: (N-1, 6, 6) dx_{k+1}/dz_k = Phi_k + dc_k/dz [-].
        z: (N, 6) reference post-burn states zbar [m].
        roe_m: (N, 6) reference pre-burn states xbar [m].
    """

    e: np.ndarray
    b: np.ndarray
    jx: np.ndarray
    p: np.ndarray
    z: np.ndarray
    roe_m: np.ndarray

    @functools.cached_property
    def terminal_sensitivity(self) -> np.ndarray:
        """d z_{N-1} / d u, (6, 3N) [s]: how the final post-burn state moves with the burns."""
        n = self.b.shape[0]
        g = np.empty((n, 6, 3))
        s = self.e[-1]
        g[-1] = self.b[-1]
        for k in range(n - 2, -1, -1):
            s = s @ self.p[k]
            g[k] = s @ self.b[k]
            s = s @ self.e[k]
        return g.transpose(1, 0, 2).reshape(6, 3 * n)


def deputy_post_burn(lat_rad: float, n: float, a_m: float, inc_rad: float,
                     x: list[float], u: list[float]) -> list[float]:
    """`post_burn_batch` for one state in float arithmetic: ``x + B_d(x) u`` written out
    element by element (the single-trajectory propagation's loop, `Horizon.propagate_nonlinear`,
    where numpy's per-call cost would dominate); the same numbers to rounding (tested).

    Args:
        lat_rad: chief mean argument of latitude at the burn [rad].
        n, a_m, inc_rad: chief mean motion [rad/s], semi-major axis [m], inclination [rad].
        x: the six pre-burn a-scaled ROE [m]; u: the three RTN burn components [m/s].
    """
    inv_a = 1.0 / a_m
    one_x = 1.0 + x[0] * inv_a
    f = math.sqrt(one_x) / n
    du = (x[1] - x[5] / math.tan(inc_rad)) * inv_a
    cd, sd = math.cos(du), math.sin(du)
    v_r, v_t = cd * u[0] + sd * u[1], -sd * u[0] + cd * u[1]
    fs, fc = f * math.sin(lat_rad + du), f * math.cos(lat_rad + du)
    sin_ratio = math.sin(inc_rad) / math.sin(inc_rad + x[4] * inv_a)
    return [x[0] + 2.0 * one_x * f * v_t, x[1] - 2.0 * f * v_r,
            x[2] + fs * v_r + 2.0 * fc * v_t, x[3] - fc * v_r + 2.0 * fs * v_t,
            x[4] + fc * u[2], x[5] + fs * sin_ratio * u[2]]


def post_burn_batch(lat_rad: float | np.ndarray, n: float, a_m: float, inc_rad: float,
                    roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
    """The post-burn ROE ``z = x + B_d(x) u`` of the deputy-aware model (B_d:
    `control_matrix_deputy`, at the deputy's own pre-burn state) for states (..., 6) [m] and
    burns (..., 3) [m/s] at chief latitude(s) `lat_rad` [rad] (broadcast against the leading
    axes): (..., 6) [m]. Every array caller's form (SCVx*, the safety model, the rollout);
    `deputy_post_burn` is the same for one state in floats."""
    return post_burn_with(_control_deputy(lat_rad, n, a_m, inc_rad, roe_m), roe_m, dv_rtn_mps)


def post_burn_with(b: np.ndarray, roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
    """`post_burn_batch` with its control matrices B_d(x) (..., 6, 3) [s] already built (the
    linearisation needs them too)."""
    if dv_rtn_mps.ndim == 1:
        return roe_m + b @ dv_rtn_mps
    return roe_m + (b @ dv_rtn_mps[..., None])[..., 0]
