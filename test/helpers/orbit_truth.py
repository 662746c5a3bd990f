"""Independent nonlinear truth for tests: two-body + J2 integration and mean/osculating elements.

Nothing here reuses a formula of `art_guidance` (constants typed in from docs/design.md): the
acceleration, Kepler <-> Cartesian conversions, the ROE definition, the RTN frame and the orbit
averaging follow `test_dynamics_truth.py`, vectorised over many bodies.

Mean elements are orbit averages: every body's osculating nonsingular elements (a, e cos w,
e sin w, i, RAAN, u = w + M, angles unwrapped) averaged over one of its *own* Keplerian periods
centred on the epoch (the definition `test_dynamics_truth.py` validates the STM against). The
average is the exact integral of a cubic spline through a dense grid of the integrated states
(257 points over 1.1 periods, error < 1 mm in a). `osculating_from_mean` inverts it by fixed-point
iteration ``osc += mean_target - average(osc)`` (the map is the identity up to O(J2) terms, so
each iteration gains ~3 digits).
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

MU = 3.986004415e14
R_E = 6378136.3
J2 = 1.082635819197e-3
RTOL = 1e-11
ATOL = 1e-7          # [m], [m/s]: relative states are differences of 7e6 m vectors
GRID = 257           # samples of the averaging window (spline error < 1 mm in a)


# --------------------------------------------------------------------------- dynamics
def accel(pos: np.ndarray) -> np.ndarray:
    """Two-body + J2 acceleration [m/s^2] for inertial positions (..., 3) [m]."""
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    r2 = x * x + y * y + z * z
    r = np.sqrt(r2)
    k = -MU / (r2 * r)
    f = 1.5 * J2 * R_E * R_E / r2
    zz = 5.0 * z * z / r2
    return np.stack([k * x * (1.0 + f * (1.0 - zz)), k * y * (1.0 + f * (1.0 - zz)),
                     k * z * (1.0 + f * (3.0 - zz))], axis=-1)


def _rhs(_t: float, y: np.ndarray) -> np.ndarray:
    s = y.reshape(-1, 6)
    return np.concatenate([s[:, 3:], accel(s[:, :3])], axis=1).ravel()


def integrate(states0: np.ndarray, t_end: float):
    """Integrate (B, 6) inertial states from 0 to t_end (either sign); dense OdeSolution."""
    sol = solve_ivp(_rhs, (0.0, t_end), np.asarray(states0, float).ravel(), method="DOP853",
                    rtol=RTOL, atol=ATOL, dense_output=True)
    assert sol.success, sol.message
    return sol.sol


# --------------------------------------------------------------------------- elements
def cart_from_kep(oe: np.ndarray) -> np.ndarray:
    """Inertial states (..., 6) from Keplerian elements (..., 6) (a, e, i, RAAN, w, M)."""
    a, e, i, raan, w, m = np.moveaxis(np.asarray(oe, float), -1, 0)
    ecc = np.array(m, dtype=float, copy=True)
    for _ in range(30):
        ecc = ecc - (ecc - e * np.sin(ecc) - m) / (1.0 - e * np.cos(ecc))
    eta = np.sqrt(1.0 - e * e)
    co, so, cw, sw, ci, si = np.cos(raan), np.sin(raan), np.cos(w), np.sin(w), np.cos(i), np.sin(i)
    p_hat = np.stack([co * cw - so * sw * ci, so * cw + co * sw * ci, sw * si], -1)
    q_hat = np.stack([-co * sw - so * cw * ci, -so * sw + co * cw * ci, cw * si], -1)
    r = a * (1.0 - e * np.cos(ecc))
    xp, yp = a * (np.cos(ecc) - e), a * eta * np.sin(ecc)
    vp, vq = -np.sqrt(MU * a) / r * np.sin(ecc), np.sqrt(MU * a) / r * eta * np.cos(ecc)
    return np.concatenate([xp[..., None] * p_hat + yp[..., None] * q_hat,
                           vp[..., None] * p_hat + vq[..., None] * q_hat], -1)


def nonsingular_from_cart(state: np.ndarray) -> np.ndarray:
    """Osculating (a, e cos w, e sin w, i, RAAN, u = w + M) (..., 6) of inertial states."""
    s = np.asarray(state, float)
    r, v = s[..., :3], s[..., 3:]
    rn = np.linalg.norm(r, axis=-1)
    v2 = np.sum(v * v, -1)
    rv = np.sum(r * v, -1)
    h = np.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    a = 1.0 / (2.0 / rn - v2 / MU)
    i = np.arccos(h[..., 2] / hn)
    raan = np.arctan2(h[..., 0], -h[..., 1])
    e_vec = ((v2 - MU / rn)[..., None] * r - rv[..., None] * v) / MU
    node = np.stack([np.cos(raan), np.sin(raan), np.zeros_like(raan)], -1)
    m_hat = np.cross(h / hn[..., None], node)
    ex, ey = np.sum(e_vec * node, -1), np.sum(e_vec * m_hat, -1)
    ecc = np.arctan2(rv / np.sqrt(MU * a), 1.0 - rn / a)
    m = ecc - rv / np.sqrt(MU * a)
    return np.stack([a, ex, ey, i, raan, np.arctan2(ey, ex) + m], -1)


def kep_from_nonsingular(ns: np.ndarray) -> np.ndarray:
    """(a, e, i, RAAN, w, M) from (a, ex, ey, i, RAAN, u)."""
    a, ex, ey, i, raan, u = np.moveaxis(np.asarray(ns, float), -1, 0)
    w = np.arctan2(ey, ex)
    return np.stack([a, np.hypot(ex, ey), i, raan, w, u - w], -1)


def nonsingular_from_kep(oe: np.ndarray) -> np.ndarray:
    """(a, ex, ey, i, RAAN, u) from (a, e, i, RAAN, w, M)."""
    a, e, i, raan, w, m = np.moveaxis(np.asarray(oe, float), -1, 0)
    return np.stack([a, e * np.cos(w), e * np.sin(w), i, raan, w + m], -1)


def wrap(x: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(x) + np.pi) % (2.0 * np.pi) - np.pi


def roe(chief: np.ndarray, deputy: np.ndarray) -> np.ndarray:
    """a-scaled quasi-nonsingular ROE [m] (..., 6) from Keplerian elements (docs/design.md)."""
    a, e, i, raan, w, m = np.moveaxis(np.asarray(chief, float), -1, 0)
    ad, ed, idp, raand, wd, md = np.moveaxis(np.asarray(deputy, float), -1, 0)
    draan = wrap(raand - raan)
    return a[..., None] * np.stack([
        (ad - a) / a, wrap(wd + md - w - m) + draan * np.cos(i),
        ed * np.cos(wd) - e * np.cos(w), ed * np.sin(wd) - e * np.sin(w),
        idp - i, draan * np.sin(i)], -1)


def deputy_from_roe(chief: np.ndarray, roe_m: np.ndarray) -> np.ndarray:
    """Deputy Keplerian elements (..., 6) from chief elements (..., 6) and ROE [m] (inverse)."""
    a, e, i, raan, w, m = np.moveaxis(np.asarray(chief, float), -1, 0)
    x = np.asarray(roe_m, float) / a[..., None]
    exd, eyd = e * np.cos(w) + x[..., 2], e * np.sin(w) + x[..., 3]
    wd = np.arctan2(eyd, exd)
    draan = x[..., 5] / np.sin(i)
    ud = w + m + x[..., 1] - draan * np.cos(i)
    return np.stack([a * (1.0 + x[..., 0]), np.hypot(exd, eyd), i + x[..., 4], raan + draan,
                     wd, ud - wd], -1)


def rtn_basis(chief_state: np.ndarray) -> np.ndarray:
    """Columns R, T, N of the chief's RTN frame, (3, 3), from one (6,) ECI state."""
    r, v = chief_state[:3], chief_state[3:]
    r_hat = r / np.linalg.norm(r)
    n_hat = np.cross(r, v)
    n_hat /= np.linalg.norm(n_hat)
    return np.column_stack([r_hat, np.cross(n_hat, r_hat), n_hat])


