"""Print the uv arguments that point uv at the package sources pip is configured with.

`make` installs the pinned packages with uv (in parallel, ~10x faster than pip here), but uv
does not read pip's configuration: the indexes and wheel folders a machine gives pip (pip.conf,
PIP_* variables; `pip config list` shows them) are handed to uv here, so both install from the
same places. Nothing configured: uv uses PyPI, as pip would.
"""
import shlex
import subprocess
import sys


def uv_args(listed: str) -> list[str]:
    """The uv arguments for pip's configuration as `pip config list` prints it."""
    # "global.find-links='/opt/wheels'", ":env:.find-links='...'": as pip ranks them, a PIP_*
    # variable over the site file over the user's over the global one
    rank = {":env:": 0, "site": 1, "user": 2, "global": 3}
    found: dict[str, tuple[int, str]] = {}
    for line in listed.splitlines():
        key, _, value = line.partition("=")
        scope, _, name = key.rpartition(".")
        if name and value:
            entry = (rank.get(scope, 4), value.strip("'\""))
            found[name] = min(found.get(name, entry), entry)
    config = {name: value for name, (_, value) in found.items()}
    args = ["--native-tls"]
    if "index-url" in config:
        args += ["--index-url", config["index-url"]]
    for url in config.get("extra-index-url", "").split():
        args += ["--extra-index-url", url]
    for where in config.get("find-links", "").split():
        args += ["--find-links", where]
    if len(args) > 1:  # pinned versions: take them from whichever source has them
        args += ["--index-strategy", "unsafe-best-match"]
    return args


def main() -> int:
    listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True,
                            text=True).stdout
    print(shlex.join(uv_args(listed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
