"""Exception hierarchy: one root, a few typed children that carry the offending values."""
from __future__ import annotations

from typing import Any


class GuidanceError(Exception):
    """Root of every error this package raises on purpose."""


class InputError(GuidanceError, ValueError):
    """Bad input: NaN, wrong shape, out-of-domain value.

    Attributes:
        field: name of the offending input.
        value: the offending value (or a short summary of it).
    """

    def __init__(self, field: str, reason: str, value: Any = None) -> None:
        self.field = field
        self.reason = reason
        self.value = value
        shown = "" if value is None else f" (got {_short(value)})"
        super().__init__(f"{field}: {reason}{shown}")


class ConfigError(GuidanceError, ValueError):
    """A configuration value or file is invalid."""


class DatasetError(GuidanceError, RuntimeError):
    """A dataset directory is corrupt, incomplete or inconsistent with its manifest."""


class SolverError(GuidanceError, RuntimeError):
    """A numerical solver failed in a way the caller cannot recover from."""


class DeadlineError(GuidanceError, TimeoutError):
    """A planning deadline passed before a step that would have run past it."""


class ModelError(GuidanceError, RuntimeError):
    """A model checkpoint is missing, corrupt or incompatible."""


class MissingDependencyError(GuidanceError, ImportError):
    """What was asked needs Python packages that this install does not have (the flight install
    has no torch: `art_guidance.extras`).

    Attributes:
        what: what needs them (e.g. "art-guidance train").
        modules: the missing modules.
        extra: the extra of art_guidance that installs them.
    """

    def __init__(self, what: str, modules: list[str], extra: str) -> None:
        self.what, self.modules, self.extra = what, list(modules), extra
        super().__init__(f"{what} needs {' and '.join(self.modules)}, which this install does "
                         f"not have: install the [{extra}] extra, pip install "
                         f"'art_guidance[{extra}]' (from a checkout: pip install '.[{extra}]')")


class CheckpointError(ModelError):
    """A checkpoint file is refused: missing, truncated, corrupt, unsafe or incompatible.

    Attributes:
        path: the checkpoint file.
        reason: why it was refused.
    """

    def __init__(self, path: object, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


def _short(value: Any, limit: int = 120) -> str:
    """A short, human-readable rendering (numpy scalars and arrays as plain numbers)."""
    if hasattr(value, "tolist"):  # numpy scalar or array: np.float64(0.0) -> 0.0
        value = value.tolist()
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
