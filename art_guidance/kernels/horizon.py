"""Compiled form of `dynamics.horizon.Horizon.propagate_nonlinear` (and of the one-state
post-burn map `dynamics.deputy.deputy_post_burn` it applies): the same floating-point
operations in the same order as the float-arithmetic oracle, in one compiled call per
trajectory (tested bit for bit). Imports only numpy and numba."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True)


@njit(**_JIT)
def deputy_post_burn(lat, n, a, inc, x, u, out):
    """`dynamics.deputy.deputy_post_burn` into `out` (6,)."""
    inv_a = 1.0 / a
    one_x = 1.0 + x[0] * inv_a
    f = math.sqrt(one_x) / n
    du = (x[1] - x[5] / math.tan(inc)) * inv_a
    cd, sd = math.cos(du), math.sin(du)
    v_r, v_t = cd * u[0] + sd * u[1], -sd * u[0] + cd * u[1]
    fs, fc = f * math.sin(lat + du), f * math.cos(lat + du)
    sin_ratio = math.sin(inc) / math.sin(inc + x[4] * inv_a)
    out[0] = x[0] + 2.0 * one_x * f * v_t
    out[1] = x[1] - 2.0 * f * v_r
    out[2] = x[2] + fs * v_r + 2.0 * fc * v_t
    out[3] = x[3] - fc * v_r + 2.0 * fs * v_t
    out[4] = x[4] + fc * u[2]
    out[5] = x[5] + fs * sin_ratio * u[2]


@njit(**_JIT)
def propagate_nonlinear(x0, u, lat, n, a, inc, stm, curv):
    """(N, 6) pre-burn ROE [m] of ``x_{k+1} = Phi_k z_k + c_k(z_k)`` from `x0` (6,) [m] with
    burns `u` (N, 3) [m/s]; `lat` (N,) chief latitude [rad], `stm` (N - 1, 6, 6), `curv`
    (N - 1,) the along-track curvature factor a n dt [m]."""
    n_nodes = u.shape[0]
    out = np.empty((n_nodes, 6))
    out[0] = x0
    z = np.empty(6)
    for k in range(n_nodes - 1):
        x = out[k]
        if u[k, 0] != 0.0 or u[k, 1] != 0.0 or u[k, 2] != 0.0:
            deputy_post_burn(lat[k], n, a, inc, x, u[k], z)
        else:
            z[:] = x
        for r in range(6):
            out[k + 1, r] = (stm[k, r, 0] * z[0] + stm[k, r, 1] * z[1] + stm[k, r, 2] * z[2]
                             + stm[k, r, 3] * z[3] + stm[k, r, 4] * z[4]
                             + stm[k, r, 5] * z[5])
        xi = z[0] / a
        out[k + 1, 1] += curv[k] * ((1.0 + xi) ** -1.5 - 1.0 + 1.5 * xi)
    return out


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the doors pass."""
    u = np.zeros((3, 3))
    u[0, 0] = 1e-3
    propagate_nonlinear(np.zeros(6), u, np.zeros(3), 1e-3, 7e6, 1.0, np.zeros((2, 6, 6)),
                        np.zeros(2))
