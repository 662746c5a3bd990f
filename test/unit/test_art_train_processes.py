"""`art-guidance train` as real processes: SIGKILL, SIGTERM and resume; data parallel (gloo).

Both compare the final weights with an uninterrupted single-process run of the same command
(tiny preset, 1 thread per process). Tolerances: resume 1e-6 (same arithmetic, only the
process changed); 2 processes 1e-5 on the validation losses and 2e-3 on the weights (the
gradient sum is reduced in another order; see `_max_diff` for the attention key biases). The
weights' tolerance is two Adam steps at the learning rate 1e-3: Adam normalises a gradient
entry whose value is at round-off level into a step of size ~lr, so a weight whose gradient
nearly vanishes (a ReLU unit near its kink) drifts by up to a few 1e-4 between the two
reduction orders within 30 steps, depending on the processor's kernels, while the model's
outputs (its validation losses) still agree to 1e-6.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from art_guidance.art import checkpoint
from art_guidance.art.train import state_path
from art_guidance.data.generate import generate

pytestmark = pytest.mark.slow  # training processes (SIGKILL, resume, torchrun)

# The `train` subcommand alone, with the CLI's error handling (exit 2 on GuidanceError).
RUNNER = """
import argparse, json, sys
from art_guidance.cli.train import add_parser
from art_guidance.errors import GuidanceError

parser = argparse.ArgumentParser(prog="art-guidance")
add_parser(parser.add_subparsers(dest="command"))
args = parser.parse_args(sys.argv[1:])
try:
    sys.exit(args.func(args))
except GuidanceError as exc:
    print(json.dumps({"error": type(exc).__name__, "message": str(exc)}), file=sys.stderr)
    sys.exit(2)
"""
TORCHRUN = Path(sys.executable).with_name("torchrun")
STEPS = 30


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("art_proc")
    generate(root / "ds", 16, "deterministic", base_seed=9, workers=2, shard_size=4,
             progress=False, log=lambda _: None)
    runner = root / "runner.py"
    runner.write_text(RUNNER)
    return root / "ds", runner


def _cmd(setup, out: Path, steps: int) -> list[str]:
    data, runner = setup
    return [str(runner), "train", "--data", str(data), "--out", str(out), "--preset", "tiny",
            "--max-steps", str(steps), "--eval-every", "5", "--threads", "1", "--no-progress",
            "--lr", "1e-3"]


def _env() -> dict[str, str]:
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return checkpoint.read_payload(path)[0]["state_dict"]


def _max_diff(a: dict, b: dict) -> float:
    """Largest weight difference, the attention key biases excepted.

    A key bias adds the same q . b to every score of a query, which the softmax cancels: its
    gradient is zero up to round-off, and Adam scales that noise up to steps of size lr, so
    it drifts differently under any change of reduction order without changing any output.
    """
    assert a.keys() == b.keys()
    diffs = []
    for k in a:
        d = (a[k] - b[k]).abs()
        if k.endswith("qkv.bias"):
            width = d.numel() // 3
            d = torch.cat([d[:width], d[2 * width:]])  # queries and values only
        diffs.append(float(d.max()))
    return max(diffs)


@pytest.fixture(scope="module")
def reference(setup, tmp_path_factory) -> Path:
    """An uninterrupted single-process run of STEPS steps."""
    ref = tmp_path_factory.mktemp("ref") / "ref.pt"
    subprocess.run([sys.executable, *_cmd(setup, ref, STEPS)], env=_env(), check=True,
                   capture_output=True, timeout=120)
    return ref


def _wait_for(predicate, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.02)


def test_killed_and_interrupted_training_resumes_to_the_same_weights(setup, reference,
                                                                     tmp_path):
    out = tmp_path / "killed.pt"
    proc = subprocess.Popen([sys.executable, *_cmd(setup, out, STEPS)], env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_for(lambda: state_path(out).exists())  # the first checkpoint (step 5)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, "training finished before it could be killed"
    killed_at = checkpoint.read_payload(state_path(out))[0]["progress"]["step"]
    assert 5 <= killed_at < STEPS
    # resume, then SIGTERM: it stops at the next step boundary, saves and exits 130
    log = tmp_path / "resume.log"
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, *_cmd(setup, out, STEPS)], env=_env(),
                                stdout=fh, stderr=subprocess.STDOUT)
        _wait_for(lambda: "resuming" in log.read_text())
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 130, log.read_text()
    assert f"resuming {out} at step {killed_at}" in log.read_text()
    stopped_at = checkpoint.read_payload(state_path(out))[0]["progress"]["step"]
    assert f"interrupted at step {stopped_at}" in log.read_text()
    res = subprocess.run([sys.executable, *_cmd(setup, out, STEPS)], env=_env(), text=True,
                         capture_output=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert _max_diff(_weights(out), _weights(reference)) <= 1e-6  # best weights
    assert _max_diff(_weights(state_path(out)), _weights(state_path(reference))) <= 1e-6


def test_two_gloo_processes_equal_one_process(setup, reference, tmp_path):
    double = tmp_path / "two.pt"
    res = subprocess.run([str(TORCHRUN), "--standalone", "--nproc_per_node", "2",
                          *_cmd(setup, double, STEPS)], env=_env(), text=True,
                         capture_output=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "2 process(es) on cpu" in res.stdout
    meta = checkpoint.load(double).meta["training"]
    assert meta["world_size"] == 2 and meta["step"] == STEPS
    assert _max_diff(_weights(state_path(double)), _weights(state_path(reference))) <= 2e-3
    hist_one = checkpoint.load(reference).meta["training"]["history"]
    assert [h[0] for h in meta["history"]] == [h[0] for h in hist_one]
    assert all(abs(a[2] - b[2]) <= 1e-5 for a, b in zip(meta["history"], hist_one))


def test_bad_input_exits_2(setup, tmp_path):
    data, runner = setup
    res = subprocess.run([sys.executable, str(runner), "train", "--data", str(data), "--out",
                          str(tmp_path / "x.pt"), "--preset", "tiny", "--max-minutes", "0"],
                         env=_env(), text=True, capture_output=True, timeout=60)
    assert res.returncode == 2 and "--max-minutes" in res.stderr
