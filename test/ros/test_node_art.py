"""The guidance node with a learned warm start, over real DDS: a model that fails to load
leaves the node planning from CVX (one warning, a diagnostic, plans that say so); a loaded
model's rollouts go through the post hoc check, are recorded, and the log replays."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from contextlib import contextmanager

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")
from art_guidance_msgs.msg import ManeuverPlan  # noqa: E402
from helpers.art_models import write_untrained_checkpoint  # noqa: E402
from helpers.processes import interrupt  # noqa: E402
from helpers.ros_client import Client  # noqa: E402

from art_guidance.config import ScenarioConfig  # noqa: E402
from art_guidance.record.replay import read_log, replay  # noqa: E402

pytestmark = pytest.mark.ros
NOMINAL_RTN = np.array(ScenarioConfig().rtn0_nominal)


@contextmanager
def _node(ros_env, python_exe, namespace: str, *params: str):
    args = [python_exe, "-m", "art_guidance.ros.guidance_node", "--ros-args",
            "-r", f"__ns:=/{namespace}", "-p", "solve_deadline_s:=20"]
    for p in params:
        args += ["-p", p]
    proc = subprocess.Popen(args, env=ros_env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    client = Client(f"{namespace}_client", namespace=f"/{namespace}")
    try:
        assert client.wait_matched(60.0), "guidance node did not match within 60 s"
        yield proc, client
    finally:
        client.close()
        interrupt(proc, 30)


def _plan_diag(client: Client, plan_id: str) -> dict:
    def find(_, diags):
        for _, values, name in reversed(diags):
            if name == "art_guidance/plan" and values.get("plan_id") == plan_id:
                return values
        return None
    return client.wait_for(find, 10.0)


def test_a_corrupt_model_leaves_the_node_in_cvx_only_mode(ros_env, python_exe, tmp_path):
    model = tmp_path / "model.pt"
    write_untrained_checkpoint(model)
    blob = bytearray(model.read_bytes())
    blob[-100] ^= 0xFF
    model.write_bytes(bytes(blob))
    with _node(ros_env, python_exe, "corrupt", f"model_path:={model}", "record:=false") as (
            proc, client):
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning"
        plan = client.plan_for(stamp, 60.0)
        assert plan is not None and plan.status == ManeuverPlan.STATUS_CONVERGED
        assert plan.warm_start == "cvx" and plan.posthoc == ManeuverPlan.POSTHOC_NOT_RUN
        assert math.isnan(plan.posthoc_e_r) and "no learned model" in plan.warm_start_reason
        diag = _plan_diag(client, plan.plan_id)
        assert diag["model"].startswith("cvx-only: the model did not load")
        assert "corrupt" in diag["model"]
        assert proc.poll() is None  # still serving
    out = proc.stdout.read()
    assert out.count("learned warm start unavailable") == 1, out[-3000:]
    assert "Traceback" not in out


@pytest.mark.parametrize("concurrent", [False, True], ids=["in_line", "worker_process"])
def test_learned_warm_start_is_checked_recorded_and_replayed(ros_env, python_exe, tmp_path,
                                                             concurrent):
    """Also with the proposal made in a worker process (`propose_concurrently`): the node
    starts it at configure, and the log replays in line to the same plans."""
    model, bag = tmp_path / "model.pt", tmp_path / "bag"
    sha = write_untrained_checkpoint(model)
    with _node(ros_env, python_exe, f"learned{int(concurrent)}", f"model_path:={model}",
               f"record_dir:={bag}", "replan_sigma_threshold:=1e-9", "endgame:=none",
               "replan_warm_start:=fresh",  # a fix on the plan's grid would be carried
               f"propose_concurrently:={str(concurrent).lower()}") as (proc, client):
        plans = []
        for offset in (0.0, 300.0):
            stamp, decision = client.send_nav(NOMINAL_RTN + [0.0, offset, 0, 0, 0, 0])
            assert decision == "replanning"
            plans.append(client.plan_for(stamp, 60.0))
        for plan in plans:
            assert plan is not None and plan.posthoc in (ManeuverPlan.POSTHOC_ACCEPTED,
                                                         ManeuverPlan.POSTHOC_REJECTED)
            assert math.isfinite(plan.posthoc_e_r) and plan.posthoc_e_c >= 0
            assert "post hoc check" in plan.warm_start_reason
            diag = _plan_diag(client, plan.plan_id)
            assert diag["model_sha256"] == sha and float(diag["art_ms"]) > 0.0
            assert diag["model"].startswith("loaded model.pt")
    assert proc.returncode == 0
    out = proc.stdout.read()
    assert ("made in a worker process" in out) == concurrent, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    log = read_log(bag)
    assert log.metadata["model_checksum"] == sha
    records = log.of_type("art_guidance_msgs/msg/SolveRecord")
    assert len(records) == 2 and all(r.model_sha256 == sha for r in records)
    assert all(len(r.warm_start_art_dv_rtn_mps) == 300 for r in records)
    assert all(r.timing_model_load_ms > 0.0 and r.timing_art_ms > 0.0 for r in records)
    report = replay(bag, model)
    assert report["compared"] == 2 and report["matched"] == 2, report


def test_an_equatorial_chief_is_refused_and_planning_goes_on(ros_env, python_exe):
    """The sequence that once stopped the node for good (shipped model, proposal worker): a
    valid fix, a fix whose chief inclination is 1e-300 rad (its plan overflowed to NaN in SCVx*
    while the proposal was out, and the worker stayed held), then valid fixes and a replan
    request. The bad fix is refused at validation with the reason; every later fix is planned
    and published; SIGINT stops the node (exit 0)."""
    from art_guidance_msgs.msg import ReplanRequest

    # every fix replans (the end game would keep the plan in force from a fix on target)
    with _node(ros_env, python_exe, "equatorial", "record:=false", "endgame:=none",
               "replan_sigma_threshold:=1e-9", "propose_concurrently:=true") as (proc, client):
        stamp, decision = client.send_nav(NOMINAL_RTN)
        assert decision == "replanning"
        assert client.plan_for(stamp, 60.0) is not None
        chief = np.array(ScenarioConfig().chief_oe)
        chief[2] = 1e-300
        stamp, decision = client.send_nav(NOMINAL_RTN + [0, 100.0, 0, 0, 0, 0], chief_oe=chief)
        assert decision == "rejected"
        plan = client.plan_for(stamp, 10.0)
        assert plan.status == ManeuverPlan.STATUS_REJECTED_INPUT
        assert "inclination" in plan.status_text, plan.status_text
        for offset in (200.0, 300.0):
            stamp, decision = client.send_nav(NOMINAL_RTN + [0, offset, 0, 0, 0, 0])
            assert decision == "replanning"
            plan = client.plan_for(stamp, 60.0)
            assert plan is not None and plan.status == ManeuverPlan.STATUS_CONVERGED
            diag = _plan_diag(client, plan.plan_id)
            assert diag["proposal_worker"] in ("running", "loading the model"), diag
            made, taken = (int(diag[k]) for k in ("proposal_worker_scvx_runs",
                                                  "proposal_worker_scvx_runs_taken"))
            assert 0 <= taken <= made, diag
        client.req_pub.publish(ReplanRequest(waypoint="minus_vbar", chance_constrained=True))
        assert client.plan_for(stamp, 60.0) is not None
        assert client.wait_for(lambda plans, _: sum(
            p.status == ManeuverPlan.STATUS_CONVERGED for _, p in plans) >= 4, 60.0)
    assert proc.returncode == 0
    out = proc.stdout.read()
    assert "Traceback" not in out, out[-3000:]


def test_a_non_default_planning_yaml_replays_as_flown(ros_env, python_exe, tmp_path):
    """Replay rebuilds the pipeline from what the bag recorded: a planning.yaml that judges
    the candidates on the rollout itself (`posthoc_subject: rollout`), with a wider post hoc
    region and `art_min_gain_mps: 0`, changes which candidate is proposed and whether it is
    accepted; the replay ranks them the same way and every solve matches. The recorded
    configuration is sealed: a bag whose configuration was altered afterwards is reported
    (`config_check`) and replay exits 1."""
    from mcap.records import Metadata

    from art_guidance.config import default_config_dir
    from art_guidance.record.reindex import rebuild
    from art_guidance.record.replay import EXIT_MISMATCH, EXIT_OK
    from art_guidance.record.scan import scan_file

    config = tmp_path / "config"
    shutil.copytree(default_config_dir(), config)
    planning = yaml.safe_load((config / "planning.yaml").read_text())
    planning.update(posthoc_subject="rollout", art_min_gain_mps=0.0)
    planning["posthoc"] = {**planning["posthoc"], "e_r_pct_max": 50.0, "e_c_max": 20.0}
    (config / "planning.yaml").write_text(yaml.safe_dump(planning))
    model, bag = tmp_path / "model.pt", tmp_path / "bag"
    write_untrained_checkpoint(model)
    with _node(ros_env, python_exe, "nondefault", f"model_path:={model}", f"record_dir:={bag}",
               f"config_dir:={config}", "replan_sigma_threshold:=1e-9", "endgame:=none",
               "replan_warm_start:=fresh", "propose_concurrently:=false") as (proc, client):
        for offset in (0.0, 300.0, 600.0):
            stamp, decision = client.send_nav(NOMINAL_RTN + [0.0, offset, 0, 0, 0, 0])
            assert decision == "replanning"
            assert client.plan_for(stamp, 60.0) is not None
    report = replay(bag, model)
    assert report["config_check"] == "ok" and report["exit_code"] == EXIT_OK, report
    assert report["compared"] == 3 and report["matched"] == 3, report
    path = bag / "guidance_0.mcap"
    scan = scan_file(path)
    altered = []
    for record in scan.metadata:
        values = dict(record.metadata)
        if "config" in values:
            data = json.loads(values["config"])
            data["planning"]["art_min_gain_mps"] = 0.5
            values["config"] = json.dumps(data)
        altered.append(Metadata(name=record.name, metadata=values))
    scan.metadata = altered
    rebuild(path, scan)
    report = replay(bag, model)
    assert "altered after recording" in report["config_check"], report["config_check"]
    assert report["exit_code"] == EXIT_MISMATCH
