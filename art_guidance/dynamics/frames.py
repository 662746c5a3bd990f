"""The chief's RTN frame: inertial <-> RTN states and the first-order ROE <-> RTN map Psi.

RTN states are ``[r_R, r_T, r_N]`` [m] and ``[v_R, v_T, v_N]`` [m/s] of the deputy relative to
the chief, in the chief's rotating RTN frame.
"""
from __future__ import annotations

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.dynamics.elements import (
    check_oe, eci_from_oe, mean_arg_latitude, mean_motion, oe_from_eci, oe_from_roe, roe_from_oe,
)


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
