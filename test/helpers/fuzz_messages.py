"""Seeded field-level mutations of the node's inputs, and a campaign that sends them over DDS.

A case is a seed: `case(seed, now_ns)` draws a short message sequence (navigation fixes and
replan requests, 85 / 15 %) in which about half of the messages have one to three fields mutated
to values a bus or a broken filter can carry: NaN, +-inf, +-1e308, zero, huge and negative
numbers, orbit elements at and beyond the planner's limits, unknown enums and frames, long and
non-ASCII strings, stamps from the past and the future and at the edges of their types. Valid
fixes follow each other in stamp order, so the sequences also hold what fuzzing found fatal
before: a bad fix then a good request, a future stamp then good fixes, resets by a request.

`run_campaign` publishes every message of `n_cases` cases to a running guidance node, paced
(each fix waits for its `art_guidance/nav` diagnostic, each request for its
`art_guidance/replan_request` one), and checks the node's promises: every message is answered,
nothing stops the node, and after each case a valid request and fix still get a usable plan
(a poisoned state would not). A failure names the seed, so `case(seed)` replays it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest

from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.dynamics.elements import (
    MAX_ECCENTRICITY, MAX_SEMI_MAJOR_AXIS_M, MIN_INCLINATION_RAD,
)
from helpers.ros_client import nav_msg

SC = ScenarioConfig()
NOMINAL_RTN = np.array(SC.rtn0_nominal)
NAV_COV = np.diag([25.0, 400.0, 25.0, 1e-4, 1e-4, 1e-4])
FLOATS = (math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -1.0, 1e12, -1e12, 1e-300, 5e-324)
STRINGS = ("", "map", "chief_roe", "chief_rtn", "x" * 2000, "ünïcødé", "plus_vbar ", "custom")
INT32_MAX, UINT32_MAX = 2**31 - 1, 2**32 - 1
# chief elements at and beyond the limits of docs/node.md (inclination, eccentricity, a), and
# huge finite angles (beyond ~1e15 rad the J2 drift is below one ulp unless reduced)
CHIEF_EDGES = (0.95, 1.0, 1.2, -0.1, 1e12, 6.0e6, 0.0, 1e-300, MIN_INCLINATION_RAD,
               0.999 * MIN_INCLINATION_RAD, math.pi - MIN_INCLINATION_RAD, math.pi,
               MAX_ECCENTRICITY, MAX_SEMI_MAJOR_AXIS_M, 7e15, -7e15, 1e18, 1.7e308)


@dataclass
class Message:
    """One message of a case: kind "nav" or "request", the message, what was mutated."""

    kind: str
    msg: object
    mutated: list[str] = field(default_factory=list)


def _float(rng: np.random.Generator, valid: float) -> float:
    if rng.random() < 0.7:
        return float(FLOATS[rng.integers(len(FLOATS))])
    with np.errstate(over="ignore"):  # a huge value times 1e12 is inf: a case as well
        return float(valid * 10.0 ** rng.uniform(-6, 12) * rng.choice([-1.0, 1.0]))


def _stamp(rng: np.random.Generator, msg: object, now_ns: int) -> None:
    choice = rng.integers(6)
    sec, nanosec = divmod(now_ns, 1_000_000_000)
    if choice == 0:
        sec += 3600  # an hour in the future
    elif choice == 1:
        sec -= 3600
    elif choice == 2:
        sec = 0
    elif choice == 3:
        sec = INT32_MAX
    elif choice == 4:
        nanosec = int(rng.choice([1_000_000_000, UINT32_MAX]))
    else:
        sec = -int(rng.integers(1, INT32_MAX))
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(sec), int(nanosec)


def _mutate_nav(rng: np.random.Generator, msg: RelativeNavState, now_ns: int) -> list[str]:
    names = []
    for _ in range(int(rng.integers(1, 4))):
        what = ("mean", "covariance", "chief_oe", "representation", "frame_id",
                "stamp")[rng.integers(6)]
        names.append(what)
        if what == "mean":
            mean = list(msg.mean)
            i = int(rng.integers(6))
            mean[i] = _float(rng, mean[i] or 1.0)
            msg.mean = mean
        elif what == "covariance":
            cov = list(msg.covariance)
            i = int(rng.integers(36))
            cov[i] = _float(rng, cov[i] or 1.0)
            msg.covariance = cov
        elif what == "chief_oe":
            oe = list(msg.chief_oe)
            i = int(rng.integers(6))
            oe[i] = float(rng.choice([_float(rng, oe[i]), *CHIEF_EDGES]))
            msg.chief_oe = oe
        elif what == "representation":
            msg.representation = int(rng.choice([0, 1, 2, 255]))
        elif what == "frame_id":
            msg.header.frame_id = STRINGS[rng.integers(len(STRINGS))]
        else:
            _stamp(rng, msg, now_ns)
    return names


def _request(rng: np.random.Generator, stamp_ns: int) -> tuple[ReplanRequest, list[str]]:
    msg = ReplanRequest(waypoint=str(rng.choice(sorted(SC.waypoints_rtn))),
                        chance_constrained=bool(rng.random() < 0.7))
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    names = []
    if rng.random() < 0.5:
        for _ in range(int(rng.integers(1, 3))):
            what = ("waypoint", "warm_start", "target_rtn", "horizon_orbits")[rng.integers(4)]
            names.append(what)
            if what == "waypoint":
                msg.waypoint = STRINGS[rng.integers(len(STRINGS))]
            elif what == "warm_start":
                msg.warm_start = str(rng.choice(["", "auto", "cvx", "art", "bogus"]))
            elif what == "target_rtn":
                msg.waypoint = "custom"
                target = [0.0, 750.0, 0.0, 0.0, 0.0, 0.0]
                target[int(rng.integers(6))] = _float(rng, 750.0)
                msg.target_rtn = target
            else:
                msg.horizon_orbits = float(rng.choice(
                    [0.0, -1.0, 0.005, 0.0099, 0.01, 1.29, 20.0, 20.1, math.nan, math.inf,
                     1e308]))
    return msg, names


def case(seed: int, now_ns: int) -> list[Message]:
    """The message sequence of case `seed` (valid stamps counted from `now_ns`)."""
    rng = np.random.default_rng(seed)
    out, stamp = [], int(now_ns)
    for _ in range(int(rng.integers(3, 9))):
        stamp += int(rng.integers(1, 2_000_000))  # valid fixes in stamp order (< 2 ms apart)
        if rng.random() < 0.15:
            msg, names = _request(rng, stamp)
            out.append(Message("request", msg, names))
            continue
        rtn = NOMINAL_RTN + rng.normal(0.0, 200.0, 6) * [1, 1, 1, 0, 0, 0]
        representation = int(rng.integers(2))
        if representation == RelativeNavState.REPRESENTATION_ROE:
            msg = nav_msg(stamp, roe_from_rtn_linear(np.array(SC.chief_oe), rtn),
                          representation=representation, frame_id="chief_roe",
                          cov=np.eye(6) * 400.0)
        else:
            msg = nav_msg(stamp, rtn, cov=NAV_COV)
        names = _mutate_nav(rng, msg, stamp) if rng.random() < 0.5 else []
        out.append(Message("nav", msg, names))
    return out


def stamp_of(msg: object) -> int:
    """The header stamp [ns] as the node computes it."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _request_diags(client) -> int:
    with client._cv:
        return sum(1 for _, _, name in client.diags if name == "art_guidance/replan_request")


