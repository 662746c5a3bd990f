"""Relative orbital dynamics: orbit elements, ROE <-> RTN, J2 ROE STM, control matrix, time grid.

State convention: quasi-nonsingular ROE scaled by the chief semi-major axis, metres:
``roe_m = a * [da, dlambda, dex, dey, dix, diy]``. RTN states are ``[r_R, r_T, r_N]`` [m] and
``[v_R, v_T, v_N]`` [m/s] of the deputy relative to the chief, expressed in the rotating chief
RTN frame. Orbit elements are ``(a [m], e, i, raan, argp, M)`` with angles in radians.

Mean/osculating: the STM and B propagate *mean* ROE (Koenig, Guffanti, D'Amico 2017); the exact
conversions here treat the elements they are given as osculating Keplerian elements.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.errors import InputError

MU_M3PS2 = 3.986004415e14
R_EARTH_M = 6378136.3
J2 = 1.082635819197e-3


# --------------------------------------------------------------------------- orbit elements
def check_oe(oe: object, field: str = "chief_oe") -> np.ndarray:
    """Validate orbit elements (a [m], e, i, raan, argp, M [rad]); return a (6,) array."""
    arr = as_finite_array(field, oe, (6,))
    if arr[0] <= 0:
        raise InputError(field, "semi-major axis must be positive [m]", arr[0])
    if arr[0] < R_EARTH_M:
        raise InputError(field, "semi-major axis is below the Earth's radius [m]", arr[0])
    if not 0.0 <= arr[1] < 1.0:
        raise InputError(field, "eccentricity must be in [0, 1)", arr[1])
    return arr


def mean_motion(a_m: float) -> float:
    """Keplerian mean motion [rad/s] for semi-major axis `a_m` [m]."""
    return float(np.sqrt(MU_M3PS2 / a_m**3))


def orbital_period_s(a_m: float) -> float:
    """Keplerian period [s]."""
    return 2.0 * np.pi / mean_motion(a_m)


def j2_secular_rates(oe: np.ndarray) -> tuple[float, float, float]:
    """Mean J2 secular rates (raan_dot, argp_dot, M_dot) [rad/s] for mean elements `oe`."""
    a, e, i = oe[0], oe[1], oe[2]
    eta = np.sqrt(1.0 - e * e)
    kappa = 0.75 * J2 * R_EARTH_M**2 * np.sqrt(MU_M3PS2) / (a**3.5 * eta**4)
    cos_i = np.cos(i)
    raan_dot = -2.0 * kappa * cos_i
    argp_dot = kappa * (5.0 * cos_i**2 - 1.0)
    m_dot = mean_motion(a) + kappa * eta * (3.0 * cos_i**2 - 1.0)
    return float(raan_dot), float(argp_dot), float(m_dot)


def propagate_mean_oe(oe: object, tau_s: float | np.ndarray) -> np.ndarray:
    """Propagate mean elements by `tau_s` [s] with the J2 secular rates: (6,) or (K, 6)."""
    oe = check_oe(oe)
    raan_dot, argp_dot, m_dot = j2_secular_rates(oe)
    tau = np.asarray(tau_s, dtype=float)
    out = np.broadcast_to(oe, tau.shape + (6,)).copy()
    out[..., 3] = oe[3] + raan_dot * tau
    out[..., 4] = oe[4] + argp_dot * tau
    out[..., 5] = oe[5] + m_dot * tau
    return out


def mean_arg_latitude(oe: np.ndarray) -> np.ndarray:
    """Mean argument of latitude u = argp + M [rad] of (..., 6) elements."""
    return oe[..., 4] + oe[..., 5]


# --------------------------------------------------------------------------- ROE <-> OE
def roe_from_oe(chief_oe: object, deputy_oe: object) -> np.ndarray:
    """Exact a-scaled quasi-nonsingular ROE [m], shape (6,), from chief and deputy elements."""
    c = check_oe(chief_oe)
    d = check_oe(deputy_oe, "deputy_oe")
    a, e, i, raan, w, m = c
    ad, ed, idp, raand, wd, md = d
    draan = _wrap(raand - raan)
    dlam = _wrap((wd + md) - (w + m)) + draan * np.cos(i)
    return a * np.array([
        (ad - a) / a,
        dlam,
        ed * np.cos(wd) - e * np.cos(w),
        ed * np.sin(wd) - e * np.sin(w),
        idp - i,
        draan * np.sin(i),
    ])


def oe_from_roe(chief_oe: object, roe_m: object) -> np.ndarray:
    """Deputy elements (6,) from chief elements and a-scaled ROE [m] (exact inverse)."""
    c = check_oe(chief_oe)
    x = as_finite_array("roe_m", roe_m, (6,)) / c[0]
    a, e, i, raan, w, m = c
    if abs(np.sin(i)) < 1e-9:
        raise InputError("chief_oe", "ROE inclination vector is singular for equatorial orbits")
    ad = a * (1.0 + x[0])
    exd = e * np.cos(w) + x[2]
    eyd = e * np.sin(w) + x[3]
    ed = float(np.hypot(exd, eyd))
    wd = float(np.arctan2(eyd, exd)) if ed > 0 else 0.0
    idp = i + x[4]
    draan = x[5] / np.sin(i)
    ud = (w + m) + x[1] - draan * np.cos(i)
    deputy = np.array([ad, ed, idp, raan + draan, wd, ud - wd])
    return check_oe(deputy, "deputy_oe")


def _wrap(angle: float | np.ndarray) -> float | np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


# --------------------------------------------------------------------------- inertial states
def solve_kepler(m_rad: float, e: float, tol: float = 1e-14) -> float:
    """Eccentric anomaly [rad] from mean anomaly by Newton iteration."""
    ecc = m_rad if e < 0.8 else np.pi
    for _ in range(50):
        step = (ecc - e * np.sin(ecc) - m_rad) / (1.0 - e * np.cos(ecc))
        ecc -= step
        if abs(step) < tol:
            break
    return float(ecc)


def eci_from_oe(oe: object) -> np.ndarray:
    """Inertial position [m] and velocity [m/s], shape (6,), from Keplerian elements."""
    a, e, i, raan, w, m = check_oe(oe, "oe")
    ecc = solve_kepler(float(_wrap(m)), e)
    nu = 2.0 * np.arctan2(np.sqrt(1 + e) * np.sin(ecc / 2), np.sqrt(1 - e) * np.cos(ecc / 2))
    p = a * (1 - e * e)
    r = p / (1 + e * np.cos(nu))
    r_pf = np.array([r * np.cos(nu), r * np.sin(nu), 0.0])
    v_pf = np.sqrt(MU_M3PS2 / p) * np.array([-np.sin(nu), e + np.cos(nu), 0.0])
    rot = _rot3(-raan) @ _rot1(-i) @ _rot3(-w)
    return np.concatenate([rot @ r_pf, rot @ v_pf])


def oe_from_eci(state: object) -> np.ndarray:
    """Keplerian elements (6,) from an inertial state [m, m/s] (non-equatorial, elliptic)."""
    s = as_finite_array("eci_state", state, (6,))
    r, v = s[:3], s[3:]
    rn = np.linalg.norm(r)
    h = np.cross(r, v)
    hn = np.linalg.norm(h)
    node = np.cross([0.0, 0.0, 1.0], h)
    e_vec = np.cross(v, h) / MU_M3PS2 - r / rn
    e = float(np.linalg.norm(e_vec))
    energy = 0.5 * v @ v - MU_M3PS2 / rn
    if energy >= 0 or hn == 0:
        raise InputError("eci_state", "state is not on a closed orbit")
    if not np.linalg.norm(node) > 1e-12 * hn:
        raise InputError("eci_state", "equatorial orbit: node and RAAN are undefined")
    a = -MU_M3PS2 / (2.0 * energy)
    i = float(np.arccos(np.clip(h[2] / hn, -1, 1)))
    raan = float(np.arctan2(node[1], node[0]))
    node_hat = node / np.linalg.norm(node)
    # argument of latitude of the position (true), robust for small e
    u_true = float(np.arctan2(r @ np.cross(h / hn, node_hat), r @ node_hat))
    w = float(np.arctan2(e_vec @ np.cross(h / hn, node_hat), e_vec @ node_hat))
    nu = u_true - w
    ecc = 2.0 * np.arctan2(np.sqrt(1 - e) * np.sin(nu / 2), np.sqrt(1 + e) * np.cos(nu / 2))
    m = ecc - e * np.sin(ecc)
    return np.array([a, e, i, raan % (2 * np.pi), w % (2 * np.pi), m % (2 * np.pi)])


def _rot1(ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])


def _rot3(ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def rtn_frame(chief_eci: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTN basis as columns of a (3, 3) matrix and its angular velocity in RTN [rad/s]."""
    r, v = chief_eci[:3], chief_eci[3:]
    r_hat = r / np.linalg.norm(r)
    h = np.cross(r, v)
    n_hat = h / np.linalg.norm(h)
    t_hat = np.cross(n_hat, r_hat)
    omega_rtn = np.array([0.0, 0.0, np.linalg.norm(h) / (r @ r)])
    return np.column_stack([r_hat, t_hat, n_hat]), omega_rtn


