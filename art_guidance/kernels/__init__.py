"""Compiled numerics (numba) behind the array doors of the numpy modules they are named after;
the numpy forms stay where they are and are the test oracles (the same decisions).

One verb chooses the path, `choose`, once at the process's entry: "compiled" (the default where
numba imports and the kernels load) or "numpy". One door prepares it, `prepare` (the node at
configure, the worker at its warm-up, anything else at its first plan through `compiled`),
which loads the kernels:

- a warm cache: the kernels are loaded from it now (~0.4 s here);
- a cache entry that does not load (truncated, emptied, garbled): that kernel's cache files are
  moved aside into the cache folder's `damaged/` (logged, naming them) and it is compiled once
  more, the other kernels loaded as they are (numba keeps each kernel's files apart, and a
  cached kernel holds the code of those it calls); where they cannot be moved, the process
  compiles in memory. Never a traceback;
- a cold cache: with `wait` compiled now (12-15 s here, minutes on a slow flight computer);
  without, the process plans on the numpy path while a background process
  (`python -m art_guidance.kernels`, one per cache folder at a time) compiles into the cache,
  and switches to the compiled path when they are loaded (`status` says which, the node on
  /diagnostics). A flight image fills the cache at build time with that same command.

The cache lives where numba puts it (`cache_note`): `NUMBA_CACHE_DIR` where numba can use it;
else beside the modules where the package folder is writable; else
`~/.cache/art_guidance/numba`. numba checks a cached kernel against its own file only: after
an edit of `drift_bounds`, whose kernels `drift`'s call, clear the cache (or change `drift`
too). This package imports only numpy and numba (and the standard library).
"""
from __future__ import annotations

import contextlib
import enum
import errno
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

NUMERICS = ("compiled", "numpy")
NUMERICS_ENV = "ART_GUIDANCE_NUMERICS"  # a parent's `choose`, inherited by its children
_HERE = Path(__file__).resolve().parent
_LOG = logging.getLogger("art_guidance.kernels")


class Phase(enum.Enum):
    """Where the kernels are in this process."""

    IDLE = "idle"              # not loaded yet
    READY = "ready"            # the compiled path in use
    BACKGROUND = "background"  # the numpy path while the kernels compile in the background
    NUMPY = "numpy"            # the compiled path is not usable


@dataclass
class _KernelState:
    """The process's numerics: the path chosen (`mode`: None until chosen), why numba cannot
    be used (`error`: None until asked, "" when it can), the phase, when the kernels became
    ready [s], what the door did (`note`), the background thread, and why the cache was not
    filled (`cache_problem`)."""

    mode: str | None = None
    error: str | None = None
    ready_s: float | None = None
    phase: Phase = Phase.IDLE
    note: str = ""
    thread: threading.Thread | None = None
    cache_problem: str = ""


_state = _KernelState()
# what writing the cache fails with where the cache cannot be written (not a damaged cache)
UNWRITABLE = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG}
_lock = threading.RLock()


def _choose_cache_dir() -> None:
    """Point numba at a writable cache folder where the package folder is read-only (before
    numba is imported; NUMBA_CACHE_DIR as set is kept)."""
    if os.environ.get("NUMBA_CACHE_DIR") or os.access(_HERE, os.W_OK):
        return
    user = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "art_guidance"
    for where in (user / "numba", Path(tempfile.gettempdir()) / "art_guidance_numba"):
        try:
            where.mkdir(parents=True, exist_ok=True)
            if os.access(where, os.W_OK):
                os.environ["NUMBA_CACHE_DIR"] = str(where)
                return
        except OSError:
            continue


def _import_error() -> str:
    """Why numba cannot be used ("" = it can); imported once, on first need."""
    if _state.error is None:
        try:
            _choose_cache_dir()
            import numba  # noqa: F401
            _state.error = ""
        except Exception as exc:  # numba missing or broken: the numpy path
            _state.error = f"numba is not usable ({type(exc).__name__}: {exc})"
    return _state.error


