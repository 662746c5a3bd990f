"""ART training in one process: data split and normalisation, overfitting, provenance, CLI.

The dataset is a real one (16 deterministic samples through the 3-stage pipeline, generated
once per module, a few seconds).
"""
from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from art_guidance.art import build_safety, checkpoint
from art_guidance.art.config import DAGGER_REWARDS, MODALITIES, PRESETS, preset
from art_guidance.art.data import (
    load_training_data, make_batch, manifest_digest, trained_manifests,
)
from art_guidance.art.model import ArtModel, loss_counts, loss_terms
from art_guidance.art.train import TrainOptions, _check_init_data, state_path, train
from art_guidance.cli import train as cli_train
from art_guidance.data.generate import generate
from art_guidance.data.storage import MANIFEST, load_dataset
from art_guidance.eval.inputs import dataset_info, model_info
from art_guidance.errors import ConfigError, GuidanceError, InputError

torch.set_num_threads(1)
OVERFIT = {"lr": 1e-2, "min_lr_ratio": 1.0, "batch_size": 16, "suffix_fraction": 0.0,
           "max_epochs": 300, "eval_every": 100, "patience": 100, "val_fraction": 0.1}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("art") / "det16"
    generate(out, 16, "deterministic", base_seed=5, workers=2, shard_size=4, progress=False,
             log=lambda _: None)
    return out


def _train_loss(model, data) -> float:
    """Paper loss (normalised MSE) of `model` on the full training sequences."""
    rows = data.train_rows
    batch = make_batch(data.tensors, rows, np.zeros(rows.size, dtype=np.int64), 100)
    n_u, n_x = loss_counts(batch["mask"])
    model.eval()
    with torch.no_grad():
        sse_u, sse_x, _ = loss_terms(model, batch)
    return float(sse_u / n_u + sse_x / n_x)


def test_training_uses_the_train_split_only_and_its_statistics(dataset):
    raw = load_dataset(dataset)
    data = load_training_data([str(dataset)], "rtn", 0.1, seed=3)
    kept = ~raw["is_test"] & raw["feasible"]
    assert data.train_rows.size + data.val_rows.size == kept.sum() < raw["index"].size
    assert not set(data.train_rows) & set(data.val_rows)
    train_rtn = raw["rtn"][kept][data.train_rows]  # (M, N, 6) RTN states of the train rows
    assert np.allclose(data.normalizer.mean["state"], train_rtn.reshape(-1, 6).mean(0))
    assert np.allclose(data.normalizer.std["state"], train_rtn.reshape(-1, 6).std(0))
    assert np.allclose(data.normalizer.mean["goal"], raw["target_rtn"][kept][
        data.train_rows].mean(0))
    # the dataset's R and C are the paper's: R(t_i) = -sum_{j>=i} ||dv_j||, C(t_i) = sum v_j
    dv = raw["dv_rtn_mps"][kept]
    rtg = -np.cumsum(np.linalg.norm(dv, axis=2)[:, ::-1], axis=1)[:, ::-1]
    assert np.allclose(raw["reward_to_go_mps"][kept], rtg, rtol=1e-12, atol=1e-15)
    steps = -np.diff(raw["constraint_to_go"][kept], axis=1, append=0)  # v_j in {0, 1}
    assert np.isin(steps, (0, 1)).all()
    z = data.tensors["state"][torch.as_tensor(data.train_rows)]  # (M, N, 6) z-scores
    assert torch.allclose(z.reshape(-1, 6).mean(0), torch.zeros(6), atol=1e-5)


@pytest.mark.slow
def test_training_overfits_a_tiny_dataset(dataset, tmp_path):
    out = tmp_path / "overfit.pt"
    data = load_training_data([str(dataset)], "roe", OVERFIT["val_fraction"], seed=0)
    torch.manual_seed(0)
    initial = _train_loss(ArtModel(preset("tiny")[0]), data)  # the run starts from these weights
    summary = train(TrainOptions(data=(str(dataset),), out=str(out), preset="tiny",
                                 overrides=OVERFIT, progress=False), log=lambda _: None)
    assert summary["stop_reason"] == "max epochs"
    art = checkpoint.load(out)  # best validation weights; the last ones are in the state file
    last, _ = checkpoint.build(state_path(out), checkpoint.read_payload(state_path(out))[0])
    final = _train_loss(last, data)
    assert initial > 1.0 and final < 0.02, (initial, final)  # "near zero": < 2 % of the start
    assert art.meta["training"]["best_val_loss"] == summary["best_val_loss"]


