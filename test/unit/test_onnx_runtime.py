"""The exported model on ONNX Runtime: the same proposals as torch, checked files, clear refusals,
and a flight without torch.

Torch (the checkpoint) is the oracle: on held-out scenarios of each shipped model's dataset the
learned step on ONNX Runtime gives the same constraint-to-go and the same decision, with
controls within `DV_TOL_MPS` (measured: 3e-5 m/s; `art-guidance bench runtime` runs 100
scenarios per mode). A bad exported file, an unknown runtime or one that is not installed is
refused with a message that names it; the planner then flies the CVX warm start.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from helpers.flight import blocked_env, blocker_site
from helpers.shipped import heldout_requests, runtimes_agree

from art_guidance.art.onnx_art import METADATA_KEY, load_exported
from art_guidance.art.provider import (
    DEFAULT_MODELS, ArtWarmStart, default_model_path, models_dir, pinned_sha256,
    resolve_runtime,
)
from art_guidance.cli import main as cli_main
from art_guidance.errors import CheckpointError, InputError

DV_TOL_MPS = 1e-3   # largest difference of a proposed control, ONNX vs torch [m/s]
N_SCENARIOS = 12    # held-out scenarios per mode here (the benchmark runs 100)


@pytest.fixture(scope="module")
def chance_onnx() -> Path:
    return default_model_path("chance").with_suffix(".onnx")


def _python(code: str, block: str, tmp_path: Path, timeout: float = 300.0):
    """Run `code` in a fresh interpreter in which importing `block` fails (`helpers.flight`;
    test/e2e/test_flight_install.py flies the node and the CLI without torch and onnx)."""
    env = blocked_env(blocker_site(tmp_path, block))
    return subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("mode", sorted(DEFAULT_MODELS))
def test_onnx_proposals_match_torch_on_heldout_scenarios(mode):
    """The learned step (sweep, C update, judging, post hoc check) on both runtimes, on
    held-out scenarios of the shipped model's dataset."""
    path = default_model_path(mode)
    torch_p = ArtWarmStart.load(path, runtime="torch")
    onnx_p = ArtWarmStart.load(path, runtime="onnx")
    assert onnx_p.sha256 == torch_p.sha256 and onnx_p.runtime == "onnx"
    assert onnx_p.runtime_sha256 == pinned_sha256(path.with_suffix(".onnx"))
    requests = heldout_requests(N_SCENARIOS, DEFAULT_MODELS[mode])
    assert runtimes_agree(torch_p, onnx_p, requests, DV_TOL_MPS) >= N_SCENARIOS - 2


def test_the_shipped_exports_are_pinned_and_name_their_checkpoints():
    from art_guidance.art.provider import shipped_models

    for mode in DEFAULT_MODELS:
        pt = default_model_path(mode)
        art = load_exported(pt.with_suffix(".onnx"), pinned_sha256(pt),
                            pinned_sha256(pt.with_suffix(".onnx")))
        assert art.sha256 == pinned_sha256(pt) and art.checkpoint_file == pt.name
        entry = shipped_models()[pt.name]
        assert art.config.width == entry["model_config"]["width"]
        assert art.n_parameters == entry["n_parameters"]


def test_auto_takes_onnx_where_the_export_is_there_and_torch_elsewhere(tmp_path):
    assert resolve_runtime("auto", default_model_path("chance")) == "onnx"
    assert resolve_runtime("auto", tmp_path / "trained.pt") == "torch"  # no export beside it
    assert resolve_runtime("auto", tmp_path / "trained.onnx") == "onnx"
    with pytest.raises(InputError, match="art_runtime"):
        resolve_runtime("tensorrt", default_model_path("chance"))
    with pytest.raises(InputError, match="exported model"):
        resolve_runtime("torch", tmp_path / "trained.onnx")


def _refused(path: Path, match: str, **kw) -> None:
    with pytest.raises(CheckpointError, match=match):
        ArtWarmStart.load(path, runtime="onnx", **kw)


