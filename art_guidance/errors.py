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
