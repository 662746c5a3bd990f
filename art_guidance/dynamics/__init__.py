"""Relative orbital dynamics, one concept per module.

- `elements`: constants, orbit elements, J2 secular rates, ROE <-> elements, inertial states;
- `frames`: the chief's RTN frame, inertial <-> RTN, the first-order ROE <-> RTN map Psi;
- `stm`: the J2 state transition matrix of mean ROE and the control matrix B;
- `deputy`: the deputy-aware burn and drift model SCVx* plans with;
- `horizon`: the node time grid and `Horizon` (the dynamics over a planning horizon).

State convention: quasi-nonsingular ROE scaled by the chief semi-major axis, metres:
``roe_m = a * [da, dlambda, dex, dey, dix, diy]``. RTN states are ``[r_R, r_T, r_N]`` [m] and
``[v_R, v_T, v_N]`` [m/s] of the deputy relative to the chief, in the rotating chief RTN frame.
Orbit elements are ``(a [m], e, i, raan, argp, M)`` with angles in radians. Mean/osculating: the
STM and B propagate *mean* ROE (Koenig, Guffanti, D'Amico 2017); the exact conversions treat the
elements they are given as osculating Keplerian elements. Models and constants:
docs/design.md.
"""
from art_guidance.dynamics.elements import (  # noqa: F401
    J2, MU_M3PS2, R_EARTH_M, check_chief, check_deputy_inclination, check_oe, eci_from_oe,
    j2_secular_rates, mean_arg_latitude, mean_motion, oe_from_eci, oe_from_roe, orbital_period_s,
    propagate_mean_oe, roe_from_oe, solve_kepler,
)
from art_guidance.dynamics.frames import (  # noqa: F401
    eci_from_rtn, psi_from_latitude, psi_matrix, roe_from_rtn_exact, roe_from_rtn_linear,
    rtn_frame, rtn_from_eci, rtn_from_roe_exact, rtn_from_roe_linear,
)
from art_guidance.dynamics.stm import (  # noqa: F401
    control_matrix, stm_basis, stm_basis_orders, stm_j2, stm_j2_terms,
)
from art_guidance.dynamics.deputy import (  # noqa: F401
    along_track_curvature_m, control_matrix_deputy, DeputyLinearization,
)
from art_guidance.dynamics.horizon import (  # noqa: F401
    Horizon, time_grid_s,
)