def rtn_from_eci(chief_eci: object, deputy_eci: object) -> np.ndarray:
    """Exact relative RTN state [m, m/s] of the deputy in the rotating chief frame, (6,)."""
    c = as_finite_array("chief_eci", chief_eci, (6,))
    d = as_finite_array("deputy_eci", deputy_eci, (6,))
    basis, omega = rtn_frame(c)
    dr = basis.T @ (d[:3] - c[:3])
    dv = basis.T @ (d[3:] - c[3:]) - np.cross(omega, dr)
    return np.concatenate([dr, dv])


def eci_from_rtn(chief_eci: object, rtn: object) -> np.ndarray:
    """Deputy inertial state (6,) from the chief's inertial state and a relative RTN state."""
    c = as_finite_array("chief_eci", chief_eci, (6,))
    x = as_finite_array("rtn", rtn, (6,))
    basis, omega = rtn_frame(c)
    r = c[:3] + basis @ x[:3]
    v = c[3:] + basis @ (x[3:] + np.cross(omega, x[:3]))
    return np.concatenate([r, v])


# --------------------------------------------------------------------------- ROE <-> RTN
def psi_matrix(chief_oe: object) -> np.ndarray:
    """First-order ROE -> RTN map Psi(u), (6, 6): rtn [m, m/s] = Psi @ roe_m (near-circular)."""
    c = check_oe(chief_oe)
    return psi_from_latitude(float(mean_arg_latitude(c)), mean_motion(c[0]))


