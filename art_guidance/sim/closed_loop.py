"""The lockstep closed loop: truth simulator + guidance link, one step per plan node.

Loop: publish the nav fix at the current sim time; wait (wall-clock ``step_timeout_s``) for its
decision and, after "replanning", for its plan; adopt every plan received so far in arrival
order (a usable plan with valid arrays that the guidance put in force, its `active_plan_id`
its own or empty, becomes the active plan; an unusable one, or a usable one the guidance left
out of force, leaves the plan the guidance keeps in force, as the guidance does); execute the
active plan's burn whose epoch is within 1 s of now (each node once, with Gates errors); stop
after the burn at the active plan's final epoch; otherwise advance the truth to the plan's next
epoch. Without an active plan
the truth drifts for one nominal node spacing and the next fix is published (five rejected fixes
in a row without a plan end the run). The request and the first fix are re-sent every 2 s until
the first answer (over DDS a message published right after discovery can be lost). Plans
answering stamps this run never sent are ignored, and rejection notices do not count as replans.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.scenarios import sample_scenario
from art_guidance.dynamics import orbital_period_s
from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic
from art_guidance.planning import WARM_STARTS
from art_guidance.sim.faults import (
    ZONES, DriftCheck, Fault, free_drift_check, safety_duration_s,
)
from art_guidance.sim.link import GuidanceLink, LinkPlan
from art_guidance.sim.plot import plot_rendezvous
from art_guidance.sim.report import koz_switch_time_s, run_outcome, run_safety_model
from art_guidance.sim.simulator import EPOCH_MATCH_S, RendezvousSim

SIM_EPOCH0_NS = 1_000_000_000 * 1_000_000_000  # sim t = 0 is stamped 1e9 s (2001-09-09)
DECISIONS = ("replanning", "on_plan", "rejected")
MAX_REJECTED_IDLE = 5      # consecutive rejected fixes without an active plan -> give up
SETTLE_S = 0.2             # pause after discovery and after the replan request [s]
FIRST_RETRY_S = 2.0        # re-send the request and the first fix after this [s]
PARAMETERS: dict[str, object] = {
    "waypoint": "plus_vbar",
    "seed": 0,
    "chance_constrained": True,
    "warm_start": "auto",
    "step_timeout_s": 30.0,
    "max_steps": 200,
    "miss_tolerance_m": 50.0,
    "png_path": "out/rendezvous.png",
    "summary_path": "out/sim_summary.json",
    "errors": True,          # navigation (ARTMS) and actuation (Gates) errors
    "mean_elements": True,   # mean-element chief model and mean-ROE navigation (sim.py)
    "config_dir": "",        # "" = packaged config/
    "epoch0_s": SIM_EPOCH0_NS // 1_000_000_000,  # stamp of sim t = 0 [s]
    "fault": "",             # "" (none), "loss" or "missed" (sim/faults.py)
    "fault_node": 1,         # K: the burn opportunity the fault hits (0 = the first)
}
FLOAT_PARAMETERS = ("step_timeout_s", "miss_tolerance_m")
WAITING_LINE = "waiting for a guidance node"  # logged as a run starts (`ClosedLoop.run`)


@dataclass(frozen=True)
class Snapshot:
    """Truth at one instant of a run: sim time [s] and (6,) inertial states [m, m/s]."""

    t_s: float
    chief_eci: np.ndarray
    deputy_eci: np.ndarray


@dataclass(frozen=True)
class FlownPlan:
    """The plan the simulator flies (the guidance's plan in force), in sim time.

    Attributes:
        stamp_ns: the plan's header stamp (the nav stamp it answers) [ns].
        plan_id: the guidance's plan id.
        epochs_s: (N,) absolute node epochs in sim time [s].
        dv_rtn_mps: (N, 3) delta-v per node [m/s].
        rtn: (N, 6) predicted RTN trajectory, or None if the plan carries none.
    """

    stamp_ns: int
    plan_id: str
    epochs_s: np.ndarray
    dv_rtn_mps: np.ndarray
    rtn: np.ndarray | None

    def index_at(self, t_s: float) -> int | None:
        """Index of the node within EPOCH_MATCH_S of `t_s` (the closest), or None."""
        k = int(np.argmin(np.abs(self.epochs_s - t_s)))
        return k if abs(self.epochs_s[k] - t_s) <= EPOCH_MATCH_S else None

    def next_epoch_after(self, t_s: float) -> float | None:
        """First node epoch later than `t_s` + EPOCH_MATCH_S [s], or None."""
        later = self.epochs_s[self.epochs_s > t_s + EPOCH_MATCH_S]
        return float(later[0]) if later.size else None


def sim_time_s(stamp_ns: int, epoch0_ns: int = SIM_EPOCH0_NS) -> float:
    """Sim time [s] of a stamp [ns]."""
    return (int(stamp_ns) - int(epoch0_ns)) * 1e-9


def sim_stamp_ns(t_s: float, epoch0_ns: int = SIM_EPOCH0_NS) -> int:
    """Stamp [ns] of a sim time [s]."""
    return int(epoch0_ns) + int(round(float(t_s) * 1e9))


def parse_plan(msg: LinkPlan, epoch0_ns: int = SIM_EPOCH0_NS) -> FlownPlan:
    """Validate a plan's arrays and convert its epochs to sim time.

    Raises:
        InputError: on empty, non-finite, mis-sized arrays or non-increasing epochs.
    """
    epochs = np.asarray(msg.epochs_s, dtype=float)
    n = epochs.size
    if n == 0 or not np.all(np.isfinite(epochs)) or np.any(np.diff(epochs) <= 0):
        raise InputError("epochs_s", "need >= 1 finite, strictly increasing epochs", n)
    dv = np.asarray(msg.dv_rtn_mps, dtype=float)
    if dv.size != 3 * n or not np.all(np.isfinite(dv)):
        raise InputError("dv_rtn_mps", f"need {3 * n} finite values", dv.size)
    rtn = np.asarray(msg.rtn, dtype=float)
    rtn_ok = rtn.size == 6 * n and np.all(np.isfinite(rtn))
    return FlownPlan(msg.stamp_ns, msg.plan_id, sim_time_s(msg.stamp_ns, epoch0_ns) + epochs,
                     dv.reshape(n, 3), rtn.reshape(n, 6) if rtn_ok else None)


def exit_code(outcome: str, miss_m: float, tolerance_m: float) -> int:
    """0 if the run reached the active plan's final epoch within tolerance, else 1."""
    return 0 if outcome == "final_epoch" and miss_m <= tolerance_m else 1


def fault_exit_code(fault: dict | None, reached: bool) -> int:
    """Exit code of a run: 0 when it reached the waypoint (`exit_code`) or, after a loss
    fault, when the drift stayed outside the ellipsoid; a missed fault also needs no post-fault
    drift to enter it. A fault the run never reached leaves the plain rule."""
    if fault is None or not fault["hit"]:
        return 0 if reached else 1
    if fault["kind"] == "loss":
        return 0 if fault["entered"] is False else 1
    return 0 if reached and not fault["entered"] else 1


class ClosedLoop:
    """The lockstep loop over a guidance link.

    Args:
        link: the guidance (over DDS or in-process).
        params: the simulator's parameters (`ros.sim_node.PARAMETERS` names and meanings).
        log: anything with info / warning / error methods (an rclpy or a `logging` logger).
        settle_s: pause after discovery and after the replan request [s] (0 in-process).
    """

    def __init__(self, link: GuidanceLink, params: dict[str, Any], log: Any,
                 settle_s: float = SETTLE_S) -> None:
        p = self.p = params
        self.settle_s = settle_s
        self.link = link
        self.log = log
        cfg_dir = p["config_dir"] or None
        path = (lambda f: None) if cfg_dir is None else (lambda f: Path(cfg_dir) / f)
        self.scenario = ScenarioConfig.from_yaml(path("scenario.yaml"))
        if p["waypoint"] not in self.scenario.waypoints_rtn:
            raise InputError("waypoint", f"unknown; choose from "
                             f"{sorted(self.scenario.waypoints_rtn)}", p["waypoint"])
        for name in ("step_timeout_s", "miss_tolerance_m"):
            if not p[name] > 0:
                raise InputError(name, "must be > 0", p[name])
        if int(p["max_steps"]) < 1:
            raise InputError("max_steps", "must be >= 1", p["max_steps"])
        if p["warm_start"] not in WARM_STARTS:
            raise InputError("warm_start", f"must be one of {WARM_STARTS}", p["warm_start"])
        self.target = np.asarray(self.scenario.waypoints_rtn[p["waypoint"]], dtype=float)
        rtn0 = p["rtn0"]
        if rtn0 is None:
            rtn0 = sample_scenario(self.scenario, int(p["seed"])).rtn0
        uncertainty = UncertaintyConfig.from_yaml(path("uncertainty.yaml")) if p["errors"] \
            else None
        self.sim = RendezvousSim(self.scenario, uncertainty, rtn0, int(p["seed"]),
                                 mean_elements=bool(p["mean_elements"]))
        a_m = float(self.sim.chief_mean_oe0[0])
        self.idle_dt_s = (self.scenario.n_orbits * orbital_period_s(a_m)
                          / (self.scenario.n_nodes - 1))
        self.active: FlownPlan | None = None
        self.first_plan_t_s: float | None = None
        self.executed: set[tuple[int, int]] = set()
        self.sent: set[int] = set()  # nav stamps published by this run
        self.counts = {"steps": 0, "plans_received": 0, "replans": 0, "plans_failed": 0,
                       "replans_kept_active": 0, "replans_not_in_force": 0,
                       "plans_foreign": 0, "idle_steps": 0, **{d: 0 for d in DECISIONS}}
        self._seen_plans = 0
        self.fault = Fault.parse(str(p.get("fault", "")), int(p.get("fault_node", 0)))
        self.snapshots: list[Snapshot] = []  # truth at every burn opportunity (pre-burn)
        self.final_state: Snapshot | None = None  # truth right after the final burn
        self.fault_t_s: float | None = None
        self.replans_after_fault = 0

    # ------------------------------------------------------------------ loop
    def run(self) -> str:
        """Run to the end; returns the outcome (final_epoch, max_steps, no_guidance, ...)."""
        p = self.p
        timeout = p["step_timeout_s"]
        self.log.info(f"{WAITING_LINE} (up to {timeout:g} s)")
        if not self.link.wait_matched(timeout):
            self.log.error("no guidance node matched (nav/relative_state, "
                           "guidance/maneuver_plan, /diagnostics)")
            return "no_guidance"
        time.sleep(self.settle_s)
        self._publish_request()
        time.sleep(self.settle_s)
        rejected_idle = 0
        for _ in range(int(p["max_steps"])):
            self.counts["steps"] += 1
            sim = self.sim
            self.link.publish_truth(sim.trajectory_t_s, sim.trajectory_rtn)
            stamp = sim_stamp_ns(sim.t_s, self.link.epoch0_ns)
            self.sent.add(stamp)
            roe, cov = sim.nav_estimate()
            self.link.publish_nav(stamp, sim.chief_mean_oe(), roe, cov)
            if self.counts["steps"] == 1:
                values = self._first_decision(stamp, sim.chief_mean_oe(), roe, cov, timeout)
            else:
                values = self.link.wait_decision(stamp, timeout)
            if values is None:
                self.log.error(f"no decision for nav stamp {stamp} within {timeout} s")
                return "timeout_decision"
            decision = values.get("decision", "")
            self.counts[decision if decision in DECISIONS else "on_plan"] += 1
            if decision == "rejected":
                self.log.warning(f"nav at t = {sim.t_s:.1f} s rejected: "
                                 f"{values.get('reason', '')}")
            if decision == "replanning" and not self.link.wait_plan(stamp, timeout):
                self.log.error(f"no plan for nav stamp {stamp} within {timeout} s")
                return "timeout_plan"
            self._adopt_plans()
            if self.active is None:
                rejected_idle = rejected_idle + 1 if decision == "rejected" else 0
                if rejected_idle >= MAX_REJECTED_IDLE:
                    self.log.error("every nav fix is rejected: a guidance node with its "
                                   "wall-clock stamp check (use -p stamp_check:=order) or one "
                                   "that saw later stamps (restart it or raise epoch0_s)?")
                    return "rejected"
                self.counts["idle_steps"] += 1
                sim.advance(self.idle_dt_s)
                continue
            rejected_idle = 0
            ended = self._burn_now()
            if ended is not None:
                return ended
            nxt = self.active.next_epoch_after(sim.t_s)
            if nxt is None:
                return "plan_ended"
            sim.advance(nxt - sim.t_s)
        return "max_steps"

    def _first_decision(self, stamp: int, chief_oe: np.ndarray, roe: np.ndarray,
                        cov: np.ndarray, timeout_s: float) -> dict[str, str] | None:
        """Wait for the first answer, re-sending request and fix every FIRST_RETRY_S.

        Right after discovery the guidance side may not have matched our writers yet, and a
        volatile reader never sees what was published before it matched. A repeated fix has
        the same stamp: the guidance answers the first copy it gets (a later copy is stale to
        it), and only the first answer per stamp counts here.
        """
        end = time.monotonic() + timeout_s
        while True:
            left = end - time.monotonic()
            values = self.link.wait_decision(stamp, min(FIRST_RETRY_S, max(left, 0.0)))
            if values is not None or left <= FIRST_RETRY_S:
                return values
            self.log.warning("no answer to the first nav fix yet; sending request and fix "
                             "again")
            self._publish_request()
            time.sleep(self.settle_s)
            self.link.publish_nav(stamp, chief_oe, roe, cov)

    def _publish_request(self) -> None:
        p = self.p
        self.link.publish_request(p["waypoint"], bool(p["chance_constrained"]), p["warm_start"])

    def _adopt_plans(self) -> None:
        """Count new plans; the newest usable one (arrival order) becomes active."""
        for msg in self.link.take_plans(self._seen_plans):
            self._seen_plans += 1
            self.counts["plans_received"] += 1
            if msg.stamp_ns not in self.sent:
                self.counts["plans_foreign"] += 1  # answers a fix this run never sent
                continue
            if msg.rejection:
                continue  # the answer to a rejected nav fix, not a replan
            self.counts["replans"] += 1
            if self.fault_t_s is not None:
                self.replans_after_fault += 1
            if not msg.status.feasible:
                kept = self.active is not None and msg.active_plan_id == self.active.plan_id
                # the guidance keeps the plan in force: so does the simulator
                self.counts["replans_kept_active" if kept else "plans_failed"] += 1
                self.log.warning(f"plan {msg.plan_id} not usable: {msg.status_text}")
                continue
            if msg.active_plan_id not in ("", msg.plan_id):
                # usable, but the guidance left it out of force (the end game's cost cap):
                # the plan it names stays the one flown
                self.counts["replans_not_in_force"] += 1
                self.log.info(f"plan {msg.plan_id} not put in force: {msg.status_text}")
                continue
            try:
                plan = parse_plan(msg, self.link.epoch0_ns)
            except InputError as exc:
                self.counts["plans_failed"] += 1
                self.log.warning(f"plan {msg.plan_id} malformed: {exc}")
                continue
            if self.active is not None and plan.stamp_ns < self.active.stamp_ns:
                continue  # an older answer arriving late
            self.active = plan
            if self.first_plan_t_s is None:
                self.first_plan_t_s = sim_time_s(plan.stamp_ns, self.link.epoch0_ns)
            self.log.info(f"t = {self.sim.t_s:.1f} s: active plan {plan.plan_id} "
                          f"({plan.epochs_s.size} nodes, cost "
                          f"{np.linalg.norm(plan.dv_rtn_mps, axis=1).sum():.4f} m/s)")

    def _burn_now(self) -> str | None:
        """Execute the active plan's burn at the current time (each node once) or the fault
        that hits it; the outcome once the run ends here ("final_epoch", "fault_loss")."""
        plan = self.active
        k = plan.index_at(self.sim.t_s)
        if k is None or (plan.stamp_ns, k) in self.executed:
            return None
        self.executed.add((plan.stamp_ns, k))
        sim = self.sim
        node = len(self.snapshots)  # burn opportunities reached before this one
        self.snapshots.append(Snapshot(sim.t_s, sim.chief_eci.copy(), sim.deputy_eci.copy()))
        hit = self.fault is not None and self.fault.node == node
        if hit:
            self.fault_t_s = sim.t_s
            self.log.warning(f"t = {sim.t_s:.1f} s: fault '{self.fault.kind}' at node {node} "
                             f"(planned burn {np.linalg.norm(plan.dv_rtn_mps[k]):.4f} m/s)")
            if self.fault.kind == "loss":
                return "fault_loss"
            sim.skip_burn(plan.dv_rtn_mps[k])
        else:
            sim.execute_burn(plan.dv_rtn_mps[k])
        if k < plan.epochs_s.size - 1:
            return None
        self.final_state = Snapshot(sim.t_s, sim.chief_eci.copy(), sim.deputy_eci.copy())
        return "final_epoch"

    # ------------------------------------------------------------------ free-drift checks
    def zone_at(self, t_s: float) -> str:
        """The ellipsoid in force at sim time `t_s` (the guidance's switch rule)."""
        switch = koz_switch_time_s(self.scenario, self.sim.chief_mean_oe0[0],
                                   self.first_plan_t_s or 0.0)
        return ZONES[1] if t_s >= switch - EPOCH_MATCH_S else ZONES[0]

    def drift_check(self, state: Snapshot) -> DriftCheck:
        """Truth free drift for T_safety from `state` against the ellipsoid in force then."""
        duration = safety_duration_s(self.scenario, self.sim.chief_mean_oe0[0])
        return free_drift_check(state.chief_eci, state.deputy_eci, state.t_s, duration,
                                self.scenario, self.zone_at(state.t_s))

    def loss_checks(self, first_node: int = 1) -> list[tuple[int, DriftCheck]]:
        """A thruster loss at every node from `first_node` on, checked in truth.

        A loss at node K (no burn from K on) leaves the deputy drifting from the truth state
        the run reached at K, before its burn: the same state a run with `fault` loss at K
        ends in (the random draws before K are the same). The node after the last one (K =
        number of nodes flown) is the drift after the final burn. Nodes passed by a fault are
        not included (a loss run ends at its fault; nothing later was flown).
        """
        return [(k, self.drift_check(s)) for k, s in self.loss_states(first_node)]

    def loss_states(self, first_node: int = 1) -> list[tuple[int, Snapshot]]:
        """The truth state a loss at each node from `first_node` on drifts from (the pre-burn
        snapshots, then the state after the final burn), as (node, state)."""
        states = list(enumerate(self.snapshots))
        if self.final_state is not None:
            states.append((len(self.snapshots), self.final_state))
        return [(k, s) for k, s in states if k >= first_node]

    def fault_report(self) -> tuple[dict | None, DriftCheck | None]:
        """The summary's `fault` object (None without a fault) and its worst drift.

        loss: the drift from the state at the fault. missed: the worst loss check over the
        nodes flown after the fault (K + 1 on): no post-fault plan may drift into the
        ellipsoid in force. Margins in metres outside the ellipsoid, negative inside.
        """
        fault = self.fault
        if fault is None:
            return None, None
        out: dict = {"kind": fault.kind, "node": fault.node, "t_fault_s": self.fault_t_s,
                     "hit": self.fault_t_s is not None}
        if self.fault_t_s is None:
            out.update(min_margin_m=None, t_closest_s=None, entered=None, zone=None,
                       n_checked=0)
            return out, None
        if fault.kind == "loss":
            checks = [(fault.node, self.drift_check(self.snapshots[fault.node]))]
        else:
            checks = self.loss_checks(fault.node + 1)
            out["replans_after_fault"] = self.replans_after_fault
        out["n_checked"] = len(checks)
        if not checks:
            out.update(min_margin_m=None, t_closest_s=None, entered=None, zone=None)
            return out, None
        worst_node, worst = min(checks, key=lambda kc: kc[1].min_margin_m)
        out.update(worst.to_json(), entered=any(c.entered for _, c in checks),
                   worst_node=worst_node)
        return out, worst

    # ------------------------------------------------------------------ report
    def finish(self, outcome: str, wall_s: float) -> tuple[dict, int]:
        """Summary dict and exit code; writes the JSON summary and the PNG."""
        p = self.p
        switch = koz_switch_time_s(self.scenario, self.sim.chief_mean_oe0[0],
                                   self.first_plan_t_s or 0.0)
        summary = run_outcome(self.sim, self.target,
                              run_safety_model(self.sim, koz_switch_t_s=switch),
                              self.counts["replans"])
        reached = exit_code(outcome, summary["miss_m"], p["miss_tolerance_m"]) == 0
        fault, drift = self.fault_report()
        code = fault_exit_code(fault, reached)
        summary.update(
            outcome=outcome, reached=reached, waypoint=p["waypoint"], seed=int(p["seed"]),
            chance_constrained=bool(p["chance_constrained"]),
            miss_tolerance_m=p["miss_tolerance_m"], errors=bool(p["errors"]),
            mean_elements=bool(p["mean_elements"]), wall_time_s=round(wall_s, 3),
            png_path=p["png_path"] or None, **{f"n_{k}": v for k, v in self.counts.items()
                                               if k != "replans"})
        if fault is not None:
            summary["fault"] = fault
        if p["png_path"]:
            plot_rendezvous(p["png_path"], self.sim, self.scenario,
                            None if self.active is None else self.active.rtn,
                            target_rtn=self.target, summary=summary, fault_drift=drift)
        if p["summary_path"]:
            write_json_atomic(p["summary_path"], summary)
        return summary, code
