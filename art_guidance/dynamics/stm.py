"""The J2 state transition matrix of mean ROE (Koenig, Guffanti, D'Amico 2017) and the control
matrix B of an impulsive burn (near-circular, at zero separation).
"""
from __future__ import annotations

import numpy as np

from art_guidance.dynamics.elements import (
    J2, MU_M3PS2, R_EARTH_M, check_oe, mean_arg_latitude, mean_motion,
)
from art_guidance.errors import InputError


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