def psi_from_latitude(u: float | np.ndarray, n: float) -> np.ndarray:
    """Psi at mean argument(s) of latitude `u`: (6, 6), or (..., 6, 6) for an array."""
    su, cu = np.sin(u), np.cos(u)
    out = np.zeros(np.shape(u) + (6, 6))
    out[..., 0, 0] = out[..., 1, 1] = 1.0
    out[..., 0, 2], out[..., 0, 3] = -cu, -su
    out[..., 1, 2], out[..., 1, 3] = 2 * su, -2 * cu
    out[..., 2, 4], out[..., 2, 5] = su, -cu
    out[..., 3, 2], out[..., 3, 3] = n * su, -n * cu
    out[..., 4, 0] = -1.5 * n
    out[..., 4, 2], out[..., 4, 3] = 2 * n * cu, 2 * n * su
    out[..., 5, 4], out[..., 5, 5] = n * cu, n * su
    return out


def rtn_from_roe_linear(chief_oe: object, roe_m: object) -> np.ndarray:
    """Relative RTN state (6,) [m, m/s] from a-scaled ROE [m] by the first-order map."""
    return psi_matrix(chief_oe) @ as_finite_array("roe_m", roe_m, (6,))


def roe_from_rtn_linear(chief_oe: object, rtn: object) -> np.ndarray:
    """A-scaled ROE [m] (6,) from a relative RTN state by inverting the first-order map."""
    return np.linalg.solve(psi_matrix(chief_oe), as_finite_array("rtn", rtn, (6,)))


def rtn_from_roe_exact(chief_oe: object, roe_m: object) -> np.ndarray:
    """Relative RTN state (6,) from ROE through inertial states (exact, osculating Kepler)."""
    deputy = oe_from_roe(chief_oe, roe_m)
    return rtn_from_eci(eci_from_oe(chief_oe), eci_from_oe(deputy))