def rtn_position(chief_state: np.ndarray, deputy_state: np.ndarray) -> np.ndarray:
    """Deputy position relative to the chief in the chief's RTN axes [m], (..., 3)."""
    r, v = chief_state[..., :3], chief_state[..., 3:]
    r_hat = r / np.linalg.norm(r, axis=-1, keepdims=True)
    n_hat = np.cross(r, v)
    n_hat /= np.linalg.norm(n_hat, axis=-1, keepdims=True)
    t_hat = np.cross(n_hat, r_hat)
    dr = deputy_state[..., :3] - r
    return np.stack([np.sum(dr * r_hat, -1), np.sum(dr * t_hat, -1), np.sum(dr * n_hat, -1)],
                    -1)


def sphere_clearance_m(chief: np.ndarray, deputy: np.ndarray, duration_s: float,
                       radius_m: float, step_s: float) -> float:
    """Smallest |r| - radius [m] of the free drift of (6,) inertial chief and deputy states over
    [0, duration_s]: this module's DOP853 truth sampled every `step_s`, refined by a parabola
    at the sampled minimum (the fault checks' independent reference)."""
    sol = integrate(np.vstack([chief, deputy]), duration_s)
    t = np.linspace(0.0, duration_s, int(duration_s / step_s) + 1)
    y = sol(t).reshape(2, 6, -1).transpose(2, 0, 1)  # (S, 2, 6)
    r = np.linalg.norm(rtn_position(y[:, 0], y[:, 1]), axis=1) - radius_m
    j = int(np.clip(np.argmin(r), 1, r.size - 2))
    curv = r[j - 1] - 2 * r[j] + r[j + 1]
    return float(r[j] - (r[j - 1] - r[j + 1]) ** 2 / (8 * curv)) if curv > 0 else float(r.min())