def run_campaign(client, node_proc, first_seed: int, n_cases: int,
                 answer_timeout_s: float = 10.0, plan_timeout_s: float = 60.0,
                 progress=None) -> dict:
    """Send the cases `first_seed` .. `first_seed + n_cases - 1` (module docstring).

    Returns counts: cases, messages of the cases (and the closing request and fix of each,
    apart), nav answers by decision, requests answered, and the nav -> answer latency median
    [ms]. Raises AssertionError naming the seed on a failure.
    """
    counts = {"cases": 0, "messages": 0, "rejected": 0, "replanning": 0, "on_plan": 0,
              "requests": 0, "mutated": 0, "closing_messages": 0}
    answer_ms = []
    # the first samples after an endpoint match can be lost while discovery completes on the
    # node's side: a fix resent until answered (`Client.send_nav`) opens the campaign
    _, decision = client.send_nav(NOMINAL_RTN, cov=NAV_COV)
    assert decision is not None, "the node answers no fix"
    for seed in range(first_seed, first_seed + n_cases):
        messages = case(seed, time.time_ns())
        for m in messages:
            counts["messages"] += 1
            counts["mutated"] += bool(m.mutated)
            where = f"seed {seed}: {m.kind} mutated {m.mutated or 'none'}"
            if m.kind == "request":
                before = _request_diags(client)
                client.req_pub.publish(m.msg)
                got = client.wait_for(lambda *_: _request_diags(client) > before,
                                      answer_timeout_s)
                assert got, f"{where}: no replan_request diagnostic"
                counts["requests"] += 1
            else:
                t = time.monotonic()
                client.nav_pub.publish(m.msg)
                decision = client.decision_for(stamp_of(m.msg), answer_timeout_s)
                assert decision is not None, f"{where}: no nav diagnostic"
                answer_ms.append(1e3 * (time.monotonic() - t))
                counts[decision if decision in counts else "on_plan"] += 1
            assert node_proc.poll() is None, f"{where}: the node stopped"
        _assert_still_plans(client, seed, plan_timeout_s)
        counts["closing_messages"] += 2  # the valid request and fix after the case
        counts["cases"] += 1
        if progress is not None:
            progress(counts)
    counts["answer_ms_median"] = float(np.median(answer_ms)) if answer_ms else math.nan
    return counts


def _assert_still_plans(client, seed: int, timeout_s: float) -> None:
    """A valid request, then a valid fix: a usable plan must come (the state is not
    poisoned)."""
    before = _request_diags(client)
    client.req_pub.publish(ReplanRequest(waypoint="plus_vbar", chance_constrained=True))
    assert client.wait_for(lambda *_: _request_diags(client) > before, 10.0), \
        f"seed {seed}: the closing request was not answered"
    stamp = time.time_ns()
    client.nav_pub.publish(nav_msg(stamp, NOMINAL_RTN, cov=NAV_COV))
    decision = client.decision_for(stamp, 10.0)
    assert decision == "replanning", f"seed {seed}: closing fix answered {decision!r}"
    plan = client.plan_for(stamp, timeout_s)
    assert plan is not None, f"seed {seed}: no plan for the closing fix"
    usable = (ManeuverPlan.STATUS_CONVERGED, ManeuverPlan.STATUS_MAX_ITERATIONS)
    assert plan.status in usable, f"seed {seed}: closing plan {plan.status}: {plan.status_text}"