def roe_from_rtn_exact(chief_oe: object, rtn: object) -> np.ndarray:
    """A-scaled ROE (6,) from a relative RTN state through inertial states (exact)."""
    chief_eci = eci_from_oe(chief_oe)
    deputy = oe_from_eci(eci_from_rtn(chief_eci, rtn))
    return roe_from_oe(chief_oe, deputy)


# --------------------------------------------------------------------------- STM and B
def stm_basis(wdot_rad_s: float | np.ndarray, tau_s: float | np.ndarray,
              order: int = 0, axis: int = -1) -> np.ndarray:
    """Time functions of the J2 STM, ``s(tau) = (1, tau, c, s, tau c, tau s)``, or a derivative.

    ``c = cos(wdot tau)``, ``s = sin(wdot tau)`` with wdot the perigee rate [rad/s];
    ``Phi(t0 + tau, t0) = sum_b s_b(tau) terms[b]`` (`stm_j2_terms`).

    Args:
        wdot_rad_s: perigee rate [rad/s], broadcast against `tau_s`.
        tau_s: elapsed time [s], any shape (...).
        order: 0, 1 or 2: the value or its first/second derivative with respect to tau.
        axis: where the function index goes (-1: (..., 6); 0: (6, ...)).

    Returns:
        (..., 6) [-, s, -, -, s, s] divided by s^order.
    """
    out = stm_basis_orders(wdot_rad_s, tau_s, (order,))[0]
    return out if axis in (-1, out.ndim - 1) else np.ascontiguousarray(np.moveaxis(out, -1, axis))


def stm_basis_orders(wdot_rad_s: float | np.ndarray, tau_s: float | np.ndarray,
                     orders: tuple[int, ...]) -> list[np.ndarray]:
    """`stm_basis` for several derivative orders (each (..., 6)), with one cos/sin evaluation.

    Raises:
        InputError: an order other than 0, 1 or 2.
    """
    for order in orders:
        if order not in (0, 1, 2):
            raise InputError("order", "must be 0, 1 or 2", order)
    w, tau = np.asarray(wdot_rad_s, float), np.asarray(tau_s, float)
    shape = np.broadcast_shapes(w.shape, tau.shape)
    c, s = np.cos(w * tau), np.sin(w * tau)
    outs = []
    for order in orders:
        if order == 0:
            cols = (1.0, tau, c, s, tau * c, tau * s)
        elif order == 1:
            cols = (0.0, 1.0, -w * s, w * c, c - w * tau * s, s + w * tau * c)
        else:
            cols = (0.0, 0.0, -w * w * c, -w * w * s, -2 * w * s - w * w * tau * c,
                    2 * w * c - w * w * tau * s)
        out = np.empty(shape + (6,))  # filled column by column (broadcast): no temporaries
        for k, col in enumerate(cols):
            out[..., k] = col
        outs.append(out)
    return outs