def choose(mode: str) -> str:
    """Choose the path ("compiled" or "numpy"): the one verb that sets it, at a process's entry
    (the node at configure, the CLI in `main`, the proposal worker at its start) or for a
    comparison (a benchmark, a test; `using` for a block). As osqp takes `algebra=`, nothing
    is imported or loaded here: the kernels load at the first `prepare` or `compiled`, and
    "compiled" turns into the numpy path there where numba cannot be used (`error` says why).
    The processes this one starts afterwards choose alike. Returns `mode`.

    Raises:
        ValueError: an unknown mode.
    """
    if mode not in NUMERICS:
        raise ValueError(f"numerics must be one of {', '.join(NUMERICS)}, got {mode!r}")
    _state.mode = mode
    os.environ[NUMERICS_ENV] = mode
    return mode


def _default_mode() -> str:
    """The path of a process whose entry chose none: its parent's choice (`NUMERICS_ENV`),
    else "compiled"."""
    mode = os.environ.get(NUMERICS_ENV, "")
    return mode if mode in NUMERICS else "compiled"


def compiled() -> bool:
    """Whether the compiled kernels are in use now (the first call goes through `prepare`:
    False while they compile in the background)."""
    if _state.mode is None or (_state.mode == "compiled" and _state.phase is Phase.IDLE):
        prepare()
    return _state.mode == "compiled" and _state.phase is Phase.READY


def error() -> str:
    """Why the compiled path is not available ("" = it is)."""
    return _import_error()


def prepare(mode: str | None = None, *, wait: bool = False) -> str:
    """The door that loads the kernels (module docstring): choose `mode` (None: as set, by
    default "compiled"), then load them from the cache, or compile them now (`wait`) or in the
    background (the numpy path meanwhile). Idempotent; never raises for numba or its cache.
    Returns `status()`."""
    with _lock:
        if mode is not None or _state.mode is None:
            choose(mode or _default_mode())
        if _state.mode == "compiled" and _import_error():
            _state.mode = "numpy"  # numba cannot be used: `error` says why
        if _state.mode != "compiled" or _state.phase in (Phase.READY, Phase.NUMPY):
            return status()
        if _state.phase is Phase.BACKGROUND:
            thread = _state.thread
        else:
            t0 = time.perf_counter()
            try:
                from art_guidance.kernels import cache

                if _load_cached(cache):
                    return _ready(t0)
                if wait:
                    _compile(cache)
                    return _ready(t0)
                thread = _start_background(cache, t0)
            except Exception as exc:  # a kernel that does not compile: the numpy path
                return _unusable(exc)
    if wait and thread is not None:
        thread.join()
    return status()


@contextlib.contextmanager
def using(mode: str, *, wait: bool = True) -> Iterator[str]:
    """The numerics path `mode` for the block (`prepare`d, waited for by default; yields
    `status()`), and the path chosen before it again afterwards: a library call that needs one
    path (`record.replay`) leaves the process's choice as it found it."""
    before = _state.mode
    try:
        yield prepare(mode, wait=wait)
    finally:
        if before is not None:
            choose(before)


def warm_up() -> float | None:
    """`prepare` and wait for the kernels: the time they took to be ready [s], or None where
    the numpy path is taken (`error` says why). Idempotent."""
    prepare(wait=True)
    return ready_s()


def ready_s() -> float | None:
    """How long the kernels took to be ready in this process [s] (None: not in use)."""
    return _state.ready_s if _state.phase is Phase.READY else None


def status() -> str:
    """The numerics in use, in words (with what the door did: a damaged cache moved aside)."""
    phase, note = _state.phase, _state.note
    if _state.mode == "numpy" and not error() and phase is not Phase.NUMPY:
        text = "numpy (as configured)"
    elif phase is Phase.NUMPY or error():
        text = f"numpy, the compiled kernels are not available: {_state.error}"
    elif phase is Phase.READY:
        text = f"compiled, kernels ready in {_state.ready_s:.2f} s (cache: {cache_note()})"
    elif phase is Phase.BACKGROUND:
        text = ("numpy while the kernels compile in the background (a cold cache: "
                f"{cache_note()}); compiled once they are ready")
    else:
        text = "compiled, not loaded yet"
    return f"{text}; {note}" if note else text


