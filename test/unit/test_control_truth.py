"""The deputy-aware control matrix against impulses applied in an independent nonlinear truth.

For deputies at separations up to 20 km (da of -10, -5 and +5 km with along-track offsets, and
one with a 4.5 km eccentricity vector), a 2 m/s impulse along R, T or N of the *chief's* RTN frame
is added to the deputy's inertial velocity in the truth (`helpers.orbit_truth`: two-body + J2,
osculating states from the planned mean elements by inverse orbit averaging). The mean ROE jump
is the difference of the orbit-averaged ROE after the burn and the planned mean ROE before it.

`control_matrix_deputy` (the Gauss equations of the deputy's own elements, in its own frame)
must match it to ``(2 e_d + 5e-4) 2 |dv| / n`` per component, e_d the deputy's eccentricity:
the O(e) terms both matrices neglect and the J2 short-periodic part of a mean jump. The chief-
referenced `control_matrix` misses the deputy's mean motion, 1.5 da/a of the da response (9 m for
2 m/s at da = -10 km), and fails that bound there. Measured errors are printed.
"""
from __future__ import annotations

import numpy as np
import pytest

from art_guidance import dynamics as dyn
from art_guidance.errors import InputError
from art_guidance.config import ScenarioConfig
from helpers import orbit_truth as truth

STATES = np.array([  # a-scaled ROE [m]
    [-10000.0, -19000.0, 380.0, -400.0, 0.0, 0.0],
    [-5000.0, 2500.0, -5.0, -20.0, 0.0, -30.0],
    [5000.0, -6000.0, 100.0, 200.0, 150.0, 300.0],
    [-760.0, 6970.0, -1040.0, -4350.0, 0.0, -20.0],
])
DV_MPS = 2.0


@pytest.fixture(scope="module")
def jumps() -> dict:
    chief = np.array(ScenarioConfig().chief_oe)
    k = STATES.shape[0]
    bodies = np.vstack([chief, truth.deputy_from_roe(np.broadcast_to(chief, (k, 6)), STATES)])
    states = truth.cart_from_kep(truth.osculating_from_mean(bodies))
    r_hat = states[0, :3] / np.linalg.norm(states[0, :3])
    n_hat = np.cross(states[0, :3], states[0, 3:])
    n_hat /= np.linalg.norm(n_hat)
    basis = np.column_stack([r_hat, np.cross(n_hat, r_hat), n_hat])
    burned = [states[0]]
    for axis in range(3):
        for j in range(k):
            s = states[1 + j].copy()
            s[3:] += basis[:, axis] * DV_MPS
            burned.append(s)
    mean = truth.kep_from_nonsingular(truth.orbit_mean(truth.nonsingular_from_cart(
        np.array(burned))))
    after = truth.roe(np.broadcast_to(mean[0], (3 * k, 6)), mean[1:]).reshape(3, k, 6)
    return {"chief": chief, "jump": after - STATES[None]}  # (axis, state, 6) [m]


def test_deputy_control_matrix_matches_the_truth_impulse(jumps: dict) -> None:
    chief, jump = jumps["chief"], jumps["jump"]
    n = dyn.mean_motion(chief[0])
    b_dep = dyn.control_matrix_deputy(chief, STATES)  # (K, 6, 3)
    b_0 = dyn.control_matrix(chief)
    e_vec = chief[1] * np.array([np.cos(chief[4]), np.sin(chief[4])]) + STATES[:, 2:4] / chief[0]
    tol = (2.0 * np.linalg.norm(e_vec, axis=1) + 5e-4) * 2.0 * DV_MPS / n  # (K,) [m]
    worst_dep = worst_0 = 0.0
    for axis in range(3):
        dv = np.zeros(3)
        dv[axis] = DV_MPS
        err_dep = b_dep @ dv - jump[axis]  # (K, 6)
        err_0 = b_0 @ dv - jump[axis]
        assert np.all(np.abs(err_dep) <= tol[:, None]), (axis, err_dep, tol)
        worst_dep = max(worst_dep, float(np.max(np.abs(err_dep) / tol[:, None])))
        worst_0 = max(worst_0, float(np.max(np.abs(err_0) / tol[:, None])))
        if axis == 1:  # the da response of a tangential burn at da = -10 km
            print(f"\nda error of 2 m/s along T at da = -10 km: deputy-aware "
                  f"{err_dep[0, 0]:+.2f} m, chief-referenced {err_0[0, 0]:+.2f} m")
            assert abs(err_0[0, 0]) > tol[0] and abs(err_dep[0, 0]) < 0.25 * abs(err_0[0, 0])
    print(f"largest error / bound: deputy-aware {worst_dep:.2f}, chief-referenced {worst_0:.2f}")


def test_deputy_control_matrix_reduces_to_the_chief_one() -> None:
    chief = np.array(ScenarioConfig().chief_oe)
    np.testing.assert_array_equal(dyn.control_matrix_deputy(chief, np.zeros(6)),
                                  dyn.control_matrix(chief))
    single = dyn.control_matrix_deputy(chief, STATES[0])
    np.testing.assert_allclose(single, dyn.control_matrix_deputy(chief, STATES)[0], rtol=1e-15)
    with pytest.raises(InputError):
        dyn.control_matrix_deputy(chief, np.full(5, 1.0))