def stm_j2_terms(chief_oe: object) -> tuple[np.ndarray, float]:
    """Constant matrices of the J2 ROE STM: ``Phi(t0 + tau, t0) = sum_b s_b(tau) terms[b]``.

    With ``c = cos(wdot tau)``, ``s = sin(wdot tau)`` and the final eccentricity vector
    ``(exf, eyf) = (exi c - eyi s, eyi c + exi s)``, every entry of the STM of docs/design.md is a
    combination of the six time functions of `stm_basis`, so this decomposition is exact.

    Args:
        chief_oe: (6,) mean chief elements at t0.

    Returns:
        terms (6, 6, 6) [basis b, row, col] (units 1/s^k for the tau^k functions) and the
        perigee rate wdot [rad/s].
    """
    c = check_oe(chief_oe)
    a, e, i, _, w, _ = c
    n = mean_motion(a)
    eta = np.sqrt(1.0 - e * e)
    kappa = 0.75 * J2 * R_EARTH_M**2 * np.sqrt(MU_M3PS2) / (a**3.5 * eta**4)
    big_e, big_f, big_g = 1.0 + eta, 4.0 + 3.0 * eta, 1.0 / eta**2
    cos_i = np.cos(i)
    big_p, big_q = 3 * cos_i**2 - 1, 5 * cos_i**2 - 1
    big_s, big_t = np.sin(2 * i), np.sin(i) ** 2
    ex, ey = e * np.cos(w), e * np.sin(w)
    kq, kgq = kappa * big_q, 4 * kappa * big_g * big_q
    one, tau, cos_, sin_, tcos, tsin = range(6)
    t = np.zeros((6, 6, 6))
    t[one, 0, 0] = t[one, 1, 1] = t[one, 4, 4] = t[one, 5, 5] = 1.0
    t[tau, 1, 0] = -(3.5 * kappa * big_e * big_p + 1.5 * n)
    t[tau, 1, 2] = kappa * ex * big_f * big_g * big_p
    t[tau, 1, 3] = kappa * ey * big_f * big_g * big_p
    t[tau, 1, 4] = -kappa * big_f * big_s
    t[tau, 5, 0] = 3.5 * kappa * big_s
    t[tau, 5, 2] = -4 * kappa * ex * big_g * big_s
    t[tau, 5, 3] = -4 * kappa * ey * big_g * big_s
    t[tau, 5, 4] = 2 * kappa * big_t
    t[cos_, 2, 2] = t[cos_, 3, 3] = 1.0
    t[sin_, 2, 3], t[sin_, 3, 2] = -1.0, 1.0
    # rows 2 and 3 multiply eyf = ey c + ex s and exf = ex c - ey s respectively
    for f_row, (fc, fs) in ((2, (ey, ex)), (3, (ex, -ey))):
        sign = 1.0 if f_row == 2 else -1.0
        for basis, f in ((tcos, fc), (tsin, fs)):
            t[basis, f_row, 0] = sign * 3.5 * kq * f
            t[basis, f_row, 2] = -sign * kgq * ex * f
            t[basis, f_row, 3] = -sign * kgq * ey * f
            t[basis, f_row, 4] = sign * 5 * kappa * big_s * f
    return t, float(kappa * big_q)


def stm_j2(chief_oe: object, tau_s: float | np.ndarray) -> np.ndarray:
    """J2 ROE state transition matrix Phi(t0 + tau, t0) for mean chief elements at t0.

    Args:
        chief_oe: (6,) mean chief elements at t0.
        tau_s: elapsed time [s], a scalar or an array of shape (...).

    Returns:
        (6, 6) for a scalar `tau_s`, else (..., 6, 6).
    """
    terms, wdot = stm_j2_terms(chief_oe)
    return np.einsum("...b,bij->...ij", stm_basis(wdot, tau_s), terms)


def control_matrix(chief_oe: object) -> np.ndarray:
    """Impulsive control matrix B(u), (6, 3) [s]: d(roe_m) = B @ dv_rtn_mps (near-circular)."""
    c = check_oe(chief_oe)
    return _control(float(mean_arg_latitude(c)), mean_motion(c[0]))


def _control(u: float, n: float) -> np.ndarray:
    su, cu = np.sin(u), np.cos(u)
    return np.array([
        [0.0, 2.0, 0.0],
        [-2.0, 0.0, 0.0],
        [su, 2 * cu, 0.0],
        [-cu, 2 * su, 0.0],
        [0.0, 0.0, cu],
        [0.0, 0.0, su],
    ]) / n


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


