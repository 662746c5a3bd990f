"""Run many short `art-guidance <command>` invocations without paying the interpreter start and
the imports (torch, numpy, SciPy, rclpy, the package) for each one.

`run_briefly(jobs, env, timeout_s)` starts one helper process (this module as `__main__`) that
imports the heavy modules once and then forks a child per command: the child becomes its own
session (process group), changes into its directory, sends stdout to /dev/null and stderr to a
file, and runs `art_guidance.cli.main(argv)` as `python -m art_guidance.cli` would (its exit code;
2 with the usage message for an argparse error; 1 with a traceback for an exception). A child
still running after `timeout_s` is killed with its process group, as a subprocess would be.
The helper forks from a single thread; it never runs a tensor operation itself.

Where `os.fork` is not available, each command runs as its own subprocess instead.
"""
from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Mapping, Sequence

# Imported once by the helper, before it forks (third-party first, then every module of the
# package but its entry points, which run on import).
PRELOAD = ("numpy", "scipy.linalg", "scipy.optimize", "scipy.integrate", "torch", "clarabel",
           "osqp", "yaml", "matplotlib", "matplotlib.pyplot", "mcap.reader")
# Never imported before a fork: importing rclpy starts threads (a fork keeps only the forking
# one), Ray is heavy and only some commands use it. Package modules that import them at the
# top are left to the children too.
NOT_PRELOADED = ("rclpy", "ray")

Outcome = tuple[int | None, str]  # (exit code, or None when killed at the timeout; stderr)


def run_briefly(jobs: Sequence[tuple[str, Path]], env: Mapping[str, str], timeout_s: float,
                parallel: int = 3) -> list[Outcome]:
    """Run `art-guidance <command>` in `cwd` for every (command, cwd) in `jobs`, at most
    `parallel` at a time, each killed (with its process group) after `timeout_s`. Returns the
    (exit code or None when it was still running, stderr) of each, in the order of `jobs`."""
    if not hasattr(os, "fork"):
        with ThreadPoolExecutor(parallel) as pool:
            return list(pool.map(lambda job: _run_subprocess(*job, env, timeout_s), jobs))
    with tempfile.TemporaryDirectory(prefix="art_guidance_cli_runs_") as tmp:
        spec, results = Path(tmp) / "jobs.json", Path(tmp) / "results.json"
        spec.write_text(json.dumps({"jobs": [[c, str(d)] for c, d in jobs],
                                    "timeout_s": timeout_s, "parallel": parallel}))
        limit = 120.0 + timeout_s * len(jobs)
        helper = subprocess.run([sys.executable, "-m", "helpers.cli_runs", str(spec),
                                 str(results)], env=dict(env), stdin=subprocess.DEVNULL,
                                capture_output=True, text=True,
                                timeout=limit)
        if helper.returncode != 0 or not results.is_file():
            raise RuntimeError(f"cli_runs helper failed ({helper.returncode}):\n"
                               f"{helper.stdout[-2000:]}\n{helper.stderr[-3000:]}")
        return [(code, err) for code, err in json.loads(results.read_text())]


def _run_subprocess(command: str, cwd: Path, env: Mapping[str, str],
                    timeout_s: float) -> Outcome:
    """One command as its own `python -m art_guidance.cli` process."""
    kwargs = {"start_new_session": True} if os.name == "posix" else {}
    proc = subprocess.Popen([sys.executable, "-m", "art_guidance.cli", *shlex.split(command)],
                            cwd=cwd, env=dict(env), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, **kwargs)
    try:
        _, err = proc.communicate(timeout=timeout_s)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        if os.name == "posix":
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            proc.kill()
        _, err = proc.communicate()
        return None, err


class _Refuse:
    """Meta path finder that makes NOT_PRELOADED fail to import (while preloading)."""

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> None:
        if name.partition(".")[0] in NOT_PRELOADED:
            raise ModuleNotFoundError(f"{name} is not preloaded", name=name)


def _preload() -> None:
    import importlib
    import pkgutil

    sys.meta_path.insert(0, _Refuse)
    try:
        for name in PRELOAD:
            try:
                importlib.import_module(name)
            except ImportError:
                pass
        import art_guidance
        from art_guidance.cli import build_parser

        build_parser()  # imports every subcommand's module
        for info in pkgutil.walk_packages(art_guidance.__path__, "art_guidance."):
            if info.name.rpartition(".")[2] == "__main__":
                continue
            try:
                importlib.import_module(info.name)
            except ImportError:
                pass  # it needs rclpy (or a missing optional dependency): imported on use
    finally:
        sys.meta_path.remove(_Refuse)


def _child(command: str, cwd: str, err_fd: int) -> None:
    """In the forked child: run the command like `python -m art_guidance.cli`, never return."""
    code = 1
    try:
        os.setsid()
        os.chdir(cwd)
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)
        os.dup2(null, 1)
        os.dup2(err_fd, 2)
        from art_guidance.cli import main

        argv = shlex.split(command)
        sys.argv = ["art-guidance", *argv]
        try:
            code = main(argv)
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
                code = 1
        except BaseException:
            import traceback

            traceback.print_exc()
            code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(int(code) & 0xFF if isinstance(code, int) else 1)


def _serve(jobs: list[list[str]], timeout_s: float, parallel: int) -> list[Outcome]:
    """Fork a child per job, at most `parallel` at a time; the helper itself stays one thread."""
    pending = list(enumerate(jobs))
    running: dict[int, tuple[int, float, int]] = {}  # pid -> (job index, deadline, stderr fd)
    results: list[Outcome | None] = [None] * len(jobs)

    def finish(pid: int, code: int | None) -> None:
        k, _, fd = running.pop(pid)
        try:
            os.killpg(pid, signal.SIGKILL)  # whatever the command started
        except (ProcessLookupError, PermissionError):
            pass
        os.lseek(fd, 0, os.SEEK_SET)
        with os.fdopen(fd, "rb") as fh:
            results[k] = (code, fh.read().decode(errors="replace"))

    while pending or running:
        while pending and len(running) < parallel:
            k, (command, cwd) = pending.pop(0)
            fd, path = tempfile.mkstemp(prefix="stderr_")
            os.unlink(path)
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                _child(command, cwd, fd)
            running[pid] = (k, time.monotonic() + timeout_s, fd)
        pid, status = os.waitpid(-1, os.WNOHANG)
        if pid and pid in running:
            finish(pid, os.waitstatus_to_exitcode(status))
            continue
        now = time.monotonic()
        for pid, (_, deadline, _) in list(running.items()):
            if now >= deadline:
                os.killpg(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                finish(pid, None)
        time.sleep(0.01)
    return [r for r in results if r is not None]


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m helpers.cli_runs JOBS.json RESULTS.json` (what `run_briefly` starts)."""
    spec_path, results_path = argv if argv is not None else sys.argv[1:]
    spec = json.loads(Path(spec_path).read_text())
    _preload()
    results = _serve(spec["jobs"], float(spec["timeout_s"]), int(spec["parallel"]))
    Path(results_path).write_text(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
