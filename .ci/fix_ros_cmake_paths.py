"""Rewrite the build-machine paths baked into the ROS 2 wheels' exported CMake files.

The ros-jazzy wheels ship `*.cmake` files under `<venv>/share` that name the wheel-build machine's
Python include directory and numpy include directory. Building an interface package against them
fails unless those paths point at this venv's. Idempotent; run after every install of ROS wheels.
"""
import re
import sys
import sysconfig
from pathlib import Path

import numpy


def main() -> int:
    share = Path(sys.prefix) / "share"
    py_inc = sysconfig.get_paths()["include"]
    np_inc = numpy.get_include()
    py_pat = re.compile(r"/[^;\"\s]*/include/python3\.\d+")
    np_pat = re.compile(r"/[^;\"\s]*/numpy/(?:_core|core)/include")
    changed = 0
    for path in share.glob("*/cmake/*.cmake"):
        text = path.read_text(encoding="utf-8", errors="surrogateescape")
        new = np_pat.sub(np_inc, py_pat.sub(py_inc, text))
        if new != text:
            path.write_text(new, encoding="utf-8", errors="surrogateescape")
            changed += 1
    print(f"fix_ros_cmake_paths: rewrote {changed} file(s) under {share}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
