"""DAgger data aggregation: stitched rows, determinism and resume, the training mask, the CLI.

A real chance-constrained source dataset (12 samples through the 3-stage pipeline) and a tiny
model trained a few steps are made once per module (a few seconds); the DAgger rows of that
model are what is checked, not its skill.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from art_guidance.art import build_safety, checkpoint
from art_guidance.art.config import TrainConfig
from art_guidance.config import GuidanceConfig
from art_guidance.data.dagger import (
    DAGGER_STREAM, FIELDS, _check_model, dagger, dagger_node, expert_from, scenario_pool,
)
from art_guidance.art.data import load_training_data, make_batch, manifest_digest, valid_mask
from art_guidance.art.model import loss_counts, loss_terms
from art_guidance.art.rollout import replay, rollout
from art_guidance.art.train import TrainOptions, train
from art_guidance.cli import main
from art_guidance.data.generate import generate
from art_guidance.data.stages import GenerationSpec
from art_guidance.data.stages import FIELDS as GENERATE_FIELDS
from art_guidance.data.storage import MANIFEST, load_dataset, read_manifest
from art_guidance.errors import ConfigError, GuidanceError, InputError
from art_guidance.optim import FEASIBLE_STATUSES

torch.set_num_threads(1)
N_SRC, N_DAG, SEED, BATCH = 12, 8, 3, 4
TIMING = ("stage_time_ms",)


def _quiet(_: str) -> None:
    pass


def _run(out: Path, model: Path, src: Path, **kw) -> dict:
    kw = {"seed": SEED, "workers": 1, "shard_size": 4, "batch": BATCH, "progress": False,
          "log": _quiet, **kw}
    return dagger(out, model, src, kw.pop("n", N_DAG), **kw)


def _assert_same(a: dict, b: dict) -> None:
    """Every stored field bit-identical (NaN == NaN), timings excepted."""
    for key in FIELDS:
        if key not in TIMING:
            assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), key


@pytest.fixture(scope="module")
def src(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dagger") / "src"
    generate(out, N_SRC, "chance", base_seed=11, workers=1, shard_size=6, progress=False,
             log=_quiet)
    return out


@pytest.fixture(scope="module")
def model(src) -> Path:
    out = src.parent / "model.pt"
    train(TrainOptions(data=(str(src),), out=str(out), preset="tiny", max_steps=5,
                       progress=False), log=_quiet)
    return out


@pytest.fixture(scope="module")
def dag_dir(src, model) -> Path:
    out = src.parent / "dagger"
    assert _run(out, model, src)["status"] == "complete"
    return out


@pytest.fixture(scope="module")
def dag(dag_dir) -> dict:
    return load_dataset(dag_dir)


def test_rows_stitch_the_rollout_and_the_experts_resolve(src, model, dag, dag_dir):
    raw = load_dataset(src)
    art = checkpoint.load(model)
    safety = build_safety(art)
    horizon, n = safety.horizon, safety.n_nodes
    spec = GenerationSpec.build("chance", 0)
    # the scenarios: SRC's feasible train-split samples with a CVX solution, cycled
    pool = np.flatnonzero(raw["feasible"] & ~raw["is_test"] & (raw["cvx_constraint_to_go0"] >= 0))
    src_index = pool[np.arange(N_DAG) % pool.size]
    assert np.array_equal(dag["index"], np.arange(N_DAG))
    assert np.array_equal(dag["src_index"], src_index)
    for key in ("seed", "waypoint", "rtn0", "target_rtn", "roe0_m", "roe_f_m", "cvx_roe_m",
                "cvx_dv_rtn_mps", "cvx_cost_mps", "cvx_constraint_to_go0"):
        assert np.array_equal(dag[key], raw[key][src_index]), key
    assert not dag["is_test"].any() and dag["feasible"].all()
    k_all = dag["train_from"]
    assert np.array_equal(k_all, [dagger_node(SEED, i, n) for i in range(N_DAG)])
    assert ((1 <= k_all) & (k_all <= n - 3)).all() and np.unique(k_all).size > 1
    # the rollouts, batched as the groups of BATCH samples they were made in
    groups = [np.arange(g, min(g + BATCH, N_DAG)) for g in range(0, N_DAG, BATCH)]
    rolled = [rollout(art, safety, raw["roe0_m"][src_index[m]], raw["target_rtn"][src_index[m]],
                      -raw["cvx_cost_mps"][src_index[m]], 0.0) for m in groups]
    for i in range(N_DAG):
        res, j = rolled[i // BATCH], i % BATCH
        k, roe, dv = int(k_all[i]), dag["roe_m"][i], dag["dv_rtn_mps"][i]
        assert np.array_equal(roe[:k + 1], res.roe_m[j, :k + 1])  # prefix and x_k: the rollout
        assert np.array_equal(dv[:k], res.dv_rtn_mps[j, :k])
        stages, kept = expert_from(spec, horizon, k, res.roe_m[j, k], dag["roe_f_m"][i])
        assert kept == dag["kept_stage"][i] > 0
        expert = stages[kept - 1]
        assert expert.status in FEASIBLE_STATUSES
        assert np.array_equal(roe[k:], expert.roe_m) and np.array_equal(dv[k:], expert.dv_rtn_mps)
        assert np.array_equal(dag["stage_cost_mps"][i], [s.cost_mps for s in stages])
        # the stitched row is one trajectory of the planner's model that reaches the target
        assert np.allclose(horizon.propagate_nonlinear(dag["roe0_m"][i], dv), roe,
                           rtol=0, atol=1e-6)
        assert np.allclose(horizon.final_post_burn_nonlinear(roe, dv), dag["roe_f_m"][i],
                           atol=1e-3)
        assert np.array_equal(dag["rtn"][i], horizon.to_rtn(roe))
        # R and C in hindsight, over the whole row
        norms = np.linalg.norm(dv, axis=1)
        assert np.allclose(dag["reward_to_go_mps"][i], -np.cumsum(norms[::-1])[::-1],
                           rtol=1e-12, atol=1e-15)
        assert dag["cost_mps"][i] == pytest.approx(norms.sum(), rel=1e-12)
        ev = safety.evaluate(roe, dv)
        assert np.array_equal(dag["constraint_to_go"][i], ev.constraint_to_go)
        assert np.array_equal(dag["margin_m"][i], ev.margin_m)
    header = read_manifest(dag_dir)[0]
    assert header["mode"] == "chance" and header["fields"] == FIELDS
    assert set(GENERATE_FIELDS) | {"train_from", "src_index"} == set(FIELDS)
    assert header["config_sha256"] == read_manifest(src)[0]["config_sha256"]
    info = header["dagger"]
    assert info["model_sha256"] == art.sha256 and info["seed"] == SEED
    assert info["src_manifest_sha256"] == manifest_digest(str(src))
    assert info["rollout_batch"] == BATCH and info["pool_size"] == pool.size
    assert hex(DAGGER_STREAM) in header["seed_rule"]


def test_scenario_pool_never_reads_the_test_split(src):
    raw = load_dataset(src)
    pool = scenario_pool(src, 100)
    assert not raw["is_test"][pool["src_index"]].any()
    assert pool["src_index"].size == int(pool["pool_size"]) == \
        (raw["feasible"] & ~raw["is_test"] & (raw["cvx_constraint_to_go0"] >= 0)).sum()
    assert np.array_equal(scenario_pool(src, 3)["src_index"], pool["src_index"][:3])


def test_reruns_chunkings_and_resume_give_identical_data(src, model, dag, dag_dir, tmp_path):
    again = _run(tmp_path / "again", model, src, workers=2, shard_size=3)
    assert again["status"] == "complete" and again["this_run"]["samples"] == N_DAG
    _assert_same(load_dataset(tmp_path / "again"), dag)
    # an interrupted run: one committed shard, a torn manifest line and a temp file left
    cut = tmp_path / "cut"
    shutil.copytree(dag_dir, cut)
    lines = (cut / MANIFEST).read_bytes().splitlines(keepends=True)
    (cut / MANIFEST).write_bytes(b"".join(lines[:2]) + lines[2][:25])
    (cut / "shard-000007.npz.99.tmp").write_bytes(b"half")
    log: list[str] = []
    resumed = _run(cut, model, src, log=log.append)
    assert resumed["status"] == "complete" and resumed["this_run"]["samples"] == N_DAG - 4
    assert any(line.startswith(f"resuming {cut}: 4 of {N_DAG}") for line in log)
    _assert_same(load_dataset(cut), dag)
    manifest = (cut / MANIFEST).read_bytes()
    assert _run(cut, model, src)["status"] == "already_complete"
    assert (cut / MANIFEST).read_bytes() == manifest


@pytest.mark.slow
def test_ray_engine_gives_the_same_data(src, model, dag, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install .[distributed])")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        summary = _run(tmp_path / "ray", model, src, engine="ray", workers=2)
    finally:
        ray.shutdown()
    assert summary["status"] == "complete" and summary["this_run"]["engine"] == "ray"
    _assert_same(load_dataset(tmp_path / "ray"), dag)


def _variant(model: Path, out: Path, **meta_changes) -> Path:
    """A copy of `model` with changed provenance (another payload sha256)."""
    payload, _ = checkpoint.read_payload(model)
    payload["meta"]["dataset"].update(meta_changes)
    payload["meta"]["training"]["command"] = "variant"
    checkpoint.save(out, payload)
    return out


def test_bad_inputs_and_foreign_directories(src, model, dag_dir, tmp_path):
    for kw, field in (({"n": 0}, "--n"), ({"batch": 0}, "--batch"), ({"workers": 0}, "--workers"),
                      ({"shard_size": 0}, "--shard-size"), ({"seed": -1}, "--seed"),
                      ({"engine": "spark"}, "--engine")):
        with pytest.raises(InputError) as exc:
            _run(tmp_path / "x", model, src, **kw)
        assert exc.value.field == field
    with pytest.raises(InputError) as exc:
        _run(src, model, src)
    assert exc.value.field == "--out"
    det = _variant(model, tmp_path / "det.pt", mode="deterministic")
    with pytest.raises(InputError, match="trained on deterministic data") as exc:
        _run(tmp_path / "x", det, src)
    assert exc.value.field == "--model"
    # a model whose bundle predates a flight-only planning option describes the same data
    # (the rule of `train --init`); another scenario does not, and the difference is named
    bundle = checkpoint.load(model).meta["dataset"]["guidance_config"]
    planning = {k: v for k, v in bundle["planning"].items()
                if k not in ("propose_concurrently", "skip_art_when_cvx_safe")}
    older = _variant(model, tmp_path / "older.pt",
                     guidance_config={**bundle, "planning": planning})
    generation = GenerationSpec.build("chance", 0, GuidanceConfig.from_json(bundle))
    _check_model(checkpoint.load(older), generation, "older.pt")
    koz = {**bundle, "scenario": {**bundle["scenario"], "koz_semi_axes_m": [150.0] * 3}}
    with pytest.raises(InputError, match="differing: scenario") as exc:
        _check_model(checkpoint.load(_variant(model, tmp_path / "koz.pt",
                                              guidance_config=koz)), generation, "koz.pt")
    # resuming with another model, batch or seed is refused, and nothing is written
    copy = tmp_path / "copy"
    shutil.copytree(dag_dir, copy)
    before = (copy / MANIFEST).read_bytes()
    other = _variant(model, tmp_path / "other.pt")
    for kw, field in (({"model": other}, "--model"), ({"batch": 2}, "--batch"),
                      ({"seed": SEED + 1}, "--seed"), ({"n": N_DAG + 1}, "--n")):
        with pytest.raises(InputError) as exc:
            _run(copy, kw.pop("model", model), src, **kw)
        assert exc.value.field == field and "new --out" in str(exc.value)
    assert (copy / MANIFEST).read_bytes() == before
    with pytest.raises(InputError, match="is a DAgger dataset") as exc:  # as the source
        _run(tmp_path / "y", model, dag_dir)
    assert exc.value.field == "--data"
    plain = tmp_path / "plain"  # a generate directory as --out
    shutil.copytree(src, plain)
    with pytest.raises(GuidanceError, match="seed_rule"):
        _run(plain, model, src, seed=11, n=N_SRC)


def test_valid_mask_keeps_the_prefix_out_of_the_loss():
    starts = np.array([0, 0, 5, 40, 8])
    train_from = np.array([0, 7, 20, 7, 3])
    n = 50
    mask = valid_mask(starts, n, train_from)  # (b, N)
    for b, (s, k) in enumerate(zip(starts, train_from)):
        node = s + np.arange(n)
        assert np.array_equal(mask[b].numpy(), (node < n) & (node >= max(s, k)))
    assert np.array_equal(valid_mask(starts, n).numpy(), valid_mask(starts, n, 0 * starts))
    assert torch.equal(valid_mask(starts, n, torch.as_tensor(train_from)), mask)
    # make_batch gathers the same mask from the rows' train_from
    m = 5
    tensors = {"goal": torch.zeros(m, 6), "reward": torch.zeros(m, n),
               "constraint": torch.zeros(m, n), "state": torch.zeros(m, n, 6),
               "control": torch.zeros(m, n, 3), "burn_mps": torch.zeros(m, n),
               "train_from": torch.as_tensor(train_from[::-1].copy())}
    rows = np.arange(m)[::-1].copy()
    assert torch.equal(make_batch(tensors, rows, starts, n)["mask"], mask)


class _Predicts:
    """Stands in for the model: returns fixed predictions."""

    cfg = SimpleNamespace(burn_gate=False)

    def __init__(self, *outputs: torch.Tensor) -> None:
        self.outputs = outputs

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.outputs


def test_loss_terms_have_no_gradient_on_the_prefix():
    n, k = 12, 5
    batch = {"goal": torch.zeros(1, n, 6), "reward": torch.zeros(1, n),
             "constraint": torch.zeros(1, n), "state": torch.ones(1, n, 6),
             "control": torch.ones(1, n, 3), "burn_mps": torch.ones(1, n),
             "timestep": torch.arange(n)[None], "mask": valid_mask(np.array([0]), n, [k])}
    u_pred = torch.zeros(1, n, 3, requires_grad=True)
    x_pred = torch.zeros(1, n, 6, requires_grad=True)
    sse_u, sse_x, _ = loss_terms(_Predicts(u_pred, x_pred), batch)
    (sse_u + sse_x).backward()
    assert (u_pred.grad[0, :k] == 0).all() and (u_pred.grad[0, k:] != 0).all()
    assert (x_pred.grad[0, :k - 1] == 0).all() and (x_pred.grad[0, k - 1:-1] != 0).all()
    assert loss_counts(batch["mask"]) == (3 * (n - k), 6 * (n - k))
    assert float(sse_u.detach()) == 3 * (n - k) and float(sse_x.detach()) == 6 * (n - k)


def test_training_on_src_and_dagger_data(src, dag_dir, dag, tmp_path):
    data = load_training_data([str(src), str(dag_dir)], "roe", 0.1, seed=0)
    raw = load_dataset(src)
    n_src = int((raw["feasible"] & ~raw["is_test"]).sum())
    tf = data.tensors["train_from"].numpy()
    assert tf.shape == (n_src + N_DAG,) and (tf[:n_src] == 0).all()
    assert np.array_equal(tf[n_src:], dag["train_from"])
    infos = data.provenance["manifests"]
    assert [i["dagger_rows"] for i in infos] == [0, N_DAG]
    out = tmp_path / "m.pt"
    summary = train(TrainOptions(data=(str(src), str(dag_dir)), out=str(out), preset="tiny",
                                 max_steps=3, overrides={"suffix_fraction": 0.5},
                                 progress=False), log=_quiet)
    assert summary["step"] == 3 and np.isfinite(summary["best_val_loss"])
    assert len(checkpoint.load(out).meta["dataset"]["manifests"]) == 2
    # the cost-ratio filter: DAgger rows whose expert suffix costs more than r J_CVX are out
    rows = np.arange(N_DAG)
    ratio = -dag["reward_to_go_mps"][rows, dag["train_from"]] / dag["cvx_cost_mps"]
    r = float(np.median(ratio[dag["feasible"]]))
    cut = load_training_data([str(src), str(dag_dir)], "roe", 0.1, seed=0,
                             dagger_max_cost_ratio=r)
    kept = dag["feasible"] & (ratio <= r)
    assert np.array_equal(cut.tensors["train_from"].numpy()[n_src:], dag["train_from"][kept])
    info = cut.provenance["manifests"][1]
    assert info["dagger_rows"] == kept.sum() < dag["feasible"].sum()
    assert info["dagger_rows_over_cost_ratio"] == dag["feasible"].sum() - kept.sum()
    assert cut.provenance["dagger_max_cost_ratio"] == r
    with pytest.raises(ConfigError, match="dagger_max_cost_ratio"):
        TrainConfig(dagger_max_cost_ratio=-1.0)


def test_fed_reward_relabels_dagger_rows_as_their_rollout_was_fed(src, model, dag_dir, dag):
    """--dagger-reward fed: a DAgger row's R is the rollout's own update from R(t_1) = -J_CVX
    along the row's controls (`rollout.replay`, the oracle; float32 tensors); the source's rows
    keep their hindsight R; the choice is in the provenance and checked."""
    hind = load_training_data([str(src), str(dag_dir)], "roe", 0.1, seed=0)
    fed = load_training_data([str(src), str(dag_dir)], "roe", 0.1, seed=0,
                             dagger_reward="fed")
    n_src = int((fed.tensors["train_from"] == 0).sum())
    r_hind, r = (d.normalizer.denormalize("reward", d.tensors["reward"].double().numpy())
                 for d in (hind, fed))  # [m/s] (each fits its own statistics)
    np.testing.assert_allclose(r[:n_src], r_hind[:n_src], rtol=0, atol=1e-5)  # float32
    r = r[n_src:]
    safety = build_safety(checkpoint.load(model))
    rows = np.flatnonzero(dag["feasible"])
    assert len(rows) == r.shape[0] > 0
    for j, i in enumerate(rows):
        oracle = replay(safety, dag["roe_m"][i, 0], dag["dv_rtn_mps"][i],
                        -dag["cvx_cost_mps"][i]).reward_to_go_mps[0]
        np.testing.assert_allclose(r[j], oracle, rtol=0, atol=1e-5)  # float32 tensors
        k = int(dag["train_from"][i])  # hindsight and fed differ by a constant from k on
        diff = oracle - dag["reward_to_go_mps"][i]
        np.testing.assert_allclose(diff[k:], diff[k], rtol=0, atol=1e-9)
    assert fed.provenance["dagger_reward"] == "fed"
    with pytest.raises(ConfigError, match="dagger_reward"):
        TrainConfig(dagger_reward="oracle")


def test_cli(src, model, dag_dir, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["dagger", "--help"])
    assert exc.value.code == 0 and "train_from" in capsys.readouterr().out
    args = ["dagger", "--model", str(model), "--data", str(src), "--out", str(dag_dir),
            "--n", str(N_DAG), "--seed", str(SEED), "--batch", str(BATCH), "--workers", "1",
            "--no-progress"]
    assert main(args) == 0
    assert "already complete" in capsys.readouterr().out
    assert main([a if a != str(BATCH) else "0" for a in args]) == 2
    err = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert err["error"] == "InputError" and "--batch" in err["message"]