def _deputy_post_burn(lat_rad: float, n: float, a_m: float, inc_rad: float,
                      x: list[float], u: list[float]) -> list[float]:
    """``x + _control_deputy(...) @ u`` for one state, in float arithmetic (the rollout's loop)."""
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
    state, second-order along-track drift) and its Jacobians (`linearize_nonlinear`).

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

    def final_post_burn(self, roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
        """Post-burn ROE at the last node: x_N + B_N u_N, (6,)."""
        return roe_m[-1] + self.b[-1] @ dv_rtn_mps[-1]

    # -------------------------------------------------------------- deputy-aware model
    # `propagate` is the linear model of the convex problem (B at zero separation, first-order
    # relative drift). SCVx* plans with the model below, evaluated along its reference: every
    # burn acts through `control_matrix_deputy` at the deputy's own pre-burn state, and every
    # coast adds the second-order Keplerian along-track drift `along_track_curvature_m`.
    def _deputy_constants(self) -> tuple[np.ndarray, float, float, float]:
        a, inc = float(self.chief_oe[0, 0]), float(self.chief_oe[0, 2])
        return mean_arg_latitude(self.chief_oe), mean_motion(a), a, inc

    def b_deputy(self, roe_m: object) -> np.ndarray:
        """Deputy-aware control matrices at the pre-burn states (N, 6) [m]: (N, 6, 3) [s]."""
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        lat, n, a, inc = self._deputy_constants()
        return _control_deputy(lat, n, a, inc, x)

    def post_burn_nonlinear(self, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn ROE ``z_k = x_k + B_d(x_k) u_k`` at every node, (N, 6) [m]."""
        x = as_finite_array("roe_m", roe_m, (self.n_nodes, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3))
        return x + (self.b_deputy(x) @ u[:, :, None])[:, :, 0]

    def post_burn_nonlinear_at(self, node: int, roe_m: object, dv_rtn_mps: object) -> np.ndarray:
        """Post-burn ROE of B candidate (state (B, 6) [m], burn (B, 3) [m/s]) pairs at a node."""
        x = as_finite_array("roe_m", roe_m, (None, 6))
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (x.shape[0], 3))
        lat, n, a, inc = self._deputy_constants()
        return x + (_control_deputy(lat[int(node)], n, a, inc, x) @ u[:, :, None])[:, :, 0]

    def final_post_burn_nonlinear(self, roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
        """Post-burn ROE at the last node with the deputy-aware B, (6,) [m]."""
        lat, n, a, inc = self._deputy_constants()
        x = np.asarray(roe_m, float)[-1]
        return x + _control_deputy(lat[-1], n, a, inc, x) @ np.asarray(dv_rtn_mps, float)[-1]

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
        u = as_finite_array("dv_rtn_mps", dv_rtn_mps, (self.n_nodes, 3)).tolist()
        lat, n, a, inc = self._deputy_constants()
        lat = lat.tolist()
        stm = self._stm_rows
        curv = (a * n * np.diff(self.epochs_s)).tolist()  # (N-1,) [m]
        out = [x0.tolist()]
        x = out[0]
        for k in range(self.n_nodes - 1):
            z = _deputy_post_burn(lat[k], n, a, inc, x, u[k]) if any(u[k]) else x
            x = [r[0] * z[0] + r[1] * z[1] + r[2] * z[2] + r[3] * z[3] + r[4] * z[4]
                 + r[5] * z[5] for r in stm[k]]
            xi = z[0] / a
            x[1] += curv[k] * ((1.0 + xi) ** -1.5 - 1.0 + 1.5 * xi)
            out.append(x)
        return np.array(out)

    def step_nonlinear(self, node: int, roe_m: np.ndarray, dv_rtn_mps: np.ndarray) -> np.ndarray:
        """One step of `propagate_nonlinear` for a batch: pre-burn states at `node` (B, 6) [m]
        and burns (B, 3) [m/s] -> pre-burn states at `node + 1` (B, 6) [m].

        The batched form the ART rollout advances with, so that a rollout driven by a plan's
        own controls reproduces the plan's states (inputs are not validated: the caller's
        arrays are finite by construction).
        """
        lat, n, a, inc = self._deputy_constants()
        k = int(node)
        z = roe_m + (_control_deputy(lat[k], n, a, inc, roe_m) @ dv_rtn_mps[:, :, None])[:, :, 0]
        x1 = z @ self.stm[k].T  # (B, 6)
        x1[:, 1] += along_track_curvature_m(a, z[:, 0], self.epochs_s[k + 1] - self.epochs_s[k])
        return x1

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
        z = x + (b @ u[:, :, None])[:, :, 0]
        e = jac + np.eye(6)
        p = self.stm.copy()
        p[:, 1, 0] += _curvature_slope(a, z[:-1, 0], np.diff(self.epochs_s))
        return DeputyLinearization(e, b, (jac @ x[:, :, None])[:, :, 0], p, z, x)

    def to_rtn(self, roe_m: np.ndarray) -> np.ndarray:
        """(N, 6) ROE [m] -> (N, 6) RTN [m, m/s] by the first-order map at each node."""
        return np.einsum("kij,kj->ki", self.psi, roe_m)
