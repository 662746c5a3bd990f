"""Write the lock (.ci/constraints.txt) from pip's resolution report (`make lock`).

Each package pip would install, as the index names it, at the version it resolved (a local
version label such as torch's "+cpu" dropped: the pin takes the build the machine's sources
offer). `make` installs exactly this list without resolving again (`pip check` then proves it
is closed), so it names only installable distributions: not the names that some ROS 2 wheels'
embedded metadata adds to `pip freeze` (`rclpy`, `std_msgs`, ...), which no index serves.

    python .ci/lock_pins.py REPORT.json OUT.txt
"""
import json
import sys

HEADER = """\
# Every Python package the venv holds, pinned: `make` installs exactly these (no resolver; uv, or
# pip where uv cannot be installed), then this package without dependencies. Refresh with
# `make lock` (resolves .ci/requirements-ros.txt and setup.py's requirements with extras
# [train,test,distributed] in a scratch venv, then writes this file from the resolution).
"""


def pin_lines(report: dict) -> list[str]:
    """"name==version" of every package in pip's resolution report but this one, sorted by
    name (a local version label dropped)."""
    pins = {}
    for item in report["install"]:
        name, version = item["metadata"]["name"], item["metadata"]["version"]
        if name.replace("-", "_").lower() != "art_guidance":
            pins[name] = version.split("+")[0]
    return [f"{name}=={pins[name]}" for name in sorted(pins, key=str.lower)]


def main(report_path: str, out_path: str) -> int:
    with open(report_path) as fh:
        lines = pin_lines(json.load(fh))
    with open(out_path, "w") as fh:
        fh.write(HEADER + "\n".join(lines) + "\n")
    print(f"{len(lines)} packages pinned in {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
