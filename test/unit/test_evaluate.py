"""Warm-start evaluation: real solvers and real (tiny, untrained) checkpoints, resume, workers,
the paper's metrics on constructed rows, figures, refusals."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from art_guidance.art.checkpoint import model_payload, save
from art_guidance.cli import main
from art_guidance.config import GuidanceConfig
from art_guidance.data.stages import GenerationSpec
from art_guidance.scenarios import sample_scenario, sample_seed
from art_guidance.data.storage import DatasetWriter
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.errors import InputError
from art_guidance.eval import inputs as eval_inputs
from art_guidance.eval import results, runner
from art_guidance.eval.report import REPORT, high_bin, report_markdown
from art_guidance.eval.warmstart import ROW_FIELDS, WarmStartRow, columns, summarize
from art_guidance.optim import ScpStatus
from helpers.art_models import untrained_art

N_DATA, N_EVAL = 30, 2  # 3 held-out scenarios per dataset, 2 evaluated per model
TIMING = {"ms_cvx", "ms_art", "ms_scp_cvx", "ms_scp_art", "ms_task"}


def _dataset(root: Path, mode: str, seed: int) -> Path:
    """A dataset directory holding what the evaluation reads of a sample (initial state,
    target, a CVX label marking a solvable scenario): the scenarios of the seed rule, without
    solving the three stages."""
    spec = GenerationSpec.build(mode, seed)
    chief = np.array(spec.scenario.chief_oe)
    samples = [sample_scenario(spec.scenario, sample_seed(seed, i)) for i in range(N_DATA)]
    arrays = {"index": np.arange(N_DATA),
              "roe0_m": np.array([roe_from_rtn_linear(chief, s.rtn0) for s in samples]),
              "target_rtn": np.array([s.target_rtn for s in samples]),
              "cvx_cost_mps": np.ones(N_DATA), "cvx_constraint_to_go0": np.zeros(N_DATA, int)}
    with DatasetWriter(root, spec.header(N_DATA)) as writer:
        writer.write_shard(arrays)
    return root


def _checkpoint(path: Path, mode: str, representation: str, seed: int) -> Path:
    art = untrained_art("tiny", representation, seed)
    meta = {"dataset": {"mode": mode, "guidance_config": GuidanceConfig.load().to_json()}}
    save(path, model_payload(art.model, art.normalizer, meta))
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("inputs")
    return {"chance": _dataset(root / "chance", "chance", 3),
            "det": _dataset(root / "det", "deterministic", 4),
            "model_c": _checkpoint(root / "roe_c.pt", "chance", "roe", 0),
            "model_d": _checkpoint(root / "rtn_d.pt", "deterministic", "rtn", 1)}


def _run(inputs: dict, out: Path, **kw) -> dict:
    kw = {"n": N_EVAL, "workers": 1, "progress": False, "figures": False,
          "log": lambda _: None, **kw}
    return runner.run_evaluation(out, [inputs["chance"], inputs["det"]],
                                 [inputs["model_c"], inputs["model_d"]], **kw)


def _rows(out: Path) -> dict:
    return results.read_results(out)[1]


def _assert_same_rows(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for key in a:
        if key not in TIMING:
            assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), key


@pytest.fixture(scope="module")
def ref(inputs, tmp_path_factory) -> Path:
    """Both models, both datasets, one process, with figures."""
    out = tmp_path_factory.mktemp("ref") / "eval"
    assert _run(inputs, out, figures=True)["status"] == "complete"
    return out


@pytest.mark.slow
def test_each_model_runs_on_the_datasets_of_its_mode(ref, inputs):
    summary = json.loads((ref / "summary.json").read_text())
    assert summary["complete"] and summary["n_done"] == summary["n_scenarios"] == 2 * N_EVAL
    chance, det = summary["models"]
    assert (chance["mode"], chance["representation"], chance["datasets"]) == ("chance", "roe", [0])
    assert (det["mode"], det["representation"], det["datasets"]) == ("deterministic", "rtn", [1])
    assert chance["n"] == det["n"] == N_EVAL
    assert [d["mode"] for d in summary["datasets"]] == ["chance", "deterministic"]
    assert all(len(d["sha256"]) == 64 for d in summary["datasets"])
    assert all(len(m["sha256"]) == 64 for m in summary["models"])
    assert summary["this_run"]["scenarios"] == 2 * N_EVAL
    assert summary["this_run"]["scenarios_per_s"] > 0 and summary["sizes"]["bytes"] > 0
    for m in summary["models"]:
        b = m["bins"][">=0"]
        assert b["n"] == N_EVAL and b["runtime_ms_median"]["total_art"] > 0
        assert b["iterations_cvx"]["mean"] >= 1 and 0 <= b["infeasible_rate_art"] <= 1
    rows = _rows(ref)
    assert set(ROW_FIELDS) <= set(rows)
    assert np.array_equal(rows["model"], [0, 0, 1, 1])
    assert np.array_equal(rows["dataset"], [0, 0, 1, 1])


def test_figures_and_the_recomputed_example(ref, monkeypatch):
    summary = json.loads((ref / "summary.json").read_text())
    names = summary["figures"]
    for kind in ("warmstart", "posthoc-maps", "posthoc-hist"):
        assert f"{kind}-0-roe-chance.png" in names and f"{kind}-1-rtn-deterministic.png" in names
    for name in names:
        data = (ref / "figures" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    examples = [m["example"] for m in summary["models"] if "example" in m]
    assert examples, "no scenario with both SCVx* runs converged"
    assert all(e["reproduced"] for e in examples)  # solving again gives the stored row
    rows = _rows(ref)
    for m in summary["models"]:
        if "example" in m:
            sel = rows["model"] == m["k"]
            gain = rows["j_scp_cvx"][sel] - rows["j_scp_art"][sel]
            assert m["example"]["gain_mps"] == pytest.approx(np.nanmax(gain), abs=1e-9)
    # re-rendering from the stored results solves nothing
    shutil.rmtree(ref / "figures")

    def no_solving(*_):
        raise AssertionError("figures-only must not solve")

    monkeypatch.setattr(results, "load_model", no_solving)
    assert main(["evaluate", "--figures-only", "--out", str(ref)]) == 0
    assert sorted(p.name for p in (ref / "figures").iterdir()) == sorted(names)


def test_report_puts_each_mode_beside_the_paper(ref):
    summary = json.loads((ref / "summary.json").read_text())
    text = (ref / REPORT).read_text()
    assert text == report_markdown(summary)  # written with the summary
    det = text.index("## Deterministic")
    chance = text.index("## Chance-constrained")
    assert "up to 35 % at high C_CVX" in text[det:] and "up to 22 % at high C_CVX" in text[chance:]
    assert "### roe-chance (roe_c.pt)" in text and "### rtn-deterministic (rtn_d.pt)" in text
    m = summary["models"][0]
    b = m["bins"][">=0"]
    row = next(line for line in text[text.index("### roe-chance"):].splitlines()
               if line.startswith("| >= 0 |"))
    assert row.startswith(f"| >= 0 | {b['n']} | {b['n_both_converged']} |")
    assert f"{b['iterations_cvx']['mean']:.1f} / {b['iterations_art']['mean']:.1f}" in row
    assert m["train_n"] == 0 and m["n_parameters"] > 0  # the test checkpoints record no data
    # the high bin needs MIN_PAIRS converged pairs; none here, so the >= 0 bin stands in
    assert high_bin(m["bins"]) is None
    assert high_bin({">=0": {"n_both_converged": 30}, ">=10": {"n_both_converged": 20},
                     ">=20": {"n_both_converged": 5}}) == ">=10"


def test_two_workers_give_the_same_results(ref, inputs, tmp_path):
    out = tmp_path / "w2"
    assert _run(inputs, out, workers=2, shard_size=1)["status"] == "complete"
    _assert_same_rows(_rows(ref), _rows(out))


def test_resume_after_an_interruption_loses_nothing(ref, inputs, tmp_path, monkeypatch):
    out = tmp_path / "resumed"
    real, calls = runner.evaluate_chunk, []

    def interrupted(spec, indices):
        calls.append(list(indices))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(spec, indices)

    monkeypatch.setattr(runner, "evaluate_chunk", interrupted)
    cmd = ["evaluate", "--suite", "warmstart", "--data", str(inputs["chance"]), "--data",
           str(inputs["det"]), "--model", str(inputs["model_c"]), "--model",
           str(inputs["model_d"]), "--n", str(N_EVAL), "--workers", "1", "--shard-size", "1",
           "--no-figures", "--no-progress", "--out", str(out)]
    assert main(cmd) == 130
    assert json.loads((out / "summary.json").read_text())["n_done"] == 1
    monkeypatch.setattr(runner, "evaluate_chunk", real)
    summary = _run(inputs, out, shard_size=1)
    assert summary["status"] == "complete" and summary["this_run"]["scenarios"] == 2 * N_EVAL - 1
    assert [r["status"] for r in summary["runs"]] == ["interrupted", "complete"]
    _assert_same_rows(_rows(ref), _rows(out))
    again = _run(inputs, out)
    assert again["status"] == "already_complete" and again["this_run"]["scenarios"] == 0


def test_another_command_on_the_same_out_is_refused(ref, inputs, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(ref, copy)
    with pytest.raises(InputError, match="--n"):
        _run(inputs, copy, n=1)
    with pytest.raises(InputError, match="--model"):
        runner.run_evaluation(copy, [inputs["chance"]], [inputs["model_c"]], n=N_EVAL,
                              progress=False, log=lambda _: None)
    with pytest.raises(InputError, match="holds a dataset"):
        _run(inputs, inputs["chance"])
    assert main(["evaluate", "--suite", "warmstart", "--data", str(inputs["chance"]),
                 "--data", str(inputs["det"]), "--model", str(inputs["model_c"]), "--n", "1",
                 "--out", str(copy), "--no-progress"]) == 2
    assert "another command" in capsys.readouterr().err


def test_a_model_whose_mode_matches_no_dataset_is_refused(inputs, tmp_path, capsys):
    with pytest.raises(InputError, match="deterministic data"):
        runner.run_evaluation(tmp_path / "x", [inputs["chance"]], [inputs["model_d"]], n=1,
                              progress=False, log=lambda _: None)
    assert main(["evaluate", "--suite", "warmstart", "--data", str(inputs["chance"]),
                 "--model", str(inputs["model_c"]), "--model", str(inputs["model_d"]),
                 "--out", str(tmp_path / "y"), "--no-progress"]) == 2
    assert "no --data dataset is deterministic" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()


# --------------------------------------------------------------------------- metrics
_BASE = WarmStartRow(j_cvx=1.0, c_cvx=0, art_cost=1.0, c_art=0, e_r=0.0, e_c=0.0,
                     accepted=True, j_scp_cvx=1.2, j_scp_art=1.1, it_scp_cvx=10, it_scp_art=6,
                     ms_cvx=10.0, ms_art=50.0, ms_scp_cvx=300.0, ms_scp_art=200.0,
                     ok_scp_cvx=True, ok_scp_art=True, j_auto=1.1, ok_auto=True, it_auto=6,
                     st_scp_cvx=0, st_scp_art=0)
_INF = ScpStatus.INFEASIBLE.value
_MAXIT = ScpStatus.MAX_ITERATIONS.value


def _constructed() -> list[WarmStartRow]:
    return [
        # C_CVX 0: gap 0.2, gain 0.1 -> ratio 0.5
        _BASE,
        # C_CVX 15: gap 0.4, gain 0.4 -> ratio 1; rejected by the post hoc check
        replace(_BASE, c_cvx=15, j_scp_cvx=1.4, j_scp_art=1.0, accepted=False, e_r=-0.3,
                e_c=3.0, it_scp_cvx=20, it_scp_art=5),
        # C_CVX 25: ART not converged (iteration limit, still feasible) -> infeasible for ART
        replace(_BASE, c_cvx=25, j_scp_art=1.05, st_scp_art=_MAXIT, it_scp_art=50),
        # C_CVX 45: gap 0.1, ART worse by 0.2 -> ratio -2; CVX infeasible in the next row
        replace(_BASE, c_cvx=45, j_scp_cvx=1.1, j_scp_art=1.3, e_r=0.02, e_c=1.0),
        replace(_BASE, c_cvx=45, ok_scp_cvx=False, st_scp_cvx=_INF, j_scp_cvx=9.0),
    ]


def test_bins_ratios_and_infeasibility_on_constructed_rows():
    s = summarize(_constructed())
    assert s["n"] == 5 and [s["bins"][f">={b}"]["n"] for b in (0, 10, 20, 30, 40)] == \
        [5, 4, 3, 2, 2]
    b0, b10, b40 = s["bins"][">=0"], s["bins"][">=10"], s["bins"][">=40"]
    assert b0["n_both_converged"] == 3  # rows 0, 1, 3
    assert b0["improvement_ratio"]["mean"] == pytest.approx((0.5 + 1.0 - 2.0) / 3)
    assert b0["improvement_ratio"]["of_means"] == pytest.approx((0.1 + 0.4 - 0.2) / 0.7)
    assert b10["improvement_ratio"]["median"] == pytest.approx(-0.5)  # rows 1, 3
    assert b0["subopt_cvx_mps"]["mean"] == pytest.approx((0.2 + 0.4 + 0.1) / 3)
    assert b0["subopt_art_mps"]["median"] == pytest.approx(0.1)
    assert b0["infeasible_rate_art"] == pytest.approx(1 / 5)   # iteration limit counts
    assert b0["not_feasible_rate_art"] == 0.0
    assert b0["infeasible_rate_cvx"] == pytest.approx(1 / 5)
    assert b40["infeasible_rate_cvx"] == pytest.approx(1 / 2)
    assert b0["iterations_cvx"]["mean"] == pytest.approx((10 + 20 + 10 + 10 + 10) / 5)
    assert b0["runtime_ms_median"]["total_art"] == pytest.approx(260.0)
    assert b0["runtime_ms_median"]["total_cvx"] == pytest.approx(310.0)


def test_histograms_with_and_without_the_posthoc_check():
    s = summarize(_constructed())
    h, ph = s["gain_histogram"], s["gain_histogram_posthoc"]
    assert h["n"] == 3 and sum(h["counts"]) == 3
    assert (h["min_mps"], h["max_mps"]) == (pytest.approx(-0.2), pytest.approx(0.4))
    # the rejected row flies PS-CVX (difference 0); the not-converged-ART row is accepted and
    # has no defined difference; the infeasible-CVX row has none either
    assert ph["n"] == 3
    assert (ph["min_mps"], ph["max_mps"]) == (pytest.approx(-0.2), pytest.approx(0.1))
    maps = s["posthoc_maps"]
    pop = np.array(maps["population"])
    assert pop.sum() == 5 and pop.shape == (6, 11)
    # E_C 3 (cell "2-4"), 100 E_R -30 (cell (-50, -25]): the rejected row, ratio 1, 15 saved
    assert pop[2, 1] == 1 and maps["improvement_ratio_mean"][2][1] == pytest.approx(1.0)
    assert maps["iterations_saved_mean"][2][1] == pytest.approx(15.0)
    assert maps["improvement_ratio_mean"][5][0] is None  # no data
    assert maps["improvement_ratio_of_sums"][2][1] == pytest.approx(1.0)
    assert maps["improvement_ratio_of_sums"][5][0] is None


def test_the_papers_check_beside_the_pipelines():
    """Flown gains with the pipeline's check (`accepted`) and with the paper's check of the
    same proposals (`accepted_rollout`): here the paper's check also accepts the row whose
    PS-ART is 0.2 m/s dearer; the pipeline's does not. An evaluation stored before the
    check's subject existed reads its one check as both."""
    rows = _constructed()
    rows = [replace(r, accepted_rollout=r.accepted) for r in rows]
    rows[3] = replace(rows[3], accepted=False, accepted_rollout=True)
    s = summarize(rows)
    assert s["gain_histogram_posthoc_rollout"]["min_mps"] == pytest.approx(-0.2)
    assert s["gain_histogram_posthoc"]["min_mps"] == pytest.approx(0.0)
    assert (s["posthoc_worse_by_10mm"], s["posthoc_rollout_worse_by_10mm"]) == (0, 1)
    assert s["accepted_rollout"] == s["accepted"] + 1
    old = {k: np.array([getattr(r, k) for r in _constructed()]) for k in ROW_FIELDS
           if not k.endswith("_rollout")}
    cols = columns(old)
    np.testing.assert_array_equal(cols["accepted_rollout"], cols["accepted"])
    np.testing.assert_array_equal(cols["e_r_rollout"], cols["e_r"])


