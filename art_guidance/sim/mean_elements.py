"""Orbit-averaged (mean) elements of inertial states, sampled from the truth (see `mean_elements`).
"""
from __future__ import annotations


import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.dynamics import MU_M3PS2

from art_guidance.sim.truth import integrate_truth

MEAN_SAMPLES = 128     # samples per orbit-averaging window (midpoint rule)
MEAN_ITERATIONS = 2    # fixed-point iterations of the averaging period


def _nonsingular_from_eci(states: np.ndarray) -> np.ndarray:
    """Osculating (a, e cos w, e sin w, i, raan, u = w + M) of inertial states (..., 6)."""
    r, v = states[..., :3], states[..., 3:]
    rn = np.linalg.norm(r, axis=-1)
    v2 = np.sum(v * v, axis=-1)
    rv = np.sum(r * v, axis=-1)
    h = np.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    a = 1.0 / (2.0 / rn - v2 / MU_M3PS2)
    inc = np.arccos(np.clip(h[..., 2] / hn, -1.0, 1.0))
    raan = np.arctan2(h[..., 0], -h[..., 1])
    e_vec = ((v2 - MU_M3PS2 / rn)[..., None] * r - rv[..., None] * v) / MU_M3PS2
    node = np.stack([np.cos(raan), np.sin(raan), np.zeros_like(raan)], axis=-1)
    m_hat = np.cross(h / hn[..., None], node)
    ex, ey = np.sum(e_vec * node, axis=-1), np.sum(e_vec * m_hat, axis=-1)
    e = np.hypot(ex, ey)
    w = np.arctan2(ey, ex)
    u_true = np.arctan2(np.sum(r * m_hat, axis=-1), np.sum(r * node, axis=-1))
    nu = u_true - w
    ecc = 2.0 * np.arctan2(np.sqrt(1.0 - e) * np.sin(nu / 2), np.sqrt(1.0 + e) * np.cos(nu / 2))
    return np.stack([a, ex, ey, inc, raan, w + ecc - e * np.sin(ecc)], axis=-1)


def mean_elements(states: object) -> np.ndarray:
    """Orbit-averaged (mean) Keplerian elements of inertial states under free motion.

    Every body's osculating nonsingular elements (a, e cos w, e sin w, i, raan, u = w + M,
    angles unwrapped) are averaged over one of its *own* Keplerian periods (of its averaged a,
    fixed-point iterated) centred on now, sampling the two-body + J2 truth propagated forward
    and backward. First-order J2 short-periodic terms average to zero over the mean anomaly,
    so this is the (Brouwer/Kozai) mean element to first order in J2; the secular drift is
    linear over the window and a centred average returns its value now.

    Args:
        states: (B, 6) inertial states [m, m/s].

    Returns:
        (B, 6) mean elements (a [m], e, i, raan, argp, M [rad]).
    """
    s = as_finite_array("states", states, (None, 6))
    n_body = s.shape[0]
    period = 2.0 * np.pi / np.sqrt(MU_M3PS2 / _nonsingular_from_eci(s)[:, 0] ** 3)
    span = 0.6 * float(period.max())
    y0 = s.ravel()
    fwd, bwd = integrate_truth(y0, span, dense=True), integrate_truth(y0, -span, dense=True)
    offsets = (np.arange(MEAN_SAMPLES) + 0.5) / MEAN_SAMPLES - 0.5  # ascending, symmetric
    half = MEAN_SAMPLES // 2  # offsets[:half] < 0 <= offsets[half:]
    rows = np.arange(n_body)
    for _ in range(MEAN_ITERATIONS + 1):
        times = period[:, None] * offsets[None, :]  # (B, S)
        neg = bwd.sol(times[:, :half].ravel()).reshape(n_body, 6, n_body, half)
        pos = fwd.sol(times[:, half:].ravel()).reshape(n_body, 6, n_body, MEAN_SAMPLES - half)
        own = np.concatenate([neg[rows, :, rows], pos[rows, :, rows]], axis=-1)  # (B, 6, S)
        q = _nonsingular_from_eci(np.moveaxis(own, 1, -1))  # (B, S, 6)
        q[..., 4] = np.unwrap(q[..., 4], axis=-1)
        q[..., 5] = np.unwrap(q[..., 5], axis=-1)
        avg = q.mean(axis=1)  # (B, 6)
        period = 2.0 * np.pi / np.sqrt(MU_M3PS2 / avg[:, 0] ** 3)
    w = np.arctan2(avg[:, 2], avg[:, 1])
    two_pi = 2.0 * np.pi
    return np.column_stack([avg[:, 0], np.hypot(avg[:, 1], avg[:, 2]), avg[:, 3],
                            avg[:, 4] % two_pi, w % two_pi, (avg[:, 5] - w) % two_pi])


def mean_elements_of_chief(chief_eci: object) -> np.ndarray:
    """Orbit-averaged mean elements (6,) of one inertial state (see `mean_elements`)."""
    return mean_elements(as_finite_array("chief_eci", chief_eci, (6,))[None])[0]
