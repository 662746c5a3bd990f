"""The planner's domain for the chief orbit, and planning at its edges: every chief element set
to 0, to tiny and huge finite values and to the limits of docs/node.md is either refused at
validation with the element named, or planned to finite numbers (no NaN reaches the solver
from an accepted request)."""
from __future__ import annotations

import decimal
import math

import numpy as np
import pytest

from art_guidance.art.provider import ArtWarmStart, default_model_path
from art_guidance.config import GuidanceConfig, ScenarioConfig
from art_guidance.dynamics import R_EARTH_M, check_chief, roe_from_rtn_linear
from art_guidance.dynamics.elements import (
    MAX_ECCENTRICITY, MAX_SEMI_MAJOR_AXIS_M, MIN_DEPUTY_INCLINATION_RAD, MIN_INCLINATION_RAD,
    MIN_PERIGEE_ALTITUDE_M,
)
from art_guidance.errors import InputError
from art_guidance.planning import GuidancePipeline, PlanRequest

SC = ScenarioConfig()
CHIEF = np.array(SC.chief_oe)
RTN0 = np.array(SC.rtn0_nominal)
TARGET = np.array(SC.waypoints_rtn["plus_vbar"])


def _request(chief: np.ndarray, rtn0: np.ndarray = RTN0,
             target: np.ndarray = TARGET) -> PlanRequest:
    chief = check_chief(chief)  # first, as a navigation fix is checked
    return PlanRequest(chief, roe_from_rtn_linear(chief, rtn0), target, warm_start="auto")


@pytest.mark.parametrize("inc", [0.0, 1e-300, 1e-8, 0.999 * MIN_INCLINATION_RAD,
                                 math.pi - 0.999 * MIN_INCLINATION_RAD, math.pi, 4.0, -0.5])
def test_near_equatorial_chiefs_are_refused_with_the_reason(inc):
    chief = CHIEF.copy()
    chief[2] = inc
    with pytest.raises(InputError, match=r"chief_oe: inclination must be in \[1, 179\] deg"):
        _request(chief)


def test_a_deputy_near_equatorial_is_refused_at_either_end():
    chief = CHIEF.copy()
    chief[2] = 1.2 * MIN_INCLINATION_RAD
    a = chief[0]
    # the deputy's inclination i + dix / a below the deputy limit: dix from r_N at u = 90 deg
    dix = -(chief[2] - 0.9 * MIN_DEPUTY_INCLINATION_RAD) * a
    roe0 = roe_from_rtn_linear(chief, RTN0)
    roe0[4] = dix
    with pytest.raises(InputError, match="roe0_m: the deputy's inclination"):
        PlanRequest(chief, roe0, TARGET)
    target = TARGET.copy()
    target[2] = 1.1 * abs(dix)  # |dix| >= |r_N|: a target whose deputy may cross the limit
    with pytest.raises(InputError, match="target_rtn: the deputy's inclination"):
        _request(chief, target=target)
    _request(chief)  # the nominal deputy at the same chief is planned


def _edge_values() -> list[tuple[int, float]]:
    perigee_a = (R_EARTH_M + MIN_PERIGEE_ALTITUDE_M) / (1.0 - CHIEF[1])
    values = {0: [0.0, 1e-300, 1e300, perigee_a, perigee_a * (1 - 1e-12), MAX_SEMI_MAJOR_AXIS_M,
                  MAX_SEMI_MAJOR_AXIS_M * (1 + 1e-12), 4.2164e7],
              1: [0.0, 1e-300, MAX_ECCENTRICITY, MAX_ECCENTRICITY * (1 + 1e-12), 1e300],
              2: [0.0, 1e-300, MIN_INCLINATION_RAD, 0.5 * math.pi, math.pi - MIN_INCLINATION_RAD,
                  math.pi, 1e300]}
    for i in (3, 4, 5):
        values[i] = [0.0, 1e-300, 2 * math.pi, -1e300, 1e300, 1e12]
    return [(i, v) for i, vs in values.items() for v in vs]


