"""Benchmark: the guidance node's start as a flight computer starts it, with a cold and a warm
numba cache: the time until it is ready to plan, its memory, and its first plan.

Each of `repeats` rounds starts the plain node (`python -m art_guidance.ros.guidance_node`,
the shipped model or `model`, default parameters but `stamp_check order`, `record false` and
`replan_sigma_threshold 1e-9`, so that every fix replans, and `warm_start art`, so that every
plan runs the model: its first use is in the first plan) twice in its own DDS domain: once with
`NUMBA_CACHE_DIR` a fresh empty folder (cold: the node plans on the numpy path while a
background process compiles the kernels), then, once that compile has filled the folder
(`fill_wait_s`: waited for after the cold start stopped), with the same folder again (warm:
they are loaded from it at configure). Per start:

- start-up [s]: wall time from spawning the process to its "guidance_node planning" log line,
  the end of its configure (model loaded, kernels loaded or their compile started, proposal
  worker launched but its own warm-up not waited for, topics up); `numerics_at_configure`
  (compiled or numpy); `kernel_warmup_s`: the kernels' time to be ready, as the node logs it
  ("kernels ready in ...": at configure when warm, at the switch when cold, None if the node
  stopped first); `matched_s`: from the spawn until a client sees the node's topics (DDS
  discovery included);
- RSS [MB, 2^20 bytes]: VmRSS of the node process plus its proposal worker process
  (`propose_concurrently`, on by default), read from /proc after the first plan; also each apart;
- first plan: the nav -> plan latency [ms] of the first fix after the start against the median
  of the next ten (each sent when the node is idle again, from the nominal initial state with
  small offsets, simulated stamps 1 s apart), their ratio, and the node's own solve time of
  each (`solve_time_ms` of its plan diagnostic; `first_solve_over_next10` their ratio), and
  the warm start each plan took (`first_warm_start`, `next10_warm_starts`);
  `cold_first_over_warm_next10`: the cold start's first plan against the warm start's next ten.

Every key is the median over the rounds, `cold_*` and `warm_*`. The node is stopped with SIGINT
after each start. Only the numba cache is cold: the interpreter's bytecode and the OS file cache
(torch, the model file) are warm after the first start of the run.

This benchmark measures the one-time costs on purpose, so it warms nothing up: "warm" here is
the numba cache, not the process. Its `first_plan_ms` carries what the other benchmarks pay in
their warm-up before any timed solve (`common.warm_up`, reported there as `warm_up_ms`): the
kernels' load where the node has not loaded them yet, and the runtime's first inference; the
next ten plans are the warm figure they are compared with.

    art-guidance bench startup --repeats 3 --json benchmarks/results/startup/startup.json
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from art_guidance import topics
from art_guidance.config import ScenarioConfig
from art_guidance.ros.env import isolated_ros_env

READY_LINE = "guidance_node planning"  # logged at the end of the node's start (_start_worker)
KERNELS_LINE = re.compile(r"kernels ready in ([0-9.]+) s")
NUMERICS_LINE = re.compile(r"numerics: (compiled|numpy)")  # the first: at configure
MODEL_LINE = re.compile(r"learned warm start: (.*?)(?:, loaded in [0-9]+ ms)?$")
NEXT = 10  # plans after the first, each from an idle node
STAMP_STEP_NS = 1_000_000_000  # simulated time between fixes (well under a node spacing)
START_TIMEOUT_S = 600.0  # a cold start on a loaded machine compiles every kernel
PLAN_TIMEOUT_S = 120.0
RESEND_S = 10.0  # a fix the node has not acknowledged by then was lost in discovery


class _Client:
    """A minimal rclpy client in its own context: publishes nav fixes, collects plans (arrival
    time per nav stamp) and the node's diagnostics."""

    def __init__(self, context, name: str) -> None:
        import rclpy
        from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node(name, context=context)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.nav_pub = self.node.create_publisher(RelativeNavState, topics.NAV, qos)
        self.plans: dict[int, float] = {}  # nav stamp -> perf_counter at arrival
        self.diags: list[tuple[str, dict]] = []
        self._cv = threading.Condition()
        self.plan_sub = self.node.create_subscription(ManeuverPlan, topics.MANEUVER_PLAN,
                                                      self._on_plan, qos)
        self.diag_sub = self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                                      self._on_diag, qos)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def _on_plan(self, msg) -> None:
        t = time.perf_counter()
        with self._cv:
            self.plans.setdefault(msg.header.stamp.sec * 1_000_000_000
                                  + msg.header.stamp.nanosec, t)
            self._cv.notify_all()

    def _on_diag(self, msg) -> None:
        with self._cv:
            self.diags += [(st.name, {kv.key: kv.value for kv in st.values})
                           for st in msg.status]
            self._cv.notify_all()

    def matched(self) -> bool:
        return (self.nav_pub.get_subscription_count() > 0
                and self.plan_sub.get_publisher_count() > 0
                and self.diag_sub.get_publisher_count() > 0)

    def wait_for(self, predicate, timeout_s: float):
        """The first truthy predicate() within `timeout_s`, else None (called under the lock)."""
        end = time.monotonic() + timeout_s
        with self._cv:
            while True:
                value = predicate()
                if value or time.monotonic() >= end:
                    return value or None
                self._cv.wait(timeout=max(0.0, min(0.2, end - time.monotonic())))

    def diag(self, name: str, stamp_ns: int) -> dict | None:
        """The values of the status `name` for the fix `stamp_ns` (waited for by wait_for)."""
        for got, values in self.diags:
            if got == name and values.get("nav_stamp_ns") == str(stamp_ns):
                return values
        return None

    def send(self, stamp_ns: int, rtn: np.ndarray, chief_oe) -> float:
        """Publish a fix; returns the perf_counter just before."""
        from art_guidance_msgs.msg import RelativeNavState

        msg = RelativeNavState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg.header.frame_id = "chief_rtn"
        msg.chief_oe = [float(v) for v in chief_oe]
        msg.representation = RelativeNavState.REPRESENTATION_RTN
        msg.mean = [float(v) for v in rtn]
        msg.covariance = [float(v) for v in np.diag([25.0, 400.0, 25.0, 1e-4, 1e-4, 1e-4])
                          .reshape(-1)]
        t = time.perf_counter()
        self.nav_pub.publish(msg)
        return t

    def close(self) -> None:
        self.executor.shutdown()
        self._thread.join(timeout=5)
        self.node.destroy_node()