def test_bad_exported_files_are_refused_with_the_reason(tmp_path, chance_onnx):
    import onnx

    blob = chance_onnx.read_bytes()
    cases = {"truncated.onnx": blob[:len(blob) // 2]}
    flipped = bytearray(blob)  # a byte of a weight (the middle of the file is weights)
    flipped[len(blob) // 2] ^= 0xFF
    cases["flipped.onnx"] = bytes(flipped)
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    _refused(tmp_path / "truncated.onnx", "corrupt, truncated")
    _refused(tmp_path / "flipped.onnx", "weights are not those recorded|corrupt, truncated")
    _refused(tmp_path / "missing.onnx", "cannot read")
    model = onnx.load_model_from_string(blob)
    meta = json.loads(model.metadata_props[0].value)

    def variant(name: str, **changes) -> Path:
        m = onnx.ModelProto()
        m.CopyFrom(model)
        m.metadata_props[0].value = json.dumps({**meta, **changes})
        (tmp_path / name).write_bytes(m.SerializeToString())
        return tmp_path / name
    _refused(variant("other.onnx", checkpoint_sha256="0" * 64), "exported from checkpoint",
             expected_sha256=meta["checkpoint_sha256"])
    probe = dict(meta["probe"], control=(np.array(meta["probe"]["control"]) + 0.01).tolist())
    _refused(variant("probe.onnx", probe=probe), "does not reproduce the export's probe")
    _refused(variant("format.onnx", format="something-else"), "not format")
    m = onnx.ModelProto()
    m.CopyFrom(model)
    del m.metadata_props[:]
    (tmp_path / "plain.onnx").write_bytes(m.SerializeToString())
    _refused(tmp_path / "plain.onnx", "not an exported art_guidance model")
    assert METADATA_KEY == model.metadata_props[0].key
    # beside a checkpoint, the export of another checkpoint is refused
    (tmp_path / "art.pt").write_bytes(default_model_path("deterministic").read_bytes())
    (tmp_path / "art.onnx").write_bytes(blob)
    _refused(tmp_path / "art.pt", "exported from checkpoint")


def test_auto_flies_the_checkpoint_on_torch_beside_a_damaged_export(tmp_path, chance_onnx):
    """`art_runtime: auto` with a damaged export beside an intact checkpoint keeps the learned
    warm start: the checkpoint on torch, the refusal said in the log and the model status;
    asked for "onnx" explicitly, the refusal stands."""
    from art_guidance.ros.node_status import load_model

    checkpoint = default_model_path("chance")
    (tmp_path / checkpoint.name).write_bytes(checkpoint.read_bytes())
    damaged = bytearray(chance_onnx.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    (tmp_path / chance_onnx.name).write_bytes(bytes(damaged))
    warnings: list[str] = []
    log = SimpleNamespace(warning=warnings.append, info=lambda text: None)
    params = SimpleNamespace(model_path=str(tmp_path / checkpoint.name), art_runtime="auto",
                             chance_constrained=True)
    provider, status = load_model(params, log)
    assert provider is not None and provider.runtime == "torch", status
    assert provider.sha256 == ArtWarmStart.load(checkpoint, runtime="torch").sha256
    assert "exported model was refused" in status and "on torch" in status, status
    assert len(warnings) == 1 and "flying the checkpoint on torch" in warnings[0]
    _refused(tmp_path / checkpoint.name, "weights are not those recorded|corrupt, truncated")


TEACHER = "art_small_chance_rtn"  # a small shipped pair (checkpoint and exported file)


def _pair(tmp_path: Path, damaged: str) -> dict[str, Path]:
    """The shipped TEACHER pair copied into `tmp_path`, the `damaged` one (".pt" or ".onnx")
    cut to half its length (not shipped there: nothing pins the copies)."""
    files = {}
    for suffix in (".pt", ".onnx"):
        blob = (models_dir() / (TEACHER + suffix)).read_bytes()
        files[suffix] = tmp_path / (TEACHER + suffix)
        files[suffix].write_bytes(blob[:len(blob) // 2] if suffix == damaged else blob)
    return files


@pytest.mark.parametrize("given", [".onnx", ".pt"], ids=["onnx_given", "pt_given"])
@pytest.mark.parametrize("damaged, flies, why", [
    (".onnx", "torch", "not an exported art_guidance model (corrupt, truncated"),
    (".pt", "onnx", "truncated or padded"),
], ids=["onnx_damaged", "pt_damaged"])
def test_auto_flies_the_intact_file_of_a_damaged_pair(tmp_path, given, damaged, flies, why):
    """`art_runtime: auto` treats a checkpoint and its exported file as a pair, whichever of
    them model_path names: a truncated exported file gives way to the checkpoint on torch, a
    truncated checkpoint beside an intact exported file leaves that flying on onnx; either way
    the note names the damaged file and why, and the model is the shipped one."""
    files = _pair(tmp_path, damaged)
    provider = ArtWarmStart.load(files[given], runtime="auto")
    intact = ".pt" if damaged == ".onnx" else ".onnx"
    assert provider.runtime == flies and provider.path == str(files[intact]), provider.note
    assert provider.sha256 == pinned_sha256(models_dir() / (TEACHER + ".pt"))
    assert f"{files[damaged]}: {why}" in provider.note, provider.note
    assert f"on {flies}" in provider.note and str(files[intact]) in provider.note
    if damaged == ".pt" and given == ".pt":  # checked against the header it still has
        assert "not checked" not in provider.note


def test_auto_names_both_files_of_a_pair_neither_of_which_loads(tmp_path):
    """Both files damaged: refused (CVX only in the node) with both named, whichever is
    given; asked for one runtime, the file of the other is not looked at."""
    for given in (".pt", ".onnx"):
        files = _pair(tmp_path, ".pt")
        files[".onnx"].write_bytes(files[".onnx"].read_bytes()[:1000])
        with pytest.raises(CheckpointError) as refused:
            ArtWarmStart.load(files[given], runtime="auto")
        text = str(refused.value)
        assert f"{files['.onnx']}: not an exported" in text, text
        assert f"{files['.pt']}: truncated or padded" in text, text
    files = _pair(tmp_path, ".pt")
    assert ArtWarmStart.load(files[".onnx"], runtime="onnx").note == ""


def test_a_shipped_exported_file_given_as_model_path_loads():
    """A shipped .onnx named itself is checked against its checkpoint's pinned checksum (and
    its own), not refused as another checkpoint's."""
    onnx = models_dir() / (TEACHER + ".onnx")
    for runtime in ("auto", "onnx"):
        provider = ArtWarmStart.load(onnx, runtime=runtime)
        assert provider.runtime == "onnx" and provider.note == ""
        assert provider.sha256 == pinned_sha256(onnx.with_suffix(".pt"))
        assert provider.runtime_sha256 == pinned_sha256(onnx)


def test_the_node_and_plan_fly_cvx_when_the_runtime_cannot_be_used(tmp_path, capsys):
    from art_guidance.ros.node_status import load_model

    warnings: list[str] = []
    log = SimpleNamespace(warning=warnings.append, info=lambda text: None)
    for runtime, path, why in (("tensorrt", "", "art_runtime"),
                               ("onnx", str(tmp_path / "none.pt"), "cannot read")):
        params = SimpleNamespace(model_path=path, art_runtime=runtime, chance_constrained=True)
        provider, status = load_model(params, log)
        assert provider is None and status.startswith("cvx-only") and why in status
    assert len(warnings) == 2
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    code = cli_main(["plan", "--seed", "3", "--model", str(bad), "--json",
                     str(tmp_path / "plan.json")])
    assert code in (0, 1) and "planning from CVX only" in capsys.readouterr().err
    data = json.loads((tmp_path / "plan.json").read_text())
    assert data["warm_start"] == "cvx" and data["art_runtime"] is None
    assert cli_main(["plan", "--seed", "3", "--warm-start", "art", "--model", str(bad),
                     "--json", str(tmp_path / "p2.json")]) == 2


def test_plan_flies_the_learned_warm_start_where_torch_cannot_be_imported(tmp_path):
    out = tmp_path / "plan.json"
    code = ("import sys\n"
            "try:\n    import torch\nexcept ImportError:\n    pass\n"
            "else:\n    sys.exit('torch imported')\n"
            "from art_guidance.cli import main\n"
            "code = main(['plan', '--seed', '3', '--warm-start', 'art', '--json', "
            f"{str(out)!r}])\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n"
            "sys.exit(code)\n")
    run = _python(code, "torch", tmp_path)
    assert run.returncode in (0, 1), run.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["art_runtime"] == "onnx" and data["warm_start"] == "art"
    assert data["art_cost_mps"] is not None and data["model_sha256"] == pinned_sha256(
        default_model_path("chance"))


def test_a_missing_onnxruntime_is_named_and_auto_keeps_torch(tmp_path):
    """Without ONNX Runtime, "auto" flies the checkpoint on torch, also where the .onnx itself
    is given as the model (the checkpoint beside it, the reason in the note), as a damaged
    .onnx does; "onnx" names the missing package."""
    code = ("from art_guidance.art.provider import ArtWarmStart, default_model_path\n"
            "from art_guidance.errors import ModelError\n"
            "assert ArtWarmStart.load(default_model_path(), runtime='auto').runtime == 'torch'\n"
            "p = ArtWarmStart.load(default_model_path().with_suffix('.onnx'), runtime='auto')\n"
            "assert p.runtime == 'torch', p.runtime\n"
            "print('NOTE', p.note)\n"
            "try:\n    ArtWarmStart.load(default_model_path(), runtime='onnx')\n"
            "except ModelError as exc:\n    print(exc)\n")
    run = _python(code, "onnxruntime", tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "onnxruntime" in run.stdout and "not installed" in run.stdout
    assert ("NOTE art_slim1e40_chance_rtn.onnx refused: it runs on ONNX Runtime, which is not "
            "installed; the checkpoint beside it, art_slim1e40_chance_rtn.pt, flies on torch"
            in run.stdout), run.stdout


def test_export_writes_whole_files_and_never_overwrites_without_force(tmp_path, capsys):
    pt = tmp_path / "model.pt"
    pt.write_bytes(default_model_path("chance").read_bytes())
    assert cli_main(["export", str(pt)]) == 0
    onnx_file = pt.with_suffix(".onnx")
    first = onnx_file.read_bytes()
    report = json.loads(capsys.readouterr().out)
    assert report["out"] == str(onnx_file) and report["checkpoint_sha256"] == pinned_sha256(
        default_model_path("chance"))
    onnx_file.write_bytes(b"keep me")
    assert cli_main(["export", str(pt)]) == 2  # exists, no --force
    assert onnx_file.read_bytes() == b"keep me"
    assert cli_main(["export", str(pt), "--force"]) == 0
    assert onnx_file.read_bytes() == first  # the same model gives the same file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx", "model.pt"]
    assert ArtWarmStart.load(pt, runtime="auto").runtime == "onnx"
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"no checkpoint")
    assert cli_main(["export", str(bad)]) == 2 and not bad.with_suffix(".onnx").exists()


def test_a_reused_decoder_reads_nothing_earlier_rollouts_left():
    """The ONNX decoder keeps its caches across rollouts (as torch's does): a replan over the
    last nodes, rolled out after a full-horizon rollout, equals the same replan on a fresh
    decoder bit for bit, and torch's within DV_TOL_MPS."""
    from art_guidance.art.rollout import build_safety, rollout

    path = default_model_path("chance")
    used, torch_p = (ArtWarmStart.load(path, runtime=rt) for rt in ("onnx", "torch"))
    safety = build_safety(used.art)
    request = heldout_requests(1, DEFAULT_MODELS["chance"])[0]
    x0, target = np.tile(request.roe0_m, (8, 1)), request.target_rtn
    rollout(used.art, safety, x0, target, -8.0, 0.0)  # fills the caches, 100 steps
    tail = rollout(used.art, safety, x0, target, -3.0, 0.0, start_node=60)
    fresh = ArtWarmStart.load(path, runtime="onnx")  # a decoder of its own
    again = rollout(fresh.art, safety, x0, target, -3.0, 0.0, start_node=60)
    oracle = rollout(torch_p.art, safety, x0, target, -3.0, 0.0, start_node=60)
    assert np.array_equal(tail.dv_rtn_mps, again.dv_rtn_mps)
    assert np.abs(tail.dv_rtn_mps - oracle.dv_rtn_mps).max() <= DV_TOL_MPS
