"""What an install of art_guidance has: the flight install and the extras.

`pip install art_guidance` is the flight install: the node, `plan`, `replay`, `bag` and the
simulator, with the learned warm start on ONNX Runtime (the exported `.onnx` models). It has no
torch and no `onnx`: training, exporting, distilling and DAgger need the extra [train]
(`pip install "art_guidance[train]"`; `make` installs it). A command that needs an extra says
so in its parser (`set_defaults(needs=...)`) and `art_guidance.cli.main` calls `require` before
it runs: a missing one is a `MissingDependencyError` naming the extra (exit 2), not an
ImportError deep inside.
"""
from __future__ import annotations

import importlib.util
from typing import Iterable

from art_guidance.errors import MissingDependencyError

# module -> the extra of art_guidance that installs it (setup.py extras_require)
EXTRA_OF = {"torch": "train", "onnx": "train"}
TRAIN = ("torch",)              # train, distill, dagger, a checkpoint on the torch runtime
EXPORT = ("torch", "onnx")      # export


def installed(module: str) -> bool:
    """Whether `module` can be imported here (found, not imported)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def require(what: str, modules: Iterable[str]) -> None:
    """Raise MissingDependencyError unless every module of `modules` is installed.

    Args:
        what: what needs them, for the message ("art-guidance train").
        modules: top-level module names (keys of EXTRA_OF).
    """
    missing = [m for m in modules if not installed(m)]
    if missing:
        extras = sorted({EXTRA_OF[m] for m in missing})
        raise MissingDependencyError(what, missing, ",".join(extras))