def test_summary_of_stored_columns_equals_summary_of_rows():
    rows = _constructed()
    cols = {k: np.array([getattr(r, k) for r in rows]) for k in ROW_FIELDS}
    assert json.dumps(summarize(cols)) == json.dumps(summarize(rows))


def test_flown_pairs_pair_two_models_of_a_mode_on_the_scenarios_both_flew():
    """`flown_pairs`: the per-scenario difference of two models' flown savings, over the
    scenarios (dataset, sample) where both flew a feasible plan beside a feasible SCVx* from
    CVX; models of another mode are not paired; the per-model standard error beside it."""
    models = [{"path": f"m/{n}.pt", "sha256": n * 64, "mode": mode, "representation": "rtn"}
              for n, mode in (("a", "chance"), ("d", "deterministic"), ("b", "chance"))]
    head = {"evaluation": {"models": models}}
    # (model, dataset, sample, J_auto); J_SCP,CVX = 1.2 everywhere; b's plan on (1, 0) and a's
    # on (0, 1) are infeasible, a did not run (1, 0): a and b pair on (0, 0) and (1, 1) only
    spec = [(0, 0, 0, 1.19), (0, 0, 1, 1.0), (0, 1, 1, 1.17), (2, 0, 0, 1.2), (2, 0, 1, 1.1),
            (2, 1, 0, 1.0), (2, 1, 1, 1.2), (1, 0, 0, 1.0), (1, 1, 1, 1.0)]
    rows = [replace(_BASE, j_auto=j, ok_auto=not (k == 2 and (d, i) == (1, 0)) and
                    not (k == 0 and (d, i) == (0, 1))) for k, d, i, j in spec]
    cols = {f: np.array([getattr(r, f) for r in rows]) for f in ROW_FIELDS}
    cols.update(model=np.array([k for k, *_ in spec]), dataset=np.array([d for _, d, *_ in spec]),
                sample=np.array([i for _, _, i, _ in spec]), index=np.arange(len(spec)))
    pairs = results.flown_pairs(head, cols)
    assert [(p["a"], p["b"], p["mode"], p["n"]) for p in pairs] == [("a.pt", "b.pt", "chance", 2)]
    diff = 1e3 * np.array([1.2 - 1.19, 1.2 - 1.17])  # J_auto,b - J_auto,a on (0, 0), (1, 1)
    assert pairs[0]["saving_a_minus_b_mmps"] == pytest.approx(diff.mean())
    assert pairs[0]["sem_mmps"] == pytest.approx(np.std(diff, ddof=1) / np.sqrt(2))
    assert pairs[0]["sha256_a"] == "a" * 64 and pairs[0]["sha256_b"] == "b" * 64
    d = np.array([1.2, 1.1, 1.2]) - 1.2  # model b's feasible rows: J_auto - J_SCP,CVX
    flown = summarize([r for r, (k, *_) in zip(rows, spec) if k == 2])["auto_minus_scp_cvx_mps"]
    assert flown["n"] == 3 and flown["sem"] == pytest.approx(np.std(d, ddof=1) / np.sqrt(3))