def test_checkpoint_records_provenance_and_reruns_are_safe(dataset, tmp_path):
    out = tmp_path / "m.pt"
    opts = TrainOptions(data=(str(dataset),), out=str(out), preset="tiny", seed=1,
                        overrides={"max_epochs": 2}, progress=False, command="art-guidance x")
    first = train(opts, log=lambda _: None)
    assert first["stop_reason"] == "max epochs"
    art = checkpoint.load(out)
    manifest = (dataset / "manifest.jsonl").read_bytes()
    data_meta = art.meta["dataset"]
    assert data_meta["manifests"][0]["manifest_sha256"] == hashlib.sha256(manifest).hexdigest()
    assert data_meta["mode"] == "deterministic" and data_meta["n_nodes"] == 100
    assert art.meta["training"]["command"] == "art-guidance x"
    assert build_safety(art).uncertainty is None and build_safety(art).n_nodes == 100
    assert set(art.normalizer.mean) == set(MODALITIES)
    again = train(opts, log=lambda _: None)  # finished: nothing to do, nothing rewritten
    assert again["step"] == first["step"] and checkpoint.load(out).sha256 == art.sha256
    with pytest.raises(InputError, match="different training run"):
        train(TrainOptions(**{**opts.__dict__, "seed": 2}), log=lambda _: None)
    with open(str(out) + ".lock", "w") as held:  # another run is training into this --out
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(InputError, match="another training run"):
            train(opts, log=lambda _: None)
    state_path(out).unlink()
    with pytest.raises(InputError, match="no training state"):
        train(opts, log=lambda _: None)
    with pytest.raises(ConfigError):
        train(TrainOptions(**{**opts.__dict__, "out": str(tmp_path / "n.pt"),
                              "overrides": {"lr": -1.0}}), log=lambda _: None)
    # the held-out evaluation reads the test split only, and reports against CVX's labels
    from art_guidance.cli import main as cli_main

    assert cli_main(["evaluate", "--suite", "rollouts", "--data", str(dataset), "--model",
                     str(out), "--threads", "1", "--out", str(tmp_path / "eval"),
                     "--no-progress"]) == 0
    report = json.loads((tmp_path / "eval" / "rollouts.json").read_text())["models"][0]
    raw = load_dataset(dataset)
    held = raw["is_test"] & (raw["cvx_constraint_to_go0"] >= 0)
    assert report["n_scenarios"] == held.sum() >= 1 and report["model_sha256"] == art.sha256
    assert report["c_cvx_label_agreement"] == 1.0  # labels of this code = re-evaluation
    assert report["c_cvx_t1"]["max"] <= 100
    assert sum(report["c_art_histogram"]) == held.sum()
    assert 0.0 <= report["frac_posthoc_accepted"] <= 1.0


def test_fine_tuning_starts_from_the_initial_model(dataset, tmp_path, capsys):
    base = tmp_path / "base.pt"
    opts = TrainOptions(data=(str(dataset),), out=str(base), preset="tiny", seed=1,
                        overrides={"max_epochs": 2}, progress=False)
    train(opts, log=lambda _: None)
    init = checkpoint.load(base)
    logs: list[str] = []
    tuned = tmp_path / "tuned.pt"
    ft = TrainOptions(**{**opts.__dict__, "out": str(tuned), "init": str(base), "seed": 4,
                         "overrides": {"max_epochs": 1, "lr": 1e-9, "warmup_steps": 1}})
    summary = train(ft, log=logs.append)
    art = checkpoint.load(tuned)
    # the initial weights and normalisation are kept (a step at lr 1e-9 barely moves them)
    for name, w in init.model.state_dict().items():
        assert torch.allclose(art.model.state_dict()[name], w, atol=1e-6), name
    for m in MODALITIES:
        assert np.array_equal(art.normalizer.mean[m], init.normalizer.mean[m])
        assert np.array_equal(art.normalizer.std[m], init.normalizer.std[m])
    history = art.meta["training"]["history"]
    assert history[0][0] == 0 and np.isnan(history[0][1]) and "initial model" in logs[0]
    assert summary["best_val_loss"] <= history[0][2]
    assert art.meta["training"]["init"]["sha256"] == init.sha256
    assert art.meta["training"]["init"]["file"] == "base.pt"
    assert art.meta["training"]["init"]["trained_on"] == list(trained_manifests(init.meta))
    # a fine-tuning whose flags do not describe the initial model, or of another file: refused
    with pytest.raises(InputError, match="representation: model 'roe', options 'rtn'"):
        train(TrainOptions(**{**ft.__dict__, "out": str(tmp_path / "a.pt"),
                              "representation": "rtn"}), log=lambda _: None)
    with pytest.raises(InputError, match="burn_gate"):
        train(TrainOptions(**{**ft.__dict__, "out": str(tmp_path / "b.pt"),
                              "model_overrides": {"burn_gate": True}}), log=lambda _: None)
    # on other data of the same mode: both count as trained on (`--split all` refuses both)
    other = tmp_path / "det8"
    generate(other, 8, "deterministic", base_seed=6, workers=1, shard_size=8, progress=False,
             log=lambda _: None)
    train(TrainOptions(**{**ft.__dict__, "out": str(tmp_path / "o.pt"), "data": (str(other),)}),
          log=lambda _: None)
    lineage = trained_manifests(checkpoint.load(tmp_path / "o.pt").meta)
    assert lineage == (manifest_digest(other), *trained_manifests(init.meta))
    # held out means other scenario seeds, not only another manifest: a dataset generated with
    # a seed the model was trained on is refused by `--split all`, whatever its size
    same_seed = tmp_path / "det5b"
    generate(same_seed, 4, "deterministic", base_seed=5, workers=1, shard_size=4,
             progress=False, log=lambda _: None)
    base_info, o_info = model_info(base), model_info(tmp_path / "o.pt")
    assert base_info.trained_seed_bases == (5,) and o_info.trained_seed_bases == (5, 6)
    assert base_info.saw(dataset_info(same_seed)) and not base_info.saw(dataset_info(other))
    assert o_info.saw(dataset_info(dataset)) and o_info.saw(dataset_info(other))
    from art_guidance.cli import main as cli_main

    for suite in ("rollouts", "warmstart"):
        assert cli_main(["evaluate", "--suite", suite, "--data", str(same_seed), "--model",
                         str(base), "--split", "all", "--workers", "1", "--no-progress",
                         "--out", str(tmp_path / f"ev_{suite}")]) == 2
        assert "scenarios of its seed" in capsys.readouterr().err
    # data of the same problem is accepted whatever the flight-only planning choices; another
    # problem or mode is refused, naming the difference
    prov = dict(init.meta["dataset"], config_sha256="other")
    bundle = prov["guidance_config"]
    flight = dict(bundle, planning=dict(bundle["planning"], posthoc_subject="rollout"))
    _check_init_data("base.pt", init, dict(prov, guidance_config=flight))
    safety = dict(bundle, scenario=dict(bundle["scenario"], n_safety=7))
    with pytest.raises(InputError, match=r"differ in configuration \(scenario"):
        _check_init_data("base.pt", init, dict(prov, guidance_config=safety))
    with pytest.raises(InputError, match="trained on deterministic data, --data is chance"):
        _check_init_data("base.pt", init, dict(prov, mode="chance"))
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(InputError, match="--init"):
        train(TrainOptions(**{**ft.__dict__, "out": str(tmp_path / "c.pt"),
                              "init": str(tmp_path / "junk.pt")}), log=lambda _: None)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="art-guidance")
    cli_train.add_parser(parser.add_subparsers(dest="command"))
    return parser


