"""A stand-in guidance node that follows the simulator protocol trivially (separate process).

For every nav fix it publishes a DiagnosticStatus "art_guidance/nav" with `nav_stamp_ns` and
`decision`, and after "replanning" a ManeuverPlan stamped with the nav stamp. A fix before any
replan request is rejected (with a STATUS_REJECTED_INPUT plan, as the real node does).

Modes:
  handmade  the first fix after the request gets a 3-node plan (epochs 0, 300, 600 s) with
            three 1 mm/s burns; later fixes are "on_plan".
  pipeline  GuidancePipeline plans the full horizon on the first fix and replans the remaining
            horizon every `--replan-every` fixes (while >= 3 nodes remain).
`--drop-first N` ignores the first N fixes (a message lost right after discovery).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from helpers.spin_main import spin_until_shutdown

from art_guidance import topics
from art_guidance.config import ScenarioConfig
from art_guidance.dynamics import Horizon, orbital_period_s
from art_guidance.planning import GuidancePipeline, PlanRequest
from art_guidance.ros.adapters import MSG_STATUS

HANDMADE_EPOCHS_S = (0.0, 300.0, 600.0)
HANDMADE_DV_MPS = ((0.0, 1e-3, 0.0), (1e-3, 0.0, 0.0), (0.0, -1e-3, 0.0))


class FakeGuidance(Node):
    def __init__(self, mode: str, replan_every: int, drop_first: int = 0) -> None:
        super().__init__("fake_guidance")
        self.mode, self.replan_every, self.drop_first = mode, replan_every, drop_first
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.plan_pub = self.create_publisher(ManeuverPlan, topics.MANEUVER_PLAN, qos)
        self.diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos)
        self.create_subscription(RelativeNavState, topics.NAV, self._on_nav, qos)
        self.create_subscription(ReplanRequest, topics.REPLAN_REQUEST, self._on_request,
                                 qos)
        self.request: ReplanRequest | None = None
        self.scenario = ScenarioConfig.from_yaml()
        self.pipeline = GuidancePipeline() if mode == "pipeline" else None
        self.active: tuple[int, np.ndarray] | None = None  # (t0_ns, epochs_s)
        self.navs_since_plan = 0
        self.n_plans = 0
        self.first_t0_ns = 0

    def _on_request(self, msg: ReplanRequest) -> None:
        self.request = msg
        self.active = None

    def _on_nav(self, msg: RelativeNavState) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if self.drop_first > 0:  # as if the message had been lost
            self.drop_first -= 1
            return
        if self.request is None:
            self._diag(stamp, "rejected", "no replan request yet")
            self.plan_pub.publish(self._plan_msg(stamp, ManeuverPlan.STATUS_REJECTED_INPUT))
            return
        self.navs_since_plan += 1
        chief = np.asarray(msg.chief_oe, float)
        job = self._job(stamp, float(chief[0]))
        if job is None:
            self._diag(stamp, "on_plan")
            return
        self._diag(stamp, "replanning")
        roe = np.asarray(msg.mean, float)
        if self.mode == "handmade":
            epochs = np.asarray(HANDMADE_EPOCHS_S)
            dv = np.asarray(HANDMADE_DV_MPS)
            horizon = Horizon.build(chief, epochs)
            roe_m = horizon.propagate(roe, dv)
            out = self._plan_msg(stamp, ManeuverPlan.STATUS_CONVERGED, epochs, dv, roe_m,
                                 horizon.to_rtn(roe_m))
        else:
            n_nodes, n_orbits, switch = job
            target = np.asarray(self.scenario.waypoints_rtn[self.request.waypoint])
            res = self.pipeline.plan(PlanRequest(
                chief, roe, target, chance_constrained=self.request.chance_constrained,
                warm_start="cvx", n_nodes=n_nodes, n_orbits=n_orbits, koz_switch_node=switch))
            epochs = res.epochs_s
            out = self._plan_msg(stamp, MSG_STATUS[res.status], epochs, res.dv_rtn_mps,
                                 res.roe_m, res.rtn)
        if self.active is None:
            self.first_t0_ns = stamp
        self.active = (stamp, epochs)
        self.navs_since_plan = 0
        self.n_plans += 1
        out.plan_id = f"fake-{self.n_plans}"
        self.plan_pub.publish(out)

    def _job(self, stamp: int, chief_a_m: float
             ) -> tuple[int | None, float | None, int | None] | None:
        """None = on_plan; else (n_nodes, n_orbits, koz switch node) of the replan."""
        if self.active is None:
            return (None, None, None)
        if self.mode == "handmade" or self.navs_since_plan < self.replan_every:
            return None
        t0, epochs = self.active
        dt = float(epochs[1] - epochs[0])
        remaining = (t0 - stamp) * 1e-9 + float(epochs[-1])
        n_nodes = int(round(remaining / dt)) + 1
        if n_nodes < 3:
            return None
        elapsed = int(round((stamp - self.first_t0_ns) * 1e-9 / dt))
        switch = max(0, self.scenario.ae_to_koz_node - elapsed)
        return n_nodes, (n_nodes - 1) * dt / orbital_period_s(chief_a_m), switch

    @staticmethod
    def _plan_msg(stamp: int, status: int, epochs=(), dv=None, roe=None, rtn=None):
        out = ManeuverPlan()
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        out.header.frame_id = "chief_rtn"
        out.status = status
        out.status_text = "fake"
        out.epochs_s = [float(v) for v in epochs]
        if dv is not None:
            out.dv_rtn_mps = [float(v) for v in np.ravel(dv)]
            out.roe_m = [float(v) for v in np.ravel(roe)]
            out.rtn = [float(v) for v in np.ravel(rtn)]
            out.cost_mps = float(np.linalg.norm(dv, axis=1).sum())
        return out

    def _diag(self, stamp: int, decision: str, reason: str = "") -> None:
        arr = DiagnosticArray()
        st = DiagnosticStatus()
        st.name, st.hardware_id, st.message = "art_guidance/nav", "fake", decision
        st.values = [KeyValue(key="nav_stamp_ns", value=str(stamp)),
                     KeyValue(key="decision", value=decision)]
        if reason:
            st.values.append(KeyValue(key="reason", value=reason))
        arr.status = [st]
        self.diag_pub.publish(arr)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=["handmade", "pipeline"], default="handmade")
    parser.add_argument("--replan-every", type=int, default=10)
    parser.add_argument("--drop-first", type=int, default=0, help="ignore the first N fixes")
    args = parser.parse_args()
    return spin_until_shutdown(
        lambda: FakeGuidance(args.mode, args.replan_every, args.drop_first),
        "fake guidance ready")


if __name__ == "__main__":
    sys.exit(main())