class _Log:
    """The node's stderr (its console log), read in a thread, each line with its arrival time."""

    def __init__(self, stream) -> None:
        self.lines: list[tuple[float, str]] = []
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cv:
                self.lines.append((time.perf_counter(), line.rstrip("\n")))
                self._cv.notify_all()
        with self._cv:
            self.lines.append((time.perf_counter(), None))  # EOF: the process is gone
            self._cv.notify_all()

    def wait_line(self, text: str, timeout_s: float) -> float | None:
        """Arrival time of the first line containing `text`; None if the log ended first or
        `timeout_s` passed."""
        end = time.monotonic() + timeout_s
        with self._cv:
            while True:
                for t, line in self.lines:
                    if line is None:
                        return None
                    if text in line:
                        return t
                if time.monotonic() >= end:
                    return None
                self._cv.wait(timeout=min(0.5, max(0.0, end - time.monotonic())))

    def search(self, pattern: re.Pattern) -> str | None:
        with self._cv:
            for _, line in self.lines:
                m = line is not None and pattern.search(line)
                if m:
                    return m.group(1)
        return None

    def tail(self, n: int = 30) -> str:
        with self._cv:
            return "\n".join(line for _, line in self.lines[-n:] if line is not None)

    def join(self) -> None:
        self._thread.join(timeout=10)


def _rss_mb(pid: int) -> float:
    """VmRSS of process `pid` [MB] (0 if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of the direct children of `pid`."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat[stat.rindex(")") + 2:].split()[1])
            if ppid == pid:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                out.append((int(d.name), cmd))
        except (OSError, ValueError):
            continue
    return out


def _started(pid: int) -> str | None:
    """The start time of process `pid` (/proc stat field 22), None if it is gone: tells the
    same process from a later one given its pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:].split()[19]
    except (OSError, ValueError, IndexError):
        return None


