"""The kernels' on-disk cache as numba really uses it: where it is (`folder`), whether it holds
the kernels (`inspect`), moving a damaged kernel's files aside (`move_aside`), compiling in
memory where it cannot be used (`in_memory`), and one filler at a time per folder
(`fill_lock`).

numba keeps one index (`<function>-<line>.pyXY.nbi`) and data files (`... .N.nbc`) per kernel,
and reads them when a kernel is first called: a truncated or otherwise damaged file raises
there (EOFError, UnpicklingError, ...) in whatever process plans first. These helpers use
numba's per-function cache object (`Dispatcher._cache`: its `cache_path` and index file), which
is private API: the pinned numba version is the one tested (`test_kernel_cache.py`).
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import time
from pathlib import Path
from typing import Iterable, Iterator

from numba.core.caching import NullCache
from numba.core.registry import CPUDispatcher

from art_guidance.kernels import drift, drift_bounds, horizon

# the kernels the numerics doors call (their warm_up compiles or loads them, and with them
# every kernel they call)
ENTRY_POINTS = ("drift.violated", "drift.minimum", "horizon.propagate_nonlinear")
DAMAGED_FOLDER = "damaged"
LOCK_NAME = ".art_guidance_fill.lock"
# a filler started by a process that took the fill lock for it inherits the locked file as this
# descriptor (one filler per folder: a process that finds the lock held starts none)
LOCK_FD_ENV = "ART_GUIDANCE_FILL_LOCK_FD"
# how long a process waits for another's fill lock before it compiles in memory [s] (a compile
# takes 12-15 s on a desktop core, a few minutes on a slow flight computer)
LOCK_WAIT_ENV = "ART_GUIDANCE_FILL_LOCK_WAIT_S"
LOCK_WAIT_S = 600.0


class LockBusy(Exception):
    """Another process held the cache folder's fill lock for longer than the wait allowed."""

    def __init__(self, where: Path, pid: int | None, waited_s: float) -> None:
        holder = f"process {pid}" if pid else "another process"
        super().__init__(f"{holder} has held the fill lock of {where} for more than "
                         f"{waited_s:.0f} s ({LOCK_WAIT_ENV})")
        self.pid = pid


def lock_wait_s() -> float:
    """The bound of a wait for the fill lock [s] (`LOCK_WAIT_ENV`, else `LOCK_WAIT_S`)."""
    try:
        return max(float(os.environ.get(LOCK_WAIT_ENV, LOCK_WAIT_S)), 0.0)
    except ValueError:
        return LOCK_WAIT_S


def dispatchers() -> dict[str, CPUDispatcher]:
    """Every compiled kernel of the package, by "module.name"."""
    return {f"{m.__name__.rsplit('.', 1)[-1]}.{name}": value
            for m in (drift, drift_bounds, horizon) for name, value in vars(m).items()
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == m.__name__}


def folder() -> Path | None:
    """The folder numba caches the kernels in (None: caching is off, compiled in memory).
    numba takes NUMBA_CACHE_DIR where it can create it, else the next place it can."""
    cache = getattr(dispatchers()["drift.violated"], "_cache", None)
    path = getattr(cache, "cache_path", None)
    return None if path is None else Path(path)


def _files(disp: CPUDispatcher) -> list[Path]:
    """The index and data files of one kernel."""
    index = Path(disp._cache._cache_file._index_path)
    return sorted(index.parent.glob(index.name[:-len(".nbi")] + ".*"))


def inspect(data: bool = False) -> tuple[bool, dict[str, list[Path]]]:
    """(whether every entry point has an entry in a loadable index, the damaged files by
    kernel: an index that does not load, or with `data` a data file it names that does not
    unpickle: ~20 ms more, asked only once loading failed). A stale index (another numba or
    source) reads as empty, not damaged."""
    warm, damaged = True, {}
    for name, disp in dispatchers().items():
        cache_file = getattr(getattr(disp, "_cache", None), "_cache_file", None)
        if cache_file is None:
            warm = False
            continue
        try:
            entries = cache_file._load_index()
        except Exception:  # a truncated, emptied or garbled index
            damaged[name] = [Path(cache_file._index_path)]
            entries = {}
        bad = [Path(cache_file._data_path(entry)) for entry in entries.values()
               if data and not _loads(cache_file, entry)]
        if bad:
            damaged[name] = bad
        if name in ENTRY_POINTS and not entries:
            warm = False
    return warm and not damaged, damaged


