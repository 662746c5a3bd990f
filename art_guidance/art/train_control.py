"""What controls a training run from outside the loop: the ``OUT.lock`` that keeps two runs
from writing the same checkpoint, and SIGINT/SIGTERM, which stop the loop at the next step
boundary (the state saved there is exact, so the same command resumes)."""
from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import threading
from pathlib import Path
from typing import Any, Iterator

from art_guidance.errors import InputError


class StopOnSignal:
    """SIGINT/SIGTERM ask the loop to stop at the next step boundary (a second one aborts)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: object) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def exclusive(out: str, take: bool) -> Iterator[None]:
    """Hold an exclusive lock on ``OUT.lock`` (one training run per checkpoint path)."""
    if not take:
        yield
        return
    path = Path(str(out) + ".lock")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise InputError("--out", f"cannot create {path} ({exc})", out) from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        raise InputError("--out", "another training run is writing this checkpoint",
                         out) from exc
    try:
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