# --------------------------------------------------------------------------- mean elements
def _period(a: np.ndarray) -> np.ndarray:
    return 2.0 * np.pi * np.sqrt(np.asarray(a) ** 3 / MU)


def orbit_mean(ns_osc: np.ndarray) -> np.ndarray:
    """Own-period orbit averages (B, 6) of bodies with osculating nonsingular elements at t = 0.

    Integrates every body over +-0.55 of the longest period and returns the averages of
    (a, ex, ey, i, RAAN, u) over [-P_j/2, P_j/2], P_j the Kepler period of its own averaged a
    (3 updates), as exact integrals of per-body cubic splines through GRID samples.
    """
    ns = np.asarray(ns_osc, float)
    b = ns.shape[0]
    states = cart_from_kep(kep_from_nonsingular(ns))
    span = 0.55 * float(_period(ns[:, 0]).max())
    back, fwd = integrate(states, -span), integrate(states, span)
    t = np.linspace(-span, span, GRID)
    el = np.empty((GRID, b, 6))
    for sol, sel in ((back, t < 0), (fwd, t >= 0)):
        idx = np.flatnonzero(sel)
        for chunk in np.array_split(idx, max(1, idx.size * b // 200_000)):
            el[chunk] = nonsingular_from_cart(sol(t[chunk]).T.reshape(chunk.size, b, 6))
    el[..., 4:] = np.unwrap(el[..., 4:], axis=0)
    anti = CubicSpline(t, el, axis=0).antiderivative()
    period = _period(ns[:, 0])
    bodies = np.arange(b)
    for _ in range(3):
        half = 0.5 * period
        out = (_ppoly_at(anti, half, bodies) - _ppoly_at(anti, -half, bodies)) / period[:, None]
        period = _period(out[:, 0])
    return out


def _ppoly_at(pp, t: np.ndarray, bodies: np.ndarray) -> np.ndarray:
    """Body j's components (B, 6) of a piecewise polynomial with values (B, 6), at t[j]."""
    idx = np.clip(np.searchsorted(pp.x, t) - 1, 0, pp.x.size - 2)
    dt = (t - pp.x[idx])[:, None]
    coef = pp.c[:, idx, bodies, :]  # (order, B, 6)
    out = np.zeros_like(coef[0])
    for c in coef:
        out = out * dt + c
    return out


def osculating_from_mean(mean_oe: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Osculating Keplerian elements (B, 6) at t = 0 whose orbit average is `mean_oe` (B, 6)."""
    target = nonsingular_from_kep(mean_oe)
    osc = target.copy()
    for _ in range(iterations):
        err = target - orbit_mean(osc)
        err[:, 4:] = wrap(err[:, 4:])
        osc = osc + err
    return kep_from_nonsingular(osc)
