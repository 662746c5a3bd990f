"""Child processes of the tests and benchmarks: stop a node as Ctrl-C would, read its size."""
from __future__ import annotations

import os
import signal
import subprocess


def interrupt(proc: subprocess.Popen, timeout_s: float) -> None:
    """SIGINT a process still running (a ROS node then shuts down cleanly), wait up to
    `timeout_s`, then kill it."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()


def stop_cleanly(proc: subprocess.Popen, timeout_s: float = 30.0) -> str:
    """SIGINT a node, wait for it and return its output, asserting a clean stop: exit 0 and
    no Traceback (the process must have been started with stdout piped, text mode)."""
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=timeout_s)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    return out


def process_stats(pid: int) -> tuple[float, int, int]:
    """(resident memory [MB], open file descriptors, threads) of a process (Linux /proc)."""
    rss, threads = float("nan"), -1
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024.0
            elif line.startswith("Threads:"):
                threads = int(line.split()[1])
    return rss, len(os.listdir(f"/proc/{pid}/fd")), threads