def cache_note() -> str:
    """The folder numba caches the kernels in, as it really uses it."""
    if error():
        return "none: numba is not usable"
    try:
        from art_guidance.kernels import cache

        where = cache.folder()
    except Exception as exc:  # a kernel module that does not import
        return f"unknown ({type(exc).__name__}: {exc})"
    if where is None:
        return "none: compiled in memory at every start"
    asked = os.environ.get("NUMBA_CACHE_DIR", "")
    where = where.resolve()
    if asked and Path(asked).resolve() not in (where, *where.parents):
        return f"{where} (NUMBA_CACHE_DIR={asked} cannot be used)"
    return str(where)


def cache_status() -> str:
    """Where the kernels' cache is and whether it holds them (warm, cold or damaged), without
    loading or compiling anything."""
    if error():
        return f"numba is not usable: {error()}"
    try:
        from art_guidance.kernels import cache

        warm, damaged = cache.inspect()
    except Exception as exc:  # a kernel module that does not import
        return f"the kernels do not import ({type(exc).__name__}: {exc})"
    files = _file_names(damaged)
    state = (f"damaged: {', '.join(files)} " + ("does" if len(files) == 1 else "do")
             + " not load") if damaged \
        else "warm: every kernel is there" if warm else "cold: the kernels compile at first use"
    where = cache.folder()
    pid = None if where is None else cache.filler_pid(where)
    if pid:
        state += f"; being filled by process {pid}"
    return f"kernel cache {cache_note()}: {state}"


def _load_cached(cache) -> bool:
    """Load the kernels where the cache holds them all. A damaged file (an index that does not
    load; a data file, looked for once loading failed) moves that kernel's cache files aside,
    the others stay. Whether they are loaded."""
    warm, damaged = cache.inspect()
    if damaged:
        _move_aside(cache, _did_not_load(damaged), list(damaged))
        warm, damaged = cache.inspect()
    if not warm or damaged:
        return False
    try:
        cache.load()
        return True
    except Exception as exc:  # a data file that does not load
        _move_damaged_data(cache, f"loading failed ({type(exc).__name__}: {str(exc)[:200]})")
        return False


def _move_damaged_data(cache, why: str) -> None:
    """Loading or compiling failed (`why`): move aside the kernels whose data files do not
    load, or every kernel's files where none is found."""
    _, damaged = cache.inspect(data=True)
    _move_aside(cache, f"{why}; {_did_not_load(damaged)}" if damaged else why,
                list(damaged) or None)


def _file_names(damaged: dict[str, list[Path]]) -> list[str]:
    """The names of the damaged files (`cache.inspect`'s files by kernel)."""
    return [p.name for paths in damaged.values() for p in paths]


def _did_not_load(damaged: dict[str, list[Path]]) -> str:
    """The damaged files, in words (the first four named)."""
    files = _file_names(damaged)
    return (", ".join(files[:4]) + (f" and {len(files) - 4} more" if len(files) > 4 else "")
            + " did not load")


def _move_aside(cache, why: str, names: list[str] | None = None) -> None:
    """Move the cache files of the kernels `names` (None: of all) aside (or compile in memory
    where they cannot be)."""
    moved, failed = cache.move_aside(names)
    where = cache.folder()
    if failed:
        cache.in_memory()
        note = (f"damaged kernel cache in {where} ({why}) could not be moved aside ({failed}): "
                "compiled in memory")
    else:
        which = "" if names is None else f" of {', '.join(names)}"
        note = (f"damaged kernel cache in {where} ({why}): {len(moved)} files{which} moved to "
                f"{where / cache.DAMAGED_FOLDER}, compiled again")
    _state.note = note
    _LOG.warning(note)


