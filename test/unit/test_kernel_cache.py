"""The one door that loads the kernels (`kernels.prepare`): a damaged cache (an index truncated,
emptied or garbled, a data file truncated) is moved aside and compiled again, never a traceback
and never another exit code; a cold cache plans on the numpy path while a background process
fills it; `cache_note` names the folder numba really uses.

Each test works on a copy of this run's warm cache in its own NUMBA_CACHE_DIR (numba checks a
cached kernel against its source file, the same here), so nothing compiles but where a test
says so; a background filler a test does not wait for is stopped."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.processes import stop_kernel_filler

from art_guidance import kernels
from art_guidance.kernels import cache

ROOT = Path(__file__).resolve().parents[2]
DAMAGES = ("truncated", "emptied", "garbled", "data")


def _env(cache_dir: Path) -> dict[str, str]:
    return {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir),
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def _python(code: str, cache_dir: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=_env(cache_dir),
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> tuple[Path, str]:
    """(a NUMBA_CACHE_DIR holding this run's warm kernels, the sub-folder numba uses there)."""
    kernels.warm_up()
    source = cache.folder()
    root = tmp_path_factory.mktemp("numba_cache")
    out = _python("from art_guidance.kernels import cache; print(cache.folder())", root)
    where = Path(out.stdout.strip().splitlines()[-1])
    assert where.is_relative_to(root), out
    where.mkdir(parents=True, exist_ok=True)
    for f in source.glob("*.nb[ic]"):
        shutil.copy2(f, where / f.name)
    return root, where.name


def _cache_copy(template, tmp_path: Path, damage: str | None,
                kernel: str = "*") -> tuple[Path, Path]:
    """(NUMBA_CACHE_DIR, its kernel folder): a copy of the warm cache with `damage` done to
    the files of `kernel` ("module.name"; "*": of every kernel)."""
    root, sub = template
    cache_dir = tmp_path / "numba"
    shutil.copytree(root, cache_dir)
    where = cache_dir / sub
    for f in sorted(where.glob(f"{kernel}-*" + (".nbi" if damage != "data" else ".nbc"))):
        data = f.read_bytes()
        if damage in ("truncated", "data"):
            f.write_bytes(data[:len(data) // 2])
        elif damage == "emptied":
            f.write_bytes(b"")
        elif damage == "garbled":
            noise = np.random.default_rng(0).integers(1, 256, len(data) - 40, dtype=np.uint8)
            f.write_bytes(data[:40] + (np.frombuffer(data[40:], np.uint8) ^ noise).tobytes())
    return cache_dir, where


def _stop_filler(where: Path) -> None:
    """Stop the background filler of `where`, which must have started, so that it does not
    compile on beside the other tests."""
    assert stop_kernel_filler(where) is not None, "no background filler started"


@pytest.mark.parametrize("damage", DAMAGES)
def test_a_damaged_cache_is_moved_aside_and_compiled_again(template, tmp_path, damage):
    """The door finds the damage (an index that does not load, or a data file failing to
    load), moves the kernels' files into damaged/, names them in the log, and plans on."""
    cache_dir, where = _cache_copy(template, tmp_path, damage)
    code = ("from art_guidance import kernels\n"
            "print('STATUS', kernels.prepare('compiled'))\n"
            "print('COMPILED', kernels.compiled())\n")
    out = _python(code, cache_dir)
    _stop_filler(where)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "damaged kernel cache" in out.stderr and "moved to" in out.stderr, out.stderr
    assert (where / cache.DAMAGED_FOLDER).is_dir()
    assert "COMPILED False" in out.stdout  # the numpy path while they compile again
    if damage != "data":
        assert ".nbi" in out.stderr  # the files that did not load, named


def test_a_truncated_cache_under_plan_exits_as_without_damage_and_is_compiled_again(
        template, tmp_path):
    """`art-guidance plan` on a cache whose indexes are truncated (it was EOFError, exit 1):
    exit 0, the same plan, the damage named, a background filler compiling them again."""
    args = [sys.executable, "-m", "art_guidance.cli", "plan", "--seed", "3", "--warm-start",
            "cvx", "--json"]
    clean_dir, _ = _cache_copy(template, tmp_path / "clean", None)
    clean = subprocess.run(args + [str(tmp_path / "clean.json")], env=_env(clean_dir),
                           capture_output=True, text=True, timeout=300)
    cache_dir, where = _cache_copy(template, tmp_path, "truncated")
    damaged = subprocess.run(args + [str(tmp_path / "damaged.json")], env=_env(cache_dir),
                             capture_output=True, text=True, timeout=300)
    assert clean.returncode == damaged.returncode == 0, damaged.stderr
    assert "Traceback" not in damaged.stderr and "moved to" in damaged.stderr
    assert (tmp_path / "clean.json").read_text().count("dv_rtn_mps") == 1
    strip = [line.split(", margin")[0] for line in (clean.stdout, damaged.stdout)]
    assert strip[0] == strip[1], (clean.stdout, damaged.stdout)
    _stop_filler(where)  # the filler compiling them again (~15 s; not waited for)


@pytest.mark.parametrize("damage", ["emptied", "garbled"])
def test_demo_offline_on_a_damaged_cache_exits_as_without_damage(template, tmp_path, damage):
    cache_dir, where = _cache_copy(template, tmp_path, damage)
    out = subprocess.run([sys.executable, "-m", "art_guidance.cli", "demo", "--offline"],
                         env=_env(cache_dir), capture_output=True, text=True, timeout=300)
    _stop_filler(where)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "free drift" in out.stdout and "moved to" in out.stderr


def test_cache_note_names_the_folder_numba_really_uses(tmp_path):
    """NUMBA_CACHE_DIR naming a regular file: numba falls back to another folder, and the
    note says which, and that the variable cannot be used."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    out = subprocess.run([sys.executable, "-m", "art_guidance.kernels", "--status"],
                         env=_env(blocker), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert f"NUMBA_CACHE_DIR={blocker} cannot be used" in out.stdout, out.stdout
    assert str(cache.folder()) in out.stdout or "kernel cache /" in out.stdout


def _bag(tmp_path: Path) -> Path:
    """A recorded bag of two real plans (the recorder as the node drives it)."""
    pytest.importorskip("rclpy")
    from helpers.plans import seed_plans
    from helpers.ros_client import nav_msg

    from art_guidance.record.recorder import McapRecorder
    from art_guidance.ros.adapters import plan_to_msg, solve_record_msg

    pipeline, results = seed_plans(range(2))
    rec = McapRecorder(tmp_path / "bag", {"config": pipeline.config_json()}, 1 << 26)
    for k, (s, result) in enumerate(results):
        stamp = 1_800_000_000_000_000_000 + k * 1_000_000_000
        assert rec.record_solve([
            ("/nav/relative_state", nav_msg(stamp, s.rtn0)),
            ("/guidance/solve_record", solve_record_msg(result, stamp, f"plan-{k}", "test")),
            ("/guidance/maneuver_plan", plan_to_msg(result, stamp, f"plan-{k}"))], stamp)
    rec.finish()
    return tmp_path / "bag"


def test_replay_on_a_truncated_cache_exits_as_without_damage(template, tmp_path):
    """`replay` died in numba's _load_index with exit 1, its code for a solve that does not
    reproduce: now exit 0 as on an intact cache, every solve compared and matching (replay
    waits for the kernels of the solves recorded on the compiled path: it compiles the one
    whose index is truncated itself, or waits for a filler another step started)."""
    bag = _bag(tmp_path)
    codes = []
    for damage in (None, "truncated"):
        cache_dir, where = _cache_copy(template, tmp_path / str(damage), damage, "drift.minimum")
        out = subprocess.run([sys.executable, "-m", "art_guidance.cli", "replay", str(bag)],
                             env=_env(cache_dir), capture_output=True, text=True, timeout=300)
        assert "Traceback" not in out.stderr, out.stderr
        codes.append(out.returncode)
        if damage:
            assert "moved to" in out.stderr and "drift.minimum-" in out.stderr, out.stderr
            stop_kernel_filler(where, wait_s=2.0)  # one another step started, if any
    assert codes == [0, 0], codes


def test_only_the_damaged_kernels_are_moved_aside_and_compiled_again(template, tmp_path):
    """numba keeps each kernel's files apart, and a cached kernel holds the code of those it
    calls: one kernel's truncated index (drift.minimum) and another's truncated data file
    (drift.violated, found once loading fails) move those two kernels' files aside, and only
    theirs; the others stay and load, those two compile again into the cache (the compiled
    path in use, the cache warm again)."""
    cache_dir, where = _cache_copy(template, tmp_path, "truncated", "drift.minimum")
    for f in where.glob("drift.violated-*.nbc"):
        f.write_bytes(f.read_bytes()[:100])
    kept = {p.name: p.stat().st_mtime_ns for p in where.glob("*.nb[ic]")
            if not p.name.startswith(("drift.minimum-", "drift.violated-"))}
    code = ("from art_guidance import kernels\n"
            "kernels.prepare('compiled', wait=True)\n"
            "print('COMPILED', kernels.compiled())\n"
            "print('STATUS', kernels.cache_status())\n")
    out = _python(code, cache_dir)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "COMPILED True" in out.stdout and "warm: every kernel is there" in out.stdout
    moved = sorted(p.name for p in (where / cache.DAMAGED_FOLDER).iterdir())
    assert {n.split("-")[0] for n in moved} == {"drift.minimum", "drift.violated"}, moved
    assert "files of drift.minimum moved" in out.stderr, out.stderr
    assert "files of drift.violated moved" in out.stderr, out.stderr
    assert {p.name: p.stat().st_mtime_ns for p in where.glob("*.nb[ic]")
            if p.name in kept} == kept  # the others: left as they were
    assert (where / next(n for n in moved if n.endswith(".nbi"))).is_file()  # compiled again


def test_a_full_disk_compiles_in_memory_and_moves_nothing(template, tmp_path):
    """ENOSPC while the cache is written (here: a warm cache that lacks one kernel, the disk full
    at that kernel's first data file; a 600 kB folder behaves alike) is not damage: the files
    already there and those written before stay where they are, nothing moves to `damaged/`,
    the kernel is compiled in memory (the compiled path in use), the message names the full
    disk, and `art-guidance kernels` (the flight image's build step) exits 1. One kernel
    compiles, not all of them."""
    code = """
import errno, sys
from numba.core import caching
def save_data(self, name, data):
    raise OSError(errno.ENOSPC, "No space left on device")
caching.IndexDataCacheFile._save_data = save_data
from art_guidance import kernels
from art_guidance.kernels.__main__ import main
code = main([])
print("COMPILED" if kernels.compiled() else "NUMPY")
sys.exit(code)
"""
    cache_dir, where = _cache_copy(template, tmp_path, None)
    missing = sorted(where.glob("horizon.*"))
    assert missing, sorted(p.name for p in where.iterdir())
    for f in missing:
        f.unlink()
    before = sorted(p.name for p in where.iterdir())
    out = _python(code, cache_dir)
    assert out.returncode == 1, out.stdout + out.stderr
    assert "cannot be written (ENOSPC" in out.stdout, out.stdout
    assert "compiled in memory" in out.stdout and "COMPILED" in out.stdout
    assert "Traceback" not in out.stderr
    assert not list(cache_dir.rglob(cache.DAMAGED_FOLDER))
    after = {p.name for p in where.iterdir()}
    assert set(before) <= after  # what was there stays, and what was written before ENOSPC:
    written = after - set(before) - {cache.LOCK_NAME}
    assert {n.split(".")[0] for n in written} <= {"horizon"}  # its index


def _hold_lock(where: Path):
    """The fill lock of `where` taken by this process, as a stalled filler holds it."""
    import fcntl

    where.mkdir(parents=True, exist_ok=True)
    f = open(where / cache.LOCK_NAME, "a+b")
    fcntl.flock(f, fcntl.LOCK_EX)
    f.seek(0)
    f.truncate()
    f.write(str(os.getpid()).encode())
    f.flush()
    return f


def test_a_stalled_filler_s_lock_is_waited_for_within_a_bound_naming_its_pid(
        tmp_path, monkeypatch):
    """A filler that stalls holding the fill lock: a waiter gives up after the bound
    (`LOCK_WAIT_ENV`; it then compiles in memory and `art-guidance kernels` exits 1), naming
    the holder's pid, and `kernels --status` names the filler in progress."""
    root = tmp_path / "numba"
    out = _python("from art_guidance.kernels import cache; print(cache.folder())", root)
    where = Path(out.stdout.strip().splitlines()[-1])
    held = _hold_lock(where)
    try:
        monkeypatch.setenv(cache.LOCK_WAIT_ENV, "0.3")
        with pytest.raises(cache.LockBusy, match=f"process {os.getpid()} has held the fill "
                           "lock"):
            with cache.fill_lock(where):
                pass
        status = _python("from art_guidance import kernels; print(kernels.cache_status())",
                         root)
        assert f"being filled by process {os.getpid()}" in status.stdout, status.stdout
    finally:
        held.close()
    with cache.fill_lock(where):  # free again: taken at once
        assert cache.filler_pid(where) == os.getpid()


def test_one_filler_per_folder(tmp_path):
    """A process that finds the folder's fill lock held starts no filler of its own (it waits
    for that one's kernels); one that finds it free starts one, holding the lock for it."""
    code = ("import sys; from pathlib import Path; from art_guidance import kernels; "
            "from art_guidance.kernels import cache; "
            "child = kernels._start_filler(cache, Path(sys.argv[1])); "
            "print('NONE' if child is None else 'STARTED'); "
            "child is None or (child.kill(), child.wait())")
    where = tmp_path / "kernels"

    def start() -> str:
        return subprocess.run([sys.executable, "-c", code, str(where)],
                              env=_env(tmp_path / "numba"), capture_output=True, text=True,
                              timeout=120).stdout.strip()

    held = _hold_lock(where)
    try:
        assert start() == "NONE"
    finally:
        held.close()
    assert start() == "STARTED"
