"""Child processes of the tests and benchmarks: stop a node as Ctrl-C would, read its size."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from pathlib import Path


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


def stop_kernel_filler(root: Path, wait_s: float = 30.0) -> int | None:
    """Stop the background process compiling the kernels into a cache folder under `root`
    (`python -m art_guidance.kernels`, detached from the command that started it), waiting up
    to `wait_s` for it to take the folder's lock (it does as that command ends); returns its
    pid, or None where none came."""
    from art_guidance.kernels.cache import LOCK_NAME, filler_pid

    end = time.monotonic() + wait_s
    while True:
        pid = next((p for f in root.rglob(LOCK_NAME) if (p := filler_pid(f.parent))), None)
        if pid is not None or time.monotonic() >= end:
            break
        time.sleep(0.1)
    if pid is not None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return pid