def test_cli_parser_and_bad_input(dataset, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        _parser().parse_args(["train", "--help"])
    assert info.value.code == 0 and "--max-minutes" in capsys.readouterr().out
    args = _parser().parse_args(["train", "--data", str(dataset), "--out", str(tmp_path / "x"),
                                 "--repr", "rtn", "--preset", "tiny", "--max-steps", "0"])
    assert args.representation == "rtn" and args.func is cli_train.run
    with pytest.raises(InputError, match="--max-steps"):
        args.func(args)
    args = _parser().parse_args(["train", "--data", str(tmp_path / "none"), "--out",
                                 str(tmp_path / "x")])
    with pytest.raises(GuidanceError) as info:  # DatasetError; the CLI handler exits 2
        args.func(args)
    assert "not a dataset directory" in str(info.value)


def test_building_the_parser_does_not_import_torch(python_exe):
    code = ("import argparse, sys\nfrom art_guidance.cli import train\n"
            "train.add_parser(argparse.ArgumentParser().add_subparsers())\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([python_exe, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _with_header(src: Path, out: Path, change) -> Path:
    """A copy of dataset `src` whose manifest header is changed by `change(header)`."""
    shutil.copytree(src, out)
    lines = (out / MANIFEST).read_text().splitlines(keepends=True)
    header = json.loads(lines[0])
    change(header)
    lines[0] = json.dumps(header) + "\n"
    (out / MANIFEST).write_text("".join(lines))
    return out


def test_directories_of_one_kind_mix_whatever_their_flight_only_options(dataset, tmp_path):
    """Two directories train together when they describe the same data: a header written
    before a flight-only planning option existed (another fingerprint) mixes with a new one;
    another scenario or pipeline version does not, and the error names the difference."""
    def older(h):
        planning = h["config"]["guidance_config"]["planning"]
        for key in ("propose_concurrently", "skip_art_when_cvx_safe", "also_solve_from_art"):
            planning.pop(key, None)
        h["config_sha256"] = "0" * 64

    old = _with_header(dataset, tmp_path / "old", older)
    both = load_training_data([str(dataset), str(old)], "roe", 0.1, seed=0)
    one = load_training_data([str(dataset)], "roe", 0.1, seed=0)
    n_one = one.train_rows.size + one.val_rows.size
    assert both.train_rows.size + both.val_rows.size == 2 * n_one

    def koz(h):
        h["config"]["guidance_config"]["scenario"]["koz_semi_axes_m"] = [150.0] * 3
        h["config_sha256"] = "1" * 64

    def pipeline(h):
        h["config"]["pipeline_version"] = -1
        h["config_sha256"] = "2" * 64

    for change, name in ((koz, "scenario"), (pipeline, "pipeline_version")):
        other = _with_header(dataset, tmp_path / name, change)
        with pytest.raises(InputError, match=f"differing: {name}"):
            load_training_data([str(dataset), str(other)], "roe", 0.1, seed=0)


def test_the_cli_import_free_choices_are_the_configs():
    """`art-guidance train --help` imports no torch, so its choices are copies: kept equal."""
    assert set(cli_train._PRESETS) == set(PRESETS)
    assert cli_train._DAGGER_REWARDS == DAGGER_REWARDS
