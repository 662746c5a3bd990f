"""Shared fixtures: an isolated ROS 2 environment per session (own domain, logs, discovery)."""
from __future__ import annotations

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

from art_guidance.ros.env import isolated_ros_env

TEST_ROOT = Path(__file__).resolve().parent  # on sys.path via setup.cfg `pythonpath`


# DDS domains 100-199 come in pairs (2k, 2k + 1): the first is a process's own, the second is for
# a test that needs a node apart from the one its module already runs. A pytest-xdist worker's
# pair follows from its run (the controller's pid) and its index (PYTEST_XDIST_WORKER = "gw3"),
# so the workers of one run never share a domain, and concurrent runs seldom do.
_DOMAIN_PAIRS = 50


def _domain_pair() -> tuple[int, int]:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker.startswith("gw") and worker[2:].isdigit():
        slot = (os.getppid() + int(worker[2:])) % _DOMAIN_PAIRS
    else:
        slot = os.getpid() % _DOMAIN_PAIRS
    return 100 + 2 * slot, 101 + 2 * slot


DOMAIN_ID, SECOND_DOMAIN_ID = _domain_pair()


def _ros_env() -> dict[str, str]:
    # Own domain per process so concurrent runs and workers on one machine do not cross-talk.
    home = tempfile.mkdtemp(prefix="art_guidance_ros_")
    atexit.register(shutil.rmtree, home, True)  # the nodes' logs go with the process
    env = isolated_ros_env(home, DOMAIN_ID)
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    return env


ROS_ENV = _ros_env()
os.environ.update(ROS_ENV)


@pytest.fixture(scope="session")
def ros_env() -> dict[str, str]:
    """Environment for child processes that must share this session's DDS domain."""
    env = dict(os.environ)
    env.update(ROS_ENV)
    env["PYTHONUNBUFFERED"] = "1"
    # child processes import the test helpers as `helpers.<module>` too
    env["PYTHONPATH"] = os.pathsep.join([str(TEST_ROOT), env.get("PYTHONPATH", "")])
    return env


@pytest.fixture(scope="session")
def second_ros_env(ros_env: dict[str, str]) -> dict[str, str]:
    """`ros_env` on this process's second domain: for a node kept apart from the one a module's
    fixture runs."""
    return dict(ros_env, ROS_DOMAIN_ID=str(SECOND_DOMAIN_ID))


@pytest.fixture(scope="module")
def horizon():
    """The paper scenario's horizon (Table I chief orbit, 1.29 orbits, 100 nodes)."""
    import numpy as np

    from art_guidance.config import ScenarioConfig
    from art_guidance.dynamics import Horizon, time_grid_s

    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    return Horizon.build(chief, time_grid_s(chief[0], sc.n_orbits, sc.n_nodes))


@pytest.fixture(scope="session")
def python_exe() -> str:
    """The interpreter running the tests (the project venv)."""
    return sys.executable


# Fixtures that outlive a test: a file that uses one runs whole on one pytest-xdist worker.
_SHARED_SCOPES = ("class", "module", "package")


def _shared_scopes(item: pytest.Item) -> set[str]:
    info = getattr(item, "_fixtureinfo", None)
    chains = info.name2fixturedefs.values() if info is not None else ()
    return {d.scope for chain in chains for d in chain if d.scope in _SHARED_SCOPES}


def _groups(items: list[pytest.Item]) -> dict[str, str]:
    """File -> xdist group for the files that have a class-, module- or package-scoped fixture
    (a package-scoped one groups its whole folder)."""
    groups: dict[str, str] = {}
    for item in items:
        file = item.nodeid.split("::")[0]
        scopes = _shared_scopes(item)
        if "package" in scopes:
            groups[file] = file.rpartition("/")[0] or "."
        elif scopes:
            groups.setdefault(file, file)
    packages = {g for f, g in groups.items() if g != f}
    for item in items:
        file = item.nodeid.split("::")[0]
        if (file.rpartition("/")[0] or ".") in packages:
            groups[file] = file.rpartition("/")[0] or "."
    return groups


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]):
    """`--dist loadgroup`: the tests of a file with a fixture that outlives a test go to one
    worker together, so no worker builds that fixture again for its share of the file.

    pytest-xdist reads the `xdist_group` marks in its own hook (run inside this wrapper) and
    tells the controller by appending "@group" to the node ids it sends; it does so by setting
    `item._nodeid`, which pytest 9.2 no longer reads (node ids are structured there), so every
    test would be scheduled on its own. Where that happened, the suffix is added here.

    The controller hands out the groups first (largest first), then the single tests in
    collection order; on the workers, the single tests marked slow are collected first (a
    group keeps its order), so that the run does not end with one worker on a long test while
    the other has nothing left."""
    if not config.pluginmanager.hasplugin("xdist"):
        return (yield)
    groups = _groups(items)
    for item in items:
        group = groups.get(item.nodeid.split("::")[0])
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    result = yield
    if getattr(config.option, "loadgroup", False):  # set on the workers of `--dist loadgroup`
        items[:] = sorted(items, key=lambda item: item.nodeid.split("::")[0] not in groups
                          and item.get_closest_marker("slow") is None)
        for item in items:
            names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                            for m in item.iter_markers("xdist_group")})
            suffix = "@" + "_".join(names)
            node_id = getattr(item, "_id", None)
            if names and "@" not in item.nodeid and hasattr(node_id, "parse"):
                item._id = type(node_id).parse(item.nodeid + suffix)
    return result


def pytest_configure(config: pytest.Config) -> None:
    """Compile the numba kernels (or load them from their cache) once per run, in the
    controller, before pytest-xdist starts its workers: they then load the cached kernels."""
    if not hasattr(config, "workerinput"):
        from art_guidance import kernels

        kernels.warm_up()