def test_heldout_reads_the_same_scenarios_as_the_full_load(inputs):
    from art_guidance.eval.scoring import heldout_scenarios
    from art_guidance.data.storage import load_dataset

    full = heldout_scenarios(load_dataset(inputs["chance"]))
    lean = eval_inputs.heldout(inputs["chance"])
    assert set(full) == set(lean) and full["index"].size == N_DATA // 10
    for key in full:
        assert np.array_equal(full[key], lean[key]), key


@pytest.mark.parametrize("run", ["warmstart", "warmstart_single_rollout"])
def test_the_committed_results_are_complete_and_match_the_shipped_models(run):
    """benchmarks/results/warmstart (the sweep) and warmstart_single_rollout: the README's
    results tables are rows of `report.md`, which is the report of the committed summary.json;
    it covers >= 1,000 held-out scenarios per mode with the shipped models (their pinned
    checksums; the four trained ones: the distilled chance-constrained default has its own
    evaluation, `test_shipped_model.py`), and every figure it lists is there."""
    from art_guidance.art.provider import shipped_models

    root = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / run
    summary = json.loads((root / "summary.json").read_text())
    assert (root / REPORT).read_text() == report_markdown(summary)
    assert summary["complete"] and summary["n_done"] == summary["n_scenarios"]
    pinned = {e["sha256"]: name for name, e in shipped_models().items()
              if "distilled_from" not in e}
    assert sorted(pinned[m["sha256"]] for m in summary["models"]) == sorted(pinned.values())
    for mode in ("chance", "deterministic"):
        models = [m for m in summary["models"] if m["mode"] == mode]
        assert {m["representation"] for m in models} == {"roe", "rtn"}
        assert all(m["n"] >= 1000 for m in models)
    for name in summary["figures"]:
        data = (root / "figures" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) < 400_000


def test_single_thread_needs_no_torch(monkeypatch):
    """A flight install (no torch) runs evaluate and the contingency Monte Carlo on the
    exported models: setting one thread does not import torch there."""
    import os
    import sys

    from art_guidance import extras
    from art_guidance.eval.runner import THREAD_VARS, single_thread

    monkeypatch.setattr(extras, "installed", lambda module: module != "torch")
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` would raise
    for var in THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    single_thread()
    assert all(os.environ[v] == "1" for v in THREAD_VARS)
