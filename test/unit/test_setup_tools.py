"""The set-up's own tools (.ci/): the uv arguments taken from pip's configuration, and the lock
written from pip's resolution report. Pure text in, text out: the same on every machine."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / ".ci" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_uv_takes_the_sources_pip_is_configured_with_a_variable_over_a_file():
    uv_args = _load("uv_sources").uv_args
    listed = ("global.extra-index-url='file:///a/simple file:///b/simple'\n"
              "global.find-links='/wheels'\n"
              ":env:.find-links='/env/wheels'\n"
              "user.index-url='https://mirror.example/simple'\n"
              "global.cert='/etc/ssl/certs/ca-certificates.crt'\n")
    assert uv_args(listed) == [
        "--native-tls", "--index-url", "https://mirror.example/simple",
        "--extra-index-url", "file:///a/simple", "--extra-index-url", "file:///b/simple",
        "--find-links", "/env/wheels", "--index-strategy", "unsafe-best-match"]
    assert uv_args("") == ["--native-tls"]  # nothing configured: PyPI, as for pip


def test_with_no_pip_configuration_uv_gets_no_source():
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env["PIP_CONFIG_FILE"] = os.devnull  # pip then reads no configuration file
    out = subprocess.run([sys.executable, str(ROOT / ".ci" / "uv_sources.py")], env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.split() == ["--native-tls"], out


def test_the_lock_names_each_resolved_package_once_without_local_labels():
    pin_lines = _load("lock_pins").pin_lines

    def item(name: str, version: str) -> dict:
        return {"metadata": {"name": name, "version": version}}

    report = {"install": [item("torch", "2.13.0+cpu"), item("art_guidance", "0.1.0"),
                          item("ros-rclpy", "7.1.6"), item("Jinja2", "3.1.6")]}
    assert pin_lines(report) == ["Jinja2==3.1.6", "ros-rclpy==7.1.6", "torch==2.13.0"]


def test_the_committed_lock_pins_every_package_once():
    pins = [line for line in (ROOT / ".ci" / "constraints.txt").read_text().splitlines()
            if line and not line.startswith("#")]
    names = [line.split("==")[0].replace("_", "-").lower() for line in pins]
    assert all("==" in line for line in pins) and len(names) == len(set(names))
    assert {"torch", "onnx", "ros-rclpy", "setuptools"} <= set(names)
    assert "rclpy" not in names  # a name no index serves (embedded ROS wheel metadata)