def _workers(pid: int) -> list[int]:
    """The proposal worker processes of the node `pid` (multiprocessing "spawn" children; not
    its resource tracker)."""
    return [c for c, cmd in _children(pid) if "spawn_main" in cmd]


def _fixes(n: int) -> list[np.ndarray]:
    """`n` states near the nominal initial state (offsets of 5 % of the sampling half-width)."""
    scenario = ScenarioConfig()
    rng = np.random.default_rng(7)
    half = np.asarray(scenario.rtn0_half_width)
    return [np.asarray(scenario.rtn0_nominal) + 0.05 * rng.uniform(-1, 1, 6) * half
            for _ in range(n)]


def _start(context, env: dict, params: list[str], label: str) -> dict:
    """Start the node once, plan 1 + NEXT times, stop it; the numbers of this start."""
    chief = ScenarioConfig().chief_oe
    fixes = _fixes(1 + NEXT)
    client = _Client(context, f"art_guidance_bench_startup_{label}")
    deadline = time.monotonic() + 30.0  # the previous start's endpoints are gone
    while client.nav_pub.get_subscription_count() > 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "art_guidance.ros.guidance_node", "--ros-args",
                             *params], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, errors="replace")
    log = _Log(proc.stderr)
    workers: list[tuple[int, str | None]] = []  # (pid, start time)
    try:
        t_ready = t_matched = None
        end = time.monotonic() + START_TIMEOUT_S
        while (t_ready is None or t_matched is None) and time.monotonic() < end:
            if t_matched is None and client.matched():
                t_matched = time.perf_counter()
            if t_ready is None:
                t_ready = log.wait_line(READY_LINE, 0.0)
                if t_ready is None and proc.poll() is not None:
                    break
            time.sleep(0.01)
        if t_ready is None:
            raise RuntimeError(f"guidance node did not start ({label}):\n{log.tail()}")
        if t_matched is None:
            raise RuntimeError(f"no DDS match with the guidance node ({label})")
        stamp = time.time_ns()  # simulated stamps from here, STAMP_STEP_NS apart
        sent: dict[int, float] = {}
        acked = None
        for _ in range(5):  # the first fix after a match may be lost while discovery completes
            stamp += STAMP_STEP_NS
            sent[stamp] = client.send(stamp, fixes[0], chief)
            acked = client.wait_for(lambda: next(
                (s for s in sent if client.diag("art_guidance/nav", s)), None), RESEND_S)
            if acked is not None:
                break
        if acked is None:
            raise RuntimeError(f"the guidance node acknowledged no fix ({label})")
        if client.diag("art_guidance/nav", acked).get("decision") != "replanning":
            raise RuntimeError(f"first fix not replanned ({label}): "
                               f"{client.diag('art_guidance/nav', acked)}")
        latency, solve, sources = [], [], []
        for k in range(1 + NEXT):
            if k > 0:
                stamp += STAMP_STEP_NS
                acked = stamp
                sent[stamp] = client.send(stamp, fixes[k], chief)
            if client.wait_for(lambda: acked in client.plans, PLAN_TIMEOUT_S) is None:
                raise RuntimeError(f"no plan for fix {k} ({label}): "
                                   f"{client.diag('art_guidance/nav', acked)}")
            latency.append(1e3 * (client.plans[acked] - sent[acked]))
            # idle again: the plan status is the last work of a plan (and of any resent fix)
            for s in [s for s in sent if s <= acked and (
                    client.diag("art_guidance/nav", s) or {}).get("decision") == "replanning"]:
                values = client.wait_for(lambda: client.diag("art_guidance/plan", s),
                                         PLAN_TIMEOUT_S)
                if values is None:
                    raise RuntimeError(f"no plan status for fix {k} ({label})")
            values = client.diag("art_guidance/plan", acked)
            solve.append(float(values["solve_time_ms"]))
            sources.append(values.get("warm_start", ""))
            if k == 0:
                workers = [(w, _started(w)) for w in _workers(proc.pid)]
                node_mb = _rss_mb(proc.pid)
                worker_mb = sum(_rss_mb(w) for w, _ in workers)
    finally:
        client.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.join()
        for w, started in workers:  # the node stops its worker; none is left running
            if _started(w) == started:
                os.kill(w, signal.SIGKILL)
    kernels = log.search(KERNELS_LINE)
    numerics = log.search(NUMERICS_LINE)
    next_ms = float(np.median(latency[1:]))
    return {"startup_s": t_ready - t0, "matched_s": t_matched - t0,
            "kernel_warmup_s": float(kernels) if kernels is not None else None,
            "rss_mb": node_mb + worker_mb, "node_rss_mb": node_mb, "worker_rss_mb": worker_mb,
            "workers": len(workers), "first_plan_ms": latency[0], "next10_median_ms": next_ms,
            "first_over_next10": latency[0] / next_ms, "first_solve_ms": solve[0],
            "next10_solve_median_ms": float(np.median(solve[1:])),
            "first_solve_over_next10": solve[0] / float(np.median(solve[1:])),
            "first_warm_start": sources[0], "next10_warm_starts": " ".join(
                f"{k}:{sources[1:].count(k)}" for k in sorted(set(sources[1:]))),
            "numerics_at_configure": numerics or "unknown",
            "model": log.search(MODEL_LINE) or "none"}


