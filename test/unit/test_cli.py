"""The `art-guidance` command line: help, plan JSON, clear errors."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from art_guidance.cli import build_parser, main

SUBCOMMANDS = ("demo", "plan", "bench", "node", "replay", "bag", "generate", "sim", "train",
               "evaluate", "kernels")
REQUIRED_KEYS = {"chief_oe", "epochs_s", "dv_rtn_mps", "roe_m", "rtn", "cost_mps", "status",
                 "scp_iterations", "warm_start", "posthoc", "timings_ms",
                 "constraint_margin_m"}


@pytest.mark.parametrize("sub", SUBCOMMANDS)
def test_help_for_every_subcommand(sub, capsys):
    with pytest.raises(SystemExit) as exc:
        main([sub, "--help"])
    assert exc.value.code == 0
    assert sub in capsys.readouterr().out


def test_parser_lists_subcommands():
    text = build_parser().format_help()
    for sub in SUBCOMMANDS:
        assert sub in text


@pytest.mark.parametrize("deterministic", [False, True])
def test_plan_writes_json(tmp_path, deterministic):
    out = tmp_path / "plan.json"
    args = ["plan", "--seed", "4", "--warm-start", "cvx", "--json", str(out)]
    assert main(args + (["--deterministic"] if deterministic else [])) == 0
    data = json.loads(out.read_text())
    assert REQUIRED_KEYS <= set(data)
    n = len(data["epochs_s"])
    assert np.asarray(data["dv_rtn_mps"]).shape == (n, 3)
    assert np.asarray(data["roe_m"]).shape == (n, 6)
    assert np.asarray(data["rtn"]).shape == (n, 6)
    assert data["warm_start"] == "cvx"
    assert data["status"] in ("CONVERGED", "MAX_ITERATIONS")
    assert data["cost_mps"] >= data["cvx_cost_mps"] - 1e-9
    assert set(data["timings_ms"]) >= {"art", "cvx", "scp", "total"}
    dv = np.asarray(data["dv_rtn_mps"])
    assert data["cost_mps"] == pytest.approx(np.linalg.norm(dv, axis=1).sum(), rel=1e-9)


def test_plan_bad_waypoint_is_a_clear_error(tmp_path, capsys):
    code = main(["plan", "--seed", "0", "--waypoint", "nowhere", "--json",
                 str(tmp_path / "x.json")])
    assert code == 2
    err = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert err["error"] == "InputError" and "waypoint" in err["message"]
    assert not (tmp_path / "x.json").exists()


def test_art_warm_start_without_model_is_refused(tmp_path):
    assert main(["plan", "--seed", "0", "--warm-start", "art", "--model", "none", "--json",
                 str(tmp_path / "x.json")]) == 2


def test_console_script_runs():
    out = subprocess.run([sys.executable, "-m", "art_guidance.cli", "--version"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "art-guidance" in out.stdout


def test_non_ros_commands_never_import_rclpy(tmp_path):
    """Building the parser and planning must not load ROS (a plain-Python user has none), nor
    torch (a CVX-warm-started plan needs no model)."""
    code = ("import sys, json\n"
            "from art_guidance.cli import build_parser, main\n"
            "build_parser()\n"
            f"rc = main(['plan', '--seed', '2', '--warm-start', 'cvx', '--json', "
            f"{str(tmp_path / 'p.json')!r}])\n"
            "print(json.dumps([rc, sorted(m for m in sys.modules if m.startswith(('rclpy', "
            "'art_guidance_msgs', 'art_guidance.ros.guidance', 'art_guidance.ros.sim', "
            "'torch')))]))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    rc, ros_modules = json.loads(out.stdout.strip().splitlines()[-1])
    assert rc == 0 and ros_modules == [], out.stderr[-2000:]


@pytest.mark.parametrize("argv,expected", [
    (["node", "--ros-args", "-p", "stamp_check:=order"],
     ["--ros-args", "-p", "stamp_check:=order"]),
    (["node", "--", "--ros-args", "-p", "a:=1"], ["--ros-args", "-p", "a:=1"]),
    (["node", "--managed", "--ros-args", "-r", "__ns:=/x"], ["--ros-args", "-r", "__ns:=/x"]),
    (["node"], []),
])
def test_node_takes_ros_args_as_users_type_them(argv, expected, monkeypatch):
    """`art-guidance node --ros-args ...` (the example of the README and --help) reaches rclpy
    with its arguments, as does the `--` form; no usage error."""
    import art_guidance.ros.guidance_node as gn

    seen = {}
    monkeypatch.setattr(gn, "main", lambda args, managed=False: seen.update(
        args=args, managed=managed) or 0)
    assert main(argv) == 0
    assert seen["args"] == ["guidance_node", *expected]
    assert seen["managed"] == ("--managed" in argv)


def _child(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code])


def test_demo_stops_the_flight_when_the_node_dies():
    """The demo's wait: a node that exits while the simulator flies is reported with its exit
    code at once (the simulator is stopped), not after the simulator's plan timeout."""
    import time

    from art_guidance.cli.demo import _wait_for_sim

    sim, node = _child("import time; time.sleep(60)"), _child("raise SystemExit(2)")
    t0 = time.monotonic()
    assert _wait_for_sim(sim, node, timeout_s=60) == 2
    assert time.monotonic() - t0 < 10 and sim.poll() is not None
    sim, node = _child("pass"), _child("import time; time.sleep(60)")
    assert _wait_for_sim(sim, node, timeout_s=60) is None and sim.returncode == 0
    node.kill()
    node.wait()
    sim = _child("import time; time.sleep(60)")
    node = _child("import time; time.sleep(60)")
    with pytest.raises(subprocess.TimeoutExpired):
        _wait_for_sim(sim, node, timeout_s=0.5)
    assert sim.poll() is not None
    node.kill()
    node.wait()