def _loads(cache_file, data: str) -> bool:
    """Whether the data file `data` of a kernel's index unpickles (a missing one is not damage:
    numba compiles that entry again)."""
    try:
        cache_file._load_data(data)
    except FileNotFoundError:
        return True
    except Exception:  # truncated, garbled
        return False
    return True


def move_aside(names: Iterable[str] | None = None) -> tuple[list[str], str]:
    """Move the cache files of the kernels `names` (None: of every kernel) into the cache
    folder's `damaged/` (replacing what an earlier move left there), so that numba compiles
    them again; returns (the files moved, "" or why they could not be). numba keeps one index
    and its data files per kernel, and a cached kernel holds the code of those it calls: the
    others load as they are."""
    moved = []
    kernels = dispatchers()
    try:
        for name in kernels if names is None else names:
            for path in _files(kernels[name]):
                target = path.parent / DAMAGED_FOLDER / path.name
                target.parent.mkdir(exist_ok=True)
                os.replace(path, target)
                moved.append(path.name)
    except (AttributeError, KeyError, OSError) as exc:
        return moved, f"{type(exc).__name__}: {exc}"
    return moved, ""


def in_memory() -> None:
    """Compile the kernels in memory from now on: numba neither reads nor writes the cache."""
    for disp in dispatchers().values():
        disp._cache = NullCache()


def load() -> None:
    """Compile the kernels, or load them from the cache (numba's own choice)."""
    drift.warm_up()
    horizon.warm_up()


def try_lock(where: Path) -> int | None:
    """Take the fill lock of `where` without waiting: the descriptor holding it (to be handed
    to the filler it is taken for: `LOCK_FD_ENV`), or None (held by another filler, or no lock
    file can be made there)."""
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd = os.open(where / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


@contextlib.contextmanager
def fill_lock(where: Path) -> Iterator[None]:
    """Hold the cache folder's fill lock (one process compiles into a folder at a time; the
    others wait, at most `lock_wait_s`, then find the kernels there). A filler started with the
    lock taken for it (`LOCK_FD_ENV`) holds that one.

    Raises:
        LockBusy: the lock was not free within `lock_wait_s` (naming its holder's pid).
    """
    inherited = os.environ.pop(LOCK_FD_ENV, "")
    try:
        f = os.fdopen(int(inherited), "r+b") if inherited else None
    except (OSError, ValueError):
        f = None
    held = f is not None  # taken for this process by the one that started it
    if f is None:
        try:
            where.mkdir(parents=True, exist_ok=True)
            f = open(where / LOCK_NAME, "a+b")
        except OSError:  # a read-only folder: nothing to fill, nobody to wait for
            yield
            return
    with f:
        if not held:
            _wait_for_lock(f, where)
        try:
            f.seek(0)
            f.truncate()
            f.write(str(os.getpid()).encode())  # who fills (`filler_pid`)
            f.flush()
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _wait_for_lock(f, where: Path) -> None:
    """Take the lock on the open lock file `f`, waiting at most `lock_wait_s`."""
    bound = lock_wait_s()
    t0 = time.monotonic()
    while True:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() - t0 >= bound:
                raise LockBusy(where, filler_pid(where), bound) from None
            time.sleep(0.05)


def filler_pid(where: Path) -> int | None:
    """The process filling the cache folder `where` now (None: none)."""
    try:
        with open(where / LOCK_NAME, "rb") as f:
            try:
                fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:  # held: its holder wrote its pid
                return int(f.read() or 0) or None
            fcntl.flock(f, fcntl.LOCK_UN)
            return None
    except (OSError, ValueError):
        return None
