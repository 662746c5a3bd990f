"""Compiled numerics (numba) behind the array doors of the numpy modules they are named after;
the numpy forms stay where they are and are the test oracles.

One process-wide setting chooses the path (`set_numerics`): "compiled" (the default where numba
imports and the kernels compile) or "numpy". `warm_up` compiles the kernels or loads them from
numba's on-disk cache, before the first plan; a failure is reported and the numpy path taken.

The cache lives in `NUMBA_CACHE_DIR` where that is set; else beside the modules where the
package folder is writable; else in `~/.cache/art_guidance/numba`; else nowhere (compiled in
memory at every start, `cache_note` says so). numba checks a cached kernel against its own
file only: after an edit of `drift_bounds`, whose kernels `drift`'s call, clear the cache (or
change `drift` too). This package imports only numpy and numba.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

NUMERICS = ("compiled", "numpy")
_HERE = Path(__file__).resolve().parent


def _choose_cache_dir() -> str:
    """Where numba caches compiled kernels (sets NUMBA_CACHE_DIR before numba is imported)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return f"NUMBA_CACHE_DIR={os.environ['NUMBA_CACHE_DIR']}"
    if os.access(_HERE, os.W_OK):
        return f"beside the modules ({_HERE})"
    user = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "art_guidance"
    for where in (user / "numba", Path(tempfile.gettempdir()) / "art_guidance_numba"):
        try:
            where.mkdir(parents=True, exist_ok=True)
            if os.access(where, os.W_OK):
                os.environ["NUMBA_CACHE_DIR"] = str(where)
                return f"NUMBA_CACHE_DIR={where} (the package folder is read-only)"
        except OSError:
            continue
    return "none: no writable cache folder, compiled in memory at every start"


cache_note = _choose_cache_dir()
_state = {"mode": None, "error": None, "warm_up_s": None}


def _import_error() -> str:
    """Why numba cannot be used ("" = it can); imported once, on first need."""
    if _state["error"] is None:
        try:
            import numba  # noqa: F401
            _state["error"] = ""
        except Exception as exc:  # numba missing or broken: the numpy path
            _state["error"] = f"numba is not usable ({type(exc).__name__}: {exc})"
    return _state["error"]


def set_numerics(mode: str) -> str:
    """Choose the path ("compiled" or "numpy"); returns the path taken ("numpy" where the
    kernels cannot be used: `error` says why).

    Raises:
        ValueError: an unknown mode.
    """
    if mode not in NUMERICS:
        raise ValueError(f"numerics must be one of {', '.join(NUMERICS)}, got {mode!r}")
    _state["mode"] = mode if mode == "numpy" or not _import_error() else "numpy"
    return _state["mode"]


def compiled() -> bool:
    """Whether the compiled kernels are in use (by default where numba imports)."""
    if _state["mode"] is None:
        set_numerics("compiled")
    return _state["mode"] == "compiled"


def error() -> str:
    """Why the compiled path is not available ("" = it is)."""
    return _import_error()


def warm_up() -> float | None:
    """Compile the kernels (or load them from the cache) now; returns the time taken [s], or
    None where the numpy path is taken (`error` says why). Idempotent."""
    if not compiled():
        return None
    if _state["warm_up_s"] is not None:
        return _state["warm_up_s"]
    t0 = time.perf_counter()
    try:
        from art_guidance.kernels import drift, horizon

        drift.warm_up()
        horizon.warm_up()
    except Exception as exc:  # a kernel that does not compile: the numpy path
        _state["error"] = f"the compiled kernels failed ({type(exc).__name__}: {exc})"
        _state["mode"] = "numpy"
        return None
    _state["warm_up_s"] = time.perf_counter() - t0
    return _state["warm_up_s"]
