"""A flight install: `pip install art_guidance` without the [train] extra has no torch and no
onnx. In child interpreters where importing either fails (`helpers.flight`, not merely unused)
the guidance node and the simulator fly a closed loop over DDS with the learned warm start on
ONNX Runtime (the shipped exported model) and record it; `replay`, `bag reindex`, `bag render`
and `plan` run on that record; `train`, `export`, `distill` and `dagger` answer with the extra
to install (exit 2, no traceback). setup.py keeps torch and onnx in the extra.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys

import pytest
from helpers.flight import FLIGHT_BLOCKED, REPO, blocked_env, blocker_site
from helpers.processes import interrupt, stop_cleanly

# replay, bag reindex, bag render and plan in one interpreter of the flight install
_AFTER_FLIGHT = """
import contextlib, io, json, sys
from art_guidance.cli import main
bag, out = sys.argv[1], sys.argv[2]
codes = {}
for name, argv in (("replay", ["replay", bag, "--json", out + "/replay.json"]),
                   ("reindex", ["bag", "reindex", bag]),
                   ("render", ["bag", "render", bag, "--png", out + "/bag.png"]),
                   ("plan", ["plan", "--seed", "3", "--warm-start", "art",
                             "--json", out + "/plan.json"])):
    with contextlib.redirect_stdout(io.StringIO()):
        codes[name] = main(argv)
loaded = sorted({m.partition(".")[0] for m in sys.modules} & {"torch", "onnx", "onnxruntime"})
print(json.dumps({"codes": codes, "loaded": loaded}))
"""


@pytest.mark.ros
def test_node_simulator_replay_bag_and_plan_fly_without_torch_or_onnx(second_ros_env, tmp_path):
    pytest.importorskip("rclpy")
    env = blocked_env(blocker_site(tmp_path), second_ros_env)
    bag, summary = tmp_path / "bag", tmp_path / "summary.json"
    node = subprocess.Popen([sys.executable, "-m", "art_guidance.ros.guidance_node",
                             "--ros-args", "-p", "stamp_check:=order",
                             "-p", f"record_dir:={bag}"],
                            env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    sim = None
    try:
        sim = subprocess.run([sys.executable, "-m", "art_guidance.cli", "sim", "--seed", "1",
                              "--max-steps", "3", "--png", "", "--summary-json", str(summary)],
                             env=env, cwd=tmp_path, capture_output=True, text=True, timeout=180)
    finally:
        if sim is None:  # the simulator timed out: stop the node too
            interrupt(node, 10.0)
    log = stop_cleanly(node)
    assert "runtime onnx" in log and "cvx-only" not in log, log[-3000:]
    assert sim.returncode in (0, 1) and "Traceback" not in sim.stderr, sim.stderr[-3000:]
    flown = json.loads(summary.read_text())
    assert flown["n_plans_received"] >= 1 and flown["n_plans_failed"] == 0, flown

    after = subprocess.run([sys.executable, "-c", _AFTER_FLIGHT, str(bag), str(tmp_path)],
                           env=env, cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert after.returncode == 0, after.stderr[-3000:]
    result = json.loads(after.stdout.strip().splitlines()[-1])
    codes = result["codes"]
    assert codes["reindex"] == codes["render"] == 0 and codes["replay"] in (0, 1), after.stderr
    assert codes["plan"] in (0, 1) and result["loaded"] == ["onnxruntime"]
    report = json.loads((tmp_path / "replay.json").read_text())
    assert "onnx runtime (sha256 matches)" in report["model"]
    assert report["config_check"] == report["metadata_check"] == "ok"
    assert report["solves"] == flown["n_plans_received"]
    assert report["compared"] + report["deadline_hit"] == report["solves"]
    # Every solve replays to its plan, the learned rollouts bit for bit; but the node plans a
    # fix that comes before its proposal worker has loaded the model without a proposal (no
    # rollout recorded: a cold start, e.g. no .pyc yet), which replay cannot reproduce.
    rows = report["per_solve"]
    assert all(r["match"] or r.get("rollout_max_abs_diff_mps") == float("inf")
               for r in rows), rows
    assert any(r["match"] and r.get("rollout_max_abs_diff_mps") == 0.0 for r in rows), rows
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert plan["warm_start"] == "art" and plan["art_runtime"] == "onnx"
    assert (tmp_path / "bag.png").stat().st_size > 10_000


# a well-formed command line of each (the extra is checked before anything is read)
TRAINING_COMMANDS = {
    "train": ["train", "--data", "d", "--out", "m.pt"],
    "export": ["export", "m.pt"],
    "distill": ["distill", "m.pt", "--out", "s.pt"],
    "dagger": ["dagger", "--model", "m.pt", "--data", "d", "--out", "o", "--n", "4"],
}


@pytest.mark.parametrize("command, blocked, missing", [
    *((name, FLIGHT_BLOCKED, "torch") for name in TRAINING_COMMANDS),
    ("export", ("onnx",), "onnx"),  # torch alone does not export
])
def test_training_commands_name_the_extra_where_it_is_missing(command, blocked, missing, tmp_path):
    env = blocked_env(blocker_site(tmp_path, blocked))
    run = subprocess.run([sys.executable, "-m", "art_guidance.cli",
                          *TRAINING_COMMANDS[command]],
                         env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-3000:]
    error = json.loads(run.stderr.strip().splitlines()[-1])
    assert error["error"] == "MissingDependencyError"
    message = error["message"]
    assert message.startswith(f"art-guidance {command} needs {missing}")
    assert "pip install 'art_guidance[train]'" in message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["site"]  # nothing written


def _setup_keywords() -> dict:
    tree = ast.parse((REPO / "setup.py").read_text())
    call = next(node for node in ast.walk(tree) if isinstance(node, ast.Call)
                and getattr(node.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords}


def test_torch_and_onnx_are_in_the_train_extra_only():
    keywords = _setup_keywords()
    requires = ast.literal_eval(keywords["install_requires"])
    extras = ast.literal_eval(keywords["extras_require"])
    names = {r.split("=")[0].split(">")[0].split("<")[0] for r in requires}
    assert "onnxruntime" in names and not names & set(FLIGHT_BLOCKED)
    assert {r.split("=")[0] for r in extras["train"]} == set(FLIGHT_BLOCKED)
    makefile = (REPO / "Makefile").read_text()
    # make demo / make test install the lock, which `make lock` resolves with the train extra
    assert '".[train,test,distributed]"' in makefile.split("\nlock:")[1]
    pins = (REPO / ".ci" / "constraints.txt").read_text().splitlines()
    assert {p.split("==")[0] for p in pins if "==" in p} >= set(FLIGHT_BLOCKED)