@pytest.fixture(scope="module")
def pipeline() -> GuidancePipeline:
    """The chance-constrained default model, proposals in line, a 4 s deadline."""
    return GuidancePipeline(GuidanceConfig.load(),
                            provider=ArtWarmStart.load(default_model_path("chance")),
                            deadline_s=4.0)


def test_chief_elements_at_their_edges_are_refused_or_planned_finite(pipeline):
    refused = planned = 0
    for i, value in _edge_values():
        chief = CHIEF.copy()
        chief[i] = value
        try:
            request = _request(chief)
        except InputError as exc:
            assert "chief_oe" in str(exc), (i, value, exc)
            refused += 1
            continue
        result = pipeline.plan(request)
        planned += 1
        for name in ("dv_rtn_mps", "roe_m", "rtn"):
            assert np.all(np.isfinite(getattr(result, name))), (i, value, name)
        assert math.isfinite(result.cost_mps), (i, value)
        assert result.warm_start_reason, (i, value)
    assert refused == 12 and planned == 26, (refused, planned)


def exact_reduction(x: float) -> float:
    """x modulo 2 pi into (-pi, pi], in 80-digit decimal arithmetic (x is exact as a double)."""
    with decimal.localcontext() as ctx:
        ctx.prec = 80
        two_pi = 2 * decimal.Decimal(PI_60)
        r = decimal.Decimal(x) % two_pi  # the sign of x
        if r > two_pi / 2:
            r -= two_pi
        elif r <= -two_pi / 2:
            r += two_pi
        return float(r)


PI_60 = "3.141592653589793238462643383279502884197169399375105820974944"


@pytest.mark.parametrize("value", [7e15, 1e17, 1e18, -3.3e17, 5e4, 6434.0])
def test_huge_angles_are_reduced_exactly(value):
    """`np.fmod` by the double 2 pi drifts 2.45e-16 rad a turn (0.27 rad at 7e15, arbitrary
    from 1e17): beyond 1,024 turns the reduction is exact, checked against 80-digit decimal
    arithmetic: bit for bit (correctly rounded)."""
    chief = CHIEF.copy()
    chief[3:] = value
    reduced = check_chief(chief)[3:]
    assert np.all(reduced == exact_reduction(value)), (reduced, value)


@pytest.mark.parametrize("i, value", [(3, 1e17), (4, 7e15), (5, 1e18)])
def test_a_huge_finite_chief_angle_is_planned_as_its_reduction(i, value):
    """raan, argp and M above ~1e15 rad are below one ulp of their J2 drift over the horizon:
    unreduced, the plan was made on another orbit (argp = 7e15 rad: a CONVERGED plan that
    missed the waypoint by 936 m in the planner's own model). Reduced exactly where the chief
    enters the planner, they give the exactly reduced angle's plan, bit for bit."""
    huge, reduced = CHIEF.copy(), CHIEF.copy()
    huge[i], reduced[i] = value, exact_reduction(value)
    pipeline = GuidancePipeline(GuidanceConfig.load(), deadline_s=10.0)
    plans = [pipeline.plan(PlanRequest(chief, roe_from_rtn_linear(check_chief(chief), RTN0),
                                       TARGET, warm_start="cvx")) for chief in (huge, reduced)]
    assert plans[0].status.name == "CONVERGED", plans[0].status
    for name in ("dv_rtn_mps", "roe_m", "rtn"):
        assert np.array_equal(getattr(plans[0], name), getattr(plans[1], name)), name
    assert np.allclose(plans[0].rtn[-1, :3], TARGET[:3], atol=1.0)  # the waypoint reached


def test_angles_within_one_turn_are_kept_bit_for_bit():
    for value in (0.0, 1e-300, -1.0, 2.0 * math.pi - 1e-12, -2.0 * math.pi + 1e-12, 3.0):
        chief = CHIEF.copy()
        chief[3:] = value
        assert np.array_equal(check_chief(chief), chief), value
    chief = CHIEF.copy()
    chief[3:] = [2.0 * math.pi, -7.0, 1e300]
    reduced = check_chief(chief)
    assert np.all(np.abs(reduced[3:]) < 2.0 * math.pi) and reduced[4] < 0.0