def run(repeats: int = 3, model: str | None = None) -> dict:
    """Medians over `repeats` cold and warm starts: start-up [s], kernel warm-up [s], RSS [MB],
    first plan and the median of the next ten [ms] and their ratio."""
    import rclpy

    repeats = max(int(repeats), 1)
    saved = dict(os.environ)
    home = tempfile.mkdtemp(prefix="art_guidance_bench_startup_")
    ros = isolated_ros_env(home, 200 + os.getpid() % 30)  # apart from the tests' 100-199
    ros["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    params = ["-p", "stamp_check:=order", "-p", "record:=false",
              "-p", "replan_sigma_threshold:=1e-9", "-p", "warm_start:=art"]
    if model:
        params += ["-p", f"model_path:={Path(model).resolve()}"]
    os.environ.update(ros)  # read by this process's DDS participant (the client) at init
    context = rclpy.context.Context()
    rclpy.init(context=context)
    os.environ.clear()
    os.environ.update(saved)
    rows: dict[str, list[dict]] = {"cold": [], "warm": []}
    try:
        for r in tqdm(range(repeats), desc="bench startup", unit="round"):
            with tempfile.TemporaryDirectory(prefix="art_guidance_numba_") as cache:
                env = {**saved, **ros, "NUMBA_CACHE_DIR": cache, "PYTHONUNBUFFERED": "1",
                       "RCUTILS_LOGGING_BUFFERED_STREAM": "0"}
                rows["cold"].append(_start(context, env, params, f"cold_{r}"))
                # the cold start's background compile filling the cache, waited for
                t = time.perf_counter()
                subprocess.run([sys.executable, "-m", "art_guidance.kernels", "--quiet"],
                               env=env, timeout=START_TIMEOUT_S, check=True)
                rows["cold"][-1]["fill_wait_s"] = time.perf_counter() - t
                rows["warm"].append(_start(context, env, params, f"warm_{r}"))
    finally:
        rclpy.try_shutdown(context=context)
        shutil.rmtree(home, ignore_errors=True)  # the ROS logs
    out: dict = {"repeats": repeats, "model": rows["cold"][0]["model"]}
    for state, starts in rows.items():
        for key in starts[0]:
            values = [s[key] for s in starts]
            if key == "model":
                continue
            if isinstance(values[0], str):
                out[f"{state}_{key}"] = ", ".join(sorted(set(values)))
            elif None in values:  # not logged (the numpy path)
                out[f"{state}_{key}"] = None
            else:
                out[f"{state}_{key}"] = float(np.median(values))
    out["cold_first_over_warm_next10"] = out["cold_first_plan_ms"] / out["warm_next10_median_ms"]
    return out


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
