"""Orbit elements: constants, mean motion, J2 secular rates, ROE <-> elements, Kepler,
elements <-> inertial states.

Orbit elements are ``(a [m], e, i, raan, argp, M)`` with angles in radians; ROE are
quasi-nonsingular and scaled by the chief's a, ``roe_m = a * [da, dlambda, dex, dey, dix, diy]``
[m]. The exact conversions treat the elements they are given as osculating Keplerian elements.
"""
from __future__ import annotations

import math

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


# The planner's domain (a request's and a navigation fix's chief): a near-circular Earth orbit.
MIN_PERIGEE_ALTITUDE_M = 100e3  # below it the orbit decays within hours (and may hit the Earth)
MAX_SEMI_MAJOR_AXIS_M = 1e8     # well beyond GEO (42,164 km), where J2 is no longer the model
MAX_ECCENTRICITY = 0.1          # the control matrix and Psi are the near-circular forms
# The quasi-nonsingular ROE and the deputy's control matrix divide by sin i and tan i: an orbit
# closer than this to equatorial (prograde or retrograde) is outside the domain. Measured (plans
# of seeds 3 and 11 with 800 m of cross-track ROE flown in two-body + J2 truth): miss 156-180 m
# at 1 deg (12-14 m at 51.6 deg; near-equatorial J2 alone gives ~160 m with no cross-track
# motion), 212-246 m at 0.29 deg, 0.77-0.90 km at 0.057 deg, 7-13 km at 0.011 deg; at 1e-8 rad
# a singular matrix, below it overflow to NaN.
MIN_INCLINATION_RAD = float(np.radians(1.0))
# The deputy's own inclination (chief's + dix / a) may come closer, to half of it: the deputy
# matrix's sin(i) / sin(i + dix / a) stays <= 2 for a chief at the limit.
MIN_DEPUTY_INCLINATION_RAD = 0.5 * MIN_INCLINATION_RAD
# `reduce_angles`: fmod by the double 2 pi up to 1,024 turns, the exact reduction beyond.
FMOD_MAX_RAD = 1024 * 2.0 * np.pi


def check_chief(oe: object, field: str = "chief_oe") -> np.ndarray:
    """`check_oe`, and the planner's domain: perigee altitude >= MIN_PERIGEE_ALTITUDE_M,
    a <= MAX_SEMI_MAJOR_AXIS_M, e <= MAX_ECCENTRICITY, inclination in [MIN_INCLINATION_RAD,
    pi - MIN_INCLINATION_RAD]; returns a (6,) array with raan, argp and M reduced modulo 2 pi
    (`reduce_angles`).

    Raises:
        InputError: naming the element and the bound.
    """
    arr = check_oe(oe, field)
    a, e = float(arr[0]), float(arr[1])
    if not e <= MAX_ECCENTRICITY:
        raise InputError(field, f"eccentricity above {MAX_ECCENTRICITY} (the planner's "
                         "models are the near-circular forms)", e)
    if not a <= MAX_SEMI_MAJOR_AXIS_M:
        raise InputError(field, f"semi-major axis above {MAX_SEMI_MAJOR_AXIS_M:.0f} m", a)
    if not a * (1.0 - e) - R_EARTH_M >= MIN_PERIGEE_ALTITUDE_M:
        raise InputError(field, f"perigee altitude below {MIN_PERIGEE_ALTITUDE_M:.0f} m",
                         a * (1.0 - e) - R_EARTH_M)
    inc = float(arr[2])
    if not MIN_INCLINATION_RAD <= inc <= np.pi - MIN_INCLINATION_RAD:
        raise InputError(field, f"inclination must be in [{np.degrees(MIN_INCLINATION_RAD):g}, "
                         f"{180.0 - np.degrees(MIN_INCLINATION_RAD):g}] deg: the quasi-"
                         "nonsingular ROE are singular at equatorial orbits [rad]", inc)
    return reduce_angles(arr)


def reduce_angles(oe: np.ndarray) -> np.ndarray:
    """(6,) elements with raan, argp and M reduced modulo 2 pi: an angle within (-2 pi, 2 pi)
    is returned bit for bit; up to FMOD_MAX_RAD `np.fmod` by the double 2 pi, keeping its sign
    (the recorded flights' growing anomalies, bit for bit as before); beyond, reduced exactly
    (`reduce_exactly`) into (-pi, pi].

    The double 2 pi is 2.45e-16 short of 2 pi: `fmod` drifts by that much a turn, 2.5e-13 rad
    (a micrometre along the orbit) at FMOD_MAX_RAD, but 0.27 rad at 7e15 rad and arbitrary
    from 1e17. The J2 secular propagation adds `rate * tau` to each angle: above ~1e15 rad one
    ulp is a radian or more, so an unreduced angle is rounded or frozen along the horizon and
    the plan is made on another orbit."""
    out = np.array(oe, dtype=float)
    for i in range(3, 6):
        x = float(out[i])
        out[i] = reduce_exactly(x) if abs(x) > FMOD_MAX_RAD else math.fmod(x, 2.0 * math.pi)
    return out


def _two_pi_scaled(bits: int) -> int:
    """round(2 pi * 2**bits), from Machin's formula in integer arithmetic (40 guard bits)."""
    one = 1 << (bits + 40)

    def atan_inv(n: int) -> int:  # atan(1 / n) * one
        total, power, k = 0, one // n, 0
        while power:
            total += (-1) ** k * (power // (2 * k + 1))
            power //= n * n
            k += 1
        return total

    pi = 16 * atan_inv(5) - 4 * atan_inv(239)
    return (2 * pi + (1 << 39)) >> 40


_REDUCTION_BITS = 1150  # 2 pi to 2**-1150: a double's remainder exact to ~2**-120 rad
_TWO_PI_SCALED = _two_pi_scaled(_REDUCTION_BITS)


def reduce_exactly(x: float) -> float:
    """A finite angle `x` [rad] modulo 2 pi, into (-pi, pi], correctly rounded: x is an
    exact binary fraction, reduced in integer arithmetic against 2 pi to 1,150 bits (the
    Payne-Hanek idea); a few microseconds."""
    mantissa, exponent = math.frexp(x)
    m, e = int(mantissa * 2.0 ** 53), exponent - 53
    shift = e + _REDUCTION_BITS
    if shift < 0:  # |x| < 2**-1097: already reduced
        return x
    r = (m << shift) % _TWO_PI_SCALED
    if 2 * r > _TWO_PI_SCALED:
        r -= _TWO_PI_SCALED
    return r / (1 << _REDUCTION_BITS)  # int / int is correctly rounded


def check_deputy_inclination(chief_oe: np.ndarray, dix_max_m: float, field: str) -> None:
    """Refuse a deputy whose inclination, the chief's `i` plus up to `dix_max_m` / a of
    a-scaled ROE inclination difference either way, comes closer to equatorial than
    MIN_DEPUTY_INCLINATION_RAD (`chief_oe`: checked by `check_chief`; `dix_max_m` >= 0 [m]).

    Raises:
        InputError: naming `field` and the deputy's extreme inclination [rad].
    """
    a, inc = float(chief_oe[0]), float(chief_oe[2])
    lo, hi = inc - dix_max_m / a, inc + dix_max_m / a
    limit = MIN_DEPUTY_INCLINATION_RAD
    if not (lo >= limit and hi <= np.pi - limit):
        worst = lo if inc <= 0.5 * np.pi else hi
        raise InputError(field, f"the deputy's inclination (chief's + dix / a) would be within "
                         f"{np.degrees(limit):g} deg of equatorial, where the quasi-nonsingular "
                         "ROE are singular [rad]", worst)


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
