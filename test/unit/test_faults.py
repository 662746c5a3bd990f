"""Thruster faults: the ellipsoid distance, the truth drift check, faults in the closed loop and
the Monte Carlo driver (in-process, no DDS; the DDS simulator is in test/ros/test_sim_node.py).
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict

import numpy as np
import pytest
from scipy.optimize import minimize

from art_guidance.config import ScenarioConfig
from art_guidance.errors import InputError
from art_guidance.planning import GuidancePipeline
from art_guidance.sim.closed_loop import (
    PARAMETERS, SIM_EPOCH0_NS, ClosedLoop, fault_exit_code,
)
from art_guidance.sim.contingency import ContingencySpec, run as run_mc, upper_bound
from art_guidance.sim.faults import Fault, ellipsoid_distance_m, free_drift_check
from art_guidance.sim.inprocess import InProcessGuidance
from art_guidance.sim.simulator import RendezvousSim
from helpers import orbit_truth as truth

SC = ScenarioConfig()
LOG = logging.getLogger("test_faults")


def _fly(**overrides) -> tuple[ClosedLoop, dict, int]:
    params = {**PARAMETERS, "rtn0": None, "png_path": "", "summary_path": "",
              "warm_start": "cvx", **overrides}
    loop = ClosedLoop(InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS), params, LOG,
                      settle_s=0.0)
    summary, code = loop.finish(loop.run(), 0.0)
    return loop, summary, code


# --------------------------------------------------------------------------- distance
def test_sphere_distance_is_exact():
    p = np.array([[300.0, 0, 0], [0, 0, 0], [100.0, 100.0, 0], [0, -1500.0, 0]])
    d = ellipsoid_distance_m(p, [200.0, 200.0, 200.0])
    np.testing.assert_allclose(d, [100.0, -200.0, np.hypot(100, 100) - 200.0, 1300.0])


def test_ellipsoid_distance_matches_a_direct_minimisation():
    """Against the minimum over the surface (two angles, Nelder-Mead from 8 starts), 1 cm."""
    axes = np.array([200.0, 400.0, 300.0])
    rng = np.random.default_rng(3)
    points = rng.normal(size=(25, 3)) * 350.0

    def surface(ang):
        return axes * np.array([np.cos(ang[0]) * np.cos(ang[1]),
                                np.sin(ang[0]) * np.cos(ang[1]), np.sin(ang[1])])

    for p in points:
        best = min(minimize(lambda a: np.linalg.norm(surface(a) - p), x0,
                            method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-10}).fun
                   for x0 in rng.uniform(-np.pi, np.pi, size=(8, 2)))
        sign = 1.0 if np.sum((p / axes) ** 2) >= 1.0 else -1.0
        assert float(ellipsoid_distance_m(p, axes)) == pytest.approx(sign * best, abs=1e-2)


def test_bad_semi_axes_are_refused():
    with pytest.raises(InputError, match="semi_axes_m"):
        ellipsoid_distance_m([1.0, 2.0, 3.0], [100.0, 0.0, 100.0])


# --------------------------------------------------------------------------- drift check
@pytest.mark.parametrize("rtn0, zone, entered", [
    ([0.0, 300.0, 0.0, 0.0, 0.0, 0.0], "keep_out_zone", False),      # V-bar hold at 300 m
    ([-400.0, 900.0, 0.0, 0.0, 0.0, 0.0], "approach_ellipsoid", True),  # drifts through
])
def test_drift_check_agrees_with_independent_truth(rtn0, zone, entered):
    """Margin within 5 cm of the helpers' own integration; the hold stays out, the radial
    offset drifts inside the 1 km approach ellipsoid."""
    sim = RendezvousSim(SC, None, rtn0, seed=0)
    duration = 5500.0
    check = free_drift_check(sim.chief_eci, sim.deputy_eci, 12.0, duration, SC, zone)
    radius = SC.koz_semi_axes_m[0] if zone == "keep_out_zone" else SC.ae_semi_axes_m[0]
    ref = truth.sphere_clearance_m(sim.chief_eci, sim.deputy_eci, duration, radius, 0.5)
    assert check.min_margin_m == pytest.approx(ref, abs=0.05)
    assert check.entered is entered and (check.min_margin_m < 0) is entered
    assert 12.0 <= check.t_closest_s <= 12.0 + duration
    closest = np.linalg.norm(check.closest_rtn_m) - radius
    assert closest == pytest.approx(check.min_margin_m, abs=1e-6)
    assert check.t_s[0] == 12.0 and np.all(np.diff(check.t_s) <= 5.0 + 1e-9)
    json.dumps(check.to_json())


def test_drift_check_refuses_bad_input():
    sim = RendezvousSim(SC, None, [0.0, 300.0, 0, 0, 0, 0], seed=0)
    with pytest.raises(InputError, match="zone"):
        free_drift_check(sim.chief_eci, sim.deputy_eci, 0.0, 100.0, SC, "sphere")
    with pytest.raises(InputError, match="duration_s"):
        free_drift_check(sim.chief_eci, sim.deputy_eci, 0.0, -1.0, SC, "keep_out_zone")
    with pytest.raises(InputError, match="deputy_eci"):
        free_drift_check(sim.chief_eci, [np.nan] * 6, 0.0, 100.0, SC, "keep_out_zone")


def test_fault_parameters_are_checked():
    assert Fault.parse("", 5) is None and Fault.parse("none", 5) is None
    assert Fault.parse("loss", 3) == Fault("loss", 3)
    with pytest.raises(InputError, match="fault"):
        Fault.parse("stuck", 3)
    with pytest.raises(InputError, match="fault_node"):
        Fault.parse("missed", -1)
    with pytest.raises(InputError, match="fault"):
        ClosedLoop(InProcessGuidance(GuidancePipeline(), SIM_EPOCH0_NS),
                   dict(PARAMETERS, rtn0=None, fault="lost"), LOG, settle_s=0.0)


def test_fault_exit_codes():
    assert fault_exit_code(None, True) == 0 and fault_exit_code(None, False) == 1
    loss = {"kind": "loss", "hit": True, "entered": False}
    assert fault_exit_code(loss, False) == 0
    assert fault_exit_code(dict(loss, entered=True), False) == 1
    missed = {"kind": "missed", "hit": True, "entered": False}
    assert fault_exit_code(missed, True) == 0 and fault_exit_code(missed, False) == 1
    assert fault_exit_code(dict(missed, entered=True), True) == 1
    assert fault_exit_code({"kind": "loss", "hit": False, "entered": None}, True) == 0


# --------------------------------------------------------------------------- closed loop
@pytest.fixture(scope="module")
def nominal():
    """Seed 3 with errors, CVX warm starts: the flight every fault below branches from."""
    loop, summary, code = _fly(seed=3)
    return loop, summary, code, loop.loss_checks()


@pytest.mark.slow
def test_loss_run_ends_in_the_state_the_sweep_checks(nominal, tmp_path):
    """`--fault loss --fault-node K` stops at node K and reports the drift the nominal flight's
    loss sweep computes at K (same random draws before K): identical numbers."""
    loop0, summary0, code0, checks = nominal
    assert code0 == 0 and summary0["n_burns"] == 100 and "fault" not in summary0
    assert [k for k, _ in checks] == list(range(1, 101))  # 99 nodes + after the final burn
    k = 60
    loop, summary, code = _fly(seed=3, fault="loss", fault_node=k,
                               png_path=str(tmp_path / "loss.png"))
    f = summary["fault"]
    assert summary["outcome"] == "fault_loss" and summary["n_burns"] == k
    assert f["kind"] == "loss" and f["node"] == k and f["hit"] and f["n_checked"] == 1
    ref = checks[k - 1][1]
    assert f["min_margin_m"] == ref.min_margin_m and f["t_closest_s"] == ref.t_closest_s
    assert f["zone"] == ref.zone == "keep_out_zone"  # node 60 is past the switch at 55
    assert f["entered"] is False and code == 0
    assert (tmp_path / "loss.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_missed_burn_is_replanned_and_reaches_the_waypoint(nominal):
    loop0 = nominal[0]
    dv = np.linalg.norm([h.dv_cmd_mps for h in loop0.sim.history], axis=1)
    k = int(np.argmax(dv[1:]) + 1)  # the largest burn after the first
    loop, summary, code = _fly(seed=3, fault="missed", fault_node=k)
    f = summary["fault"]
    skipped = loop.sim.history[k]
    assert np.all(skipped.dv_mps == 0.0) and np.linalg.norm(skipped.dv_cmd_mps) == dv[k]
    assert f["kind"] == "missed" and f["hit"] and f["replans_after_fault"] >= 1
    assert summary["reached"] and summary["miss_m"] < 50.0
    assert f["n_checked"] == summary["n_burns"] - k and f["entered"] is False
    assert f["worst_node"] > k and code == 0


@pytest.mark.slow
def test_fault_beyond_the_run_is_reported_not_hit(nominal):
    _, summary, code = _fly(seed=3, errors=False, fault="loss", fault_node=500)
    assert summary["fault"]["hit"] is False and summary["fault"]["entered"] is None
    assert summary["reached"] and code == 0


# --------------------------------------------------------------------------- Monte Carlo
def test_clopper_pearson_upper_bound():
    assert upper_bound(0, 2000) == pytest.approx(1.0 - 0.05 ** (1 / 2000), rel=1e-9)
    assert upper_bound(0, 2000) < 1.5e-3
    assert upper_bound(3, 1000) == pytest.approx(7.7e-3, abs=1e-4)
    assert upper_bound(0, 0) is None and upper_bound(5, 5) == 1.0


@pytest.mark.slow
def test_monte_carlo_runs_resumes_and_summarises(tmp_path):
    spec = ContingencySpec(configs=((True, "cvx"),), n_seeds=1, base_seed=5,
                           missed_per_seed=1)
    out = tmp_path / "mc"
    s = run_mc(out, spec, workers=1, progress=False, log=lambda _: None)
    assert s["complete"] and s["flights_done"] == 1 and s["run"]["status"] == "complete"
    c = s["configs"][0]
    assert c["config"] == "chance/cvx" and c["losses"]["n"] == 100
    assert c["losses"]["entries"] == 0 and c["losses"]["min_margin_m"]["min"] > 0
    assert sum(c["losses"]["histogram_m"]["counts"]) == 100
    assert c["missed"]["n"] == 1 and c["missed"]["reached"] == 1
    assert c["missed"]["missed_burn_mps"]["min"] >= spec.min_missed_dv_mps
    names = ("contingency_margins.png", "contingency_worst.png", "summary.json")
    assert all((out / name).is_file() for name in names)
    again = run_mc(out, spec, workers=1, progress=False, log=lambda _: None, figures=False)
    assert again["run"]["status"] == "already_complete" and again["configs"] == s["configs"]
    with pytest.raises(InputError, match="--out"):
        run_mc(out, ContingencySpec(configs=((True, "cvx"),), n_seeds=2), workers=1,
               progress=False, log=lambda _: None)


def test_monte_carlo_identity_records_the_replan_policy(monkeypatch):
    """A Monte Carlo directory is tied to the replan policy its flights fly (the node's
    parameters, e.g. min_remaining_nodes from guidance_node.yaml): a resume under another
    policy is refused like one with other options, and the summary says which it was."""
    from art_guidance.config import GuidanceConfig
    from art_guidance.guidance.replan import ReplanSettings
    from art_guidance.sim import contingency, inprocess

    spec, config = ContingencySpec(), GuidanceConfig.load()
    head = contingency.header(spec, config)
    flown = InProcessGuidance(GuidancePipeline(config), 0)._settings  # what `fly` replans by
    assert head["contingency"]["replan"] == asdict(flown)
    assert head["contingency"]["replan"]["stamp_check"] == "order"
    monkeypatch.setattr(inprocess, "default_settings",
                        lambda scenario: ReplanSettings(min_remaining_nodes=2))
    other = contingency.header(spec, config)
    assert other["contingency"]["replan"]["min_remaining_nodes"] == 2
    assert other["config_sha256"] != head["config_sha256"]


def test_documented_tables_are_the_committed_results():
    """docs/fault_tolerance.md shows what benchmarks/results/contingency/summary.json says;
    regenerate with `python -m art_guidance.sim.contingency <summary.json>`."""
    from pathlib import Path

    from art_guidance.sim.contingency import markdown_table, table_in_doc

    root = Path(__file__).resolve().parents[2]
    summary = json.loads((root / "benchmarks/results/contingency/summary.json").read_text())
    doc = (root / "docs/fault_tolerance.md").read_text()
    assert table_in_doc(doc) == markdown_table(summary)