def _compile(cache) -> None:
    """Compile into the cache (one process per folder at a time), or in memory where the
    cache cannot be written (a full disk, a quota, a read-only file system: the files written
    so far stay where they are) or a damaged file gets in the way (moved aside)."""
    where = cache.folder()
    try:
        if where is None:
            cache.load()
            return
        with cache.fill_lock(where):
            if not _load_cached(cache):
                cache.load()
    except cache.LockBusy as exc:  # a stalled filler: compile here, do not wait for ever
        _not_filled(cache, f"{exc}: gave up waiting, compiled in memory")
        cache.load()
    except Exception as exc:  # damage found while compiling, an unwritable folder
        full = unwritable(exc)
        if full is None:
            _move_damaged_data(cache, f"compiling failed ({type(exc).__name__}: "
                               f"{str(exc)[:200]})")
        else:
            _not_filled(cache, f"the kernel cache in {where} cannot be written "
                        f"({errno.errorcode.get(full.errno, full.errno)}: "
                        f"{os.strerror(full.errno or 0)}: a full disk, a quota or a read-only "
                        "file system): compiled in memory, the cache left as it is")
        cache.load()


def _not_filled(cache, note: str) -> None:
    """This process compiles the kernels in memory, its cache not filled: said (`note`,
    `status`, the log) and kept as the reason (`cache_problem`)."""
    cache.in_memory()
    _state.note = _state.cache_problem = note
    _LOG.warning(note)


def unwritable(exc: BaseException) -> OSError | None:
    """The OSError in `exc`'s chain that says the cache cannot be written (`UNWRITABLE`), or
    None."""
    seen: BaseException | None = exc
    for _ in range(16):
        if seen is None:
            return None
        if isinstance(seen, OSError) and seen.errno in UNWRITABLE:
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def cache_problem() -> str:
    """Why this process compiled the kernels in memory instead of into their cache (the cache
    cannot be written, or another filler held it too long; "" = it did not)."""
    return _state.cache_problem


def _start_background(cache, t0: float) -> threading.Thread:
    """The numpy path now; a background process compiles into the cache (this process then
    loads from it), or this process compiles in memory in a thread where there is none."""
    where = cache.folder()
    child = None
    if where is not None:
        child = _start_filler(cache, where)

    def finish() -> None:  # never under the lock: `compiled` keeps answering meanwhile
        try:
            if child is not None:
                code = child.wait()
                if code != 0:  # killed, or failed: this process compiles, and says so
                    _LOG.warning("kernels: the background filler (pid %d) ended with exit "
                                 "code %d: this process compiles the kernels", child.pid, code)
            if not _load_cached(cache):
                _compile(cache)
            with _lock:
                _ready(t0)
        except Exception as exc:  # the numpy path stays
            with _lock:
                _unusable(exc)

    thread = threading.Thread(target=finish, name="art_guidance_kernels", daemon=True)
    _state.phase = Phase.BACKGROUND
    _state.thread = thread
    thread.start()
    _LOG.info("kernels: %s", status())
    return thread


def _start_filler(cache, where: Path) -> subprocess.Popen | None:
    """The background filler of `where` (`python -m art_guidance.kernels`), started with the
    folder's fill lock taken for it; None where another filler holds the lock (one filler per
    folder: this process then waits for that one's kernels) or none could be started."""
    fd = cache.try_lock(where)
    filler = None if fd is not None else cache.filler_pid(where)
    if filler:
        _LOG.info("kernels: process %s fills %s; waiting for its kernels", filler, where)
        return None
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(_HERE.parent.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}
    if fd is not None:
        env[cache.LOCK_FD_ENV] = str(fd)
    try:
        child = subprocess.Popen([sys.executable, "-m", "art_guidance.kernels", "--quiet"],
                                 env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL,
                                 pass_fds=() if fd is None else (fd,),
                                 start_new_session=True)  # outlives a one-shot command
        if fd is not None:  # who fills (`cache.filler_pid`), from now on
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(child.pid).encode(), 0)
        return child
    except OSError:
        return None
    finally:
        if fd is not None:
            os.close(fd)  # the filler's copy holds the lock now


def _ready(t0: float) -> str:
    _state.phase = Phase.READY
    _state.ready_s = time.perf_counter() - t0
    _state.thread = None
    return status()


def _unusable(exc: Exception) -> str:
    _state.error = f"the compiled kernels failed ({type(exc).__name__}: {exc})"
    _state.mode = "numpy"
    _state.phase = Phase.NUMPY
    _state.thread = None
    _LOG.warning("kernels: %s", status())
    return status()
