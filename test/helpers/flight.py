"""A flight install simulated honestly in the test venv: child interpreters in which importing
torch and onnx fails (what `pip install art_guidance`, without the [train] extra, leaves out).

`blocker_site` writes a sitecustomize whose meta-path finder raises ImportError for the
blocked modules and their submodules, before any other finder looks: `import torch`,
`importlib.util.find_spec("torch")` and everything that imports it fail in that interpreter as
they would where torch is not installed, however the code reaches it.
"""
from __future__ import annotations

import os
from pathlib import Path

FLIGHT_BLOCKED = ("torch", "onnx")  # setup.py extras_require["train"]
REPO = Path(__file__).resolve().parents[2]


def blocker_site(directory: Path, blocked: str | tuple[str, ...] = FLIGHT_BLOCKED) -> Path:
    """A folder holding a sitecustomize.py that makes importing `blocked` fail."""
    blocked = (blocked,) if isinstance(blocked, str) else tuple(blocked)
    site = Path(directory) / "site"
    site.mkdir(parents=True, exist_ok=True)
    (site / "sitecustomize.py").write_text(
        "import sys\n"
        f"_BLOCKED = {blocked!r}\n"
        "class _Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        top = name.partition('.')[0]\n"
        "        if top in _BLOCKED:\n"
        "            raise ImportError(f'{top} is not installed here')\n"
        "sys.meta_path.insert(0, _Block())\n")
    return site


def blocked_env(site: Path, env: dict[str, str] | None = None) -> dict[str, str]:
    """`env` (default: this process's) for a child whose interpreter loads `site` first."""
    env = dict(os.environ if env is None else env)
    paths = [str(site), str(REPO), str(REPO / "test"), env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(p for p in paths if p)
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    return env
