"""Experiment: SCVx* from every candidate of the conditioning sweep, and what picking among
them is worth (docs/art_training.md, "The post hoc check judges the warm start").

For each scenario of a dataset (every scenario: use a dataset the model was not trained on):
CVX, the provider's eight candidates (R(t_1) = -s J_CVX, `DEFAULT_REWARD_SCALES`), and per
candidate the post hoc numbers of the rollout itself and of its terminal warm start
(`optim.TransferProblem.terminal_warm_start`, where SCVx* starts), then SCVx* from it; SCVx*
from CVX once.
The summary compares selection rules by what SCVx* makes of the pick, against SCVx* from CVX:
the improvement (ratio of sums over both-converged scenarios, all and C_CVX >= 40), and, when
the rule also decides whether ART is used (the post hoc check), how many scenarios use it and
how many of those end more than 10 mm/s dearer or cheaper than from CVX (a rejected one flies
PS-CVX: difference 0).

    python benchmarks/analyses/sweep_candidates.py --data DATA --model MODEL --n 400 --out OUT.json
    python benchmarks/analyses/sweep_candidates.py --seeds 50000:400 --model MODEL --out OUT.json
    python benchmarks/analyses/sweep_candidates.py --table  # docs/art_training.md's table

`--seeds FIRST:COUNT` draws the scenarios with `scenarios.sample_scenario` (seeds no dataset of
a shipped model used) instead of reading a dataset. The summary's "subsets" apply the
provider's rule (the check of the warm start) to the candidates of smaller sweeps
(`SUBSETS`), which is what a sweep of that size would propose: the rollouts of a batch are
independent, so the candidates of a sub-sweep are those of the full one.

About 1 s per scenario on 2 workers (nine SCVx* runs each). RESULT is the committed summary
(benchmarks/results/learned_warm_start/sweep_candidates_roe.json); `test_sweep_candidates`
keeps the documented table equal to its rendering.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from tqdm import tqdm

from art_guidance.art.provider import DEFAULT_REWARD_SCALES, best_candidate
from art_guidance.art.rollout import rollout
from art_guidance.config import GuidanceConfig
from art_guidance.eval.inputs import heldout, load_model, model_info
from art_guidance.optim import TransferProblem

SCALES = np.array(DEFAULT_REWARD_SCALES)
ROOT = Path(__file__).resolve().parents[2]
RESULT = ROOT / "benchmarks" / "results" / "learned_warm_start" / "sweep_candidates_roe.json"
DOC = ROOT / "docs" / "art_training.md"
BEGIN, END = "<!-- sweep-candidates:begin -->", "<!-- sweep-candidates:end -->"
WORSE_MMPS = 10.0  # a pair counts as worse / better beyond this difference [mm/s]
# smaller conditioning sweeps, as scales of DEFAULT_REWARD_SCALES (what each sweep size buys)
SUBSETS = {"1 (s = 1)": (1.0,), "2 (s = 0.9, 1.1)": (0.9, 1.1),
           "4 (s = 0.85, 0.95, 1.05, 1.2)": (0.85, 0.95, 1.05, 1.2),
           "8 (default)": tuple(DEFAULT_REWARD_SCALES)}


def _scenario(args: tuple) -> dict:
    """All candidates of one scenario (runs in a worker, 1 thread)."""
    import torch

    info, roe0, target = args
    torch.set_num_threads(1)
    provider, safety = load_model(info, single_rollout=True)
    cfg = GuidanceConfig()
    problem = TransferProblem.to_target(safety, roe0, target)
    cvx = problem.cvx()
    j = float(cvx.cost_mps)
    res = rollout(provider.art, safety, np.tile(roe0, (SCALES.size, 1)), target, -j * SCALES,
                  0.0)
    scvx = problem.scvx(cfg.scp, cfg.planning.samples_per_node)
    ref = scvx.solve(cvx.dv_rtn_mps)
    out = {"j_cvx": j, "c_cvx": int(safety.evaluate(cvx.roe_m, cvx.dv_rtn_mps)
                                    .constraint_to_go[0]),
           "j_scp_cvx": ref.cost_mps, "ok_cvx": ref.status.value == 0}
    rows = {k: [] for k in ("er_roll", "ec_roll", "er_ws", "ec_ws", "j_scp", "ok")}
    for b, dv in enumerate(res.dv_rtn_mps):
        rows["er_roll"].append(float(res.cost_mps[b]) / j - 1.0)
        rows["ec_roll"].append(int(res.realised_constraint_to_go[b, 0]))
        dv_w, roe_w = problem.terminal_warm_start(dv)
        rows["er_ws"].append(float(np.linalg.norm(dv_w, axis=1).sum()) / j - 1.0)
        rows["ec_ws"].append(int(safety.evaluate(roe_w, dv_w).constraint_to_go[0]))
        r = scvx.solve(dv)
        rows["j_scp"].append(r.cost_mps)
        rows["ok"].append(r.status.value == 0)
    return {**out, **rows}


def _pick(er: np.ndarray, ec: np.ndarray, j_cvx: np.ndarray,
          region: object) -> tuple[np.ndarray, np.ndarray]:
    """The provider's rule (`best_candidate`) on (M, K) post hoc numbers: (M,) pick and
    whether it is inside the region."""
    cost = (1.0 + er) * j_cvx[:, None]
    pick = np.array([best_candidate(cost[i], ec[i], j_cvx[i], region)
                     for i in range(er.shape[0])])
    rows = np.arange(er.shape[0])
    return pick, region.contains(100.0 * er[rows, pick], ec[rows, pick])


def _subset_indices() -> dict[str, np.ndarray]:
    """Column indices of every `SUBSETS` sweep among the full sweep's candidates."""
    return {name: np.array([int(np.flatnonzero(np.isclose(SCALES, s))[0]) for s in scales])
            for name, scales in SUBSETS.items()}


def _subset_pick(cols: dict[str, np.ndarray], idx: np.ndarray,
                 region: object) -> tuple[np.ndarray, np.ndarray]:
    """`_pick` (check of the warm start) among the candidates `idx` only, as full indices."""
    pick, inside = _pick(cols["er_ws"][:, idx], cols["ec_ws"][:, idx], cols["j_cvx"], region)
    return idx[pick], inside


def summarize(cols: dict[str, np.ndarray]) -> dict:
    """The selection rules' outcomes (see the module docstring)."""
    region = GuidanceConfig().planning.posthoc
    m = cols["j_cvx"].size
    ok = cols["ok"] & cols["ok_cvx"][:, None]
    gain = 1e3 * (cols["j_scp_cvx"][:, None] - cols["j_scp"])  # (M, K) [mm/s]
    gap = 1e3 * (cols["j_scp_cvx"] - cols["j_cvx"])
    high = cols["c_cvx"] >= 40
    rows = np.arange(m)

    def rule(pick: np.ndarray, used: np.ndarray | None = None) -> dict:
        g, o = gain[rows, pick], ok[rows, pick]
        out = {"improvement_all": float(g[o].sum() / gap[o].sum()),
               "improvement_high": float(g[o & high].sum() / gap[o & high].sum()),
               "not_converged": float(np.mean(~cols["ok"][rows, pick]))}
        if used is not None:
            flown = np.where(used & o, g, 0.0)
            out.update(used=int(used.sum()), worst_mmps=float(flown.min()),
                       worse=int(np.sum(flown < -WORSE_MMPS)),
                       better=int(np.sum(flown > WORSE_MMPS)), sum_mmps=float(flown.sum()))
        return out

    best = np.where(ok, gain, -np.inf).argmax(axis=1)
    return {
        "n": m, "n_high": int(high.sum()),
        "not_converged_cvx": float(np.mean(~cols["ok_cvx"])),
        "scales": {f"{s:g}": rule(np.full(m, k)) for k, s in enumerate(SCALES)},
        "check_rollout": rule(*_pick(cols["er_roll"], cols["ec_roll"], cols["j_cvx"], region)),
        "check_warm_start": rule(*_pick(cols["er_ws"], cols["ec_ws"], cols["j_cvx"], region)),
        "subsets": {name: rule(*_subset_pick(cols, idx, region))
                    for name, idx in _subset_indices().items()},
        "oracle_best_candidate": rule(best),
        "oracle_best_or_cvx": rule(best, gain[rows, best] > 0),
        "share_any_inside_rollout": float(region.contains(100 * cols["er_roll"],
                                                          cols["ec_roll"]).any(1).mean()),
        "share_any_inside_warm_start": float(region.contains(100 * cols["er_ws"],
                                                             cols["ec_ws"]).any(1).mean()),
    }


def table(summary: dict) -> str:
    """The documented markdown table of a summary."""
    def pct(x: float) -> str:
        return f"{100 * x:+.1f} %"

    lines = ["| pick | improvement C_CVX >= 40 / all | SCVx* from it not converged | flown: "
             "used, worst [mm/s], > 10 mm/s dearer / cheaper |", "|---|---|---|---|"]
    rules = [(f"every scenario's rollout at s = {s}", r) for s, r in summary["scales"].items()]
    rules += [("the check of the rollout (paper)", summary["check_rollout"]),
              ("the check of the warm start (default)", summary["check_warm_start"]),
              ("oracle: the candidate SCVx* makes cheapest", summary["oracle_best_candidate"]),
              ("oracle, flown only where it beats CVX", summary["oracle_best_or_cvx"])]
    for name, r in rules:
        flown = (f"{r['used']}, {r['worst_mmps']:.0f}, {r['worse']} / {r['better']}"
                 if "used" in r else "-")
        lines.append(f"| {name} | {pct(r['improvement_high'])} / {pct(r['improvement_all'])} "
                     f"| {100 * r['not_converged']:.1f} % | {flown} |")
    lines.append(f"| SCVx* from CVX | - | {100 * summary['not_converged_cvx']:.1f} % | - |")
    return "\n".join(lines)


def _scenarios(args: argparse.Namespace) -> list[tuple[np.ndarray, np.ndarray]]:
    """(roe0_m, target_rtn) of the experiment's scenarios: a dataset's first --n, or --seeds."""
    if args.data:
        held = heldout(args.data, "all")
        return [(held["roe0_m"][i], held["target_rtn"][i])
                for i in range(min(args.n, held["index"].size))]
    from art_guidance.config import ScenarioConfig
    from art_guidance.dynamics import roe_from_rtn_linear
    from art_guidance.scenarios import sample_scenario

    first, count = (int(x) for x in args.seeds.split(":"))
    sc = ScenarioConfig()
    chief = np.array(sc.chief_oe)
    out = []
    for seed in range(first, first + count):
        sample = sample_scenario(sc, seed)
        out.append((roe_from_rtn_linear(chief, sample.rtn0), sample.target_rtn))
    return out


def in_doc() -> str:
    """The table between the markers of docs/art_training.md."""
    text = DOC.read_text()
    return text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip()


def main(argv: list[str] | None = None) -> int:
    """Run the experiment and write its summary (and per-scenario arrays beside it)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="dataset directory (every scenario used)")
    ap.add_argument("--seeds", help="FIRST:COUNT scenario seeds drawn instead of a dataset")
    ap.add_argument("--model", help="checkpoint")
    ap.add_argument("--n", type=int, default=400, help="first N scenarios by sample index")
    ap.add_argument("--workers", type=int, default=2, help="processes")
    ap.add_argument("--out", help="summary JSON (per-scenario rows: .npz)")
    ap.add_argument("--table", action="store_true",
                    help="print the documented table of the committed RESULT and exit")
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.loads(RESULT.read_text())))
        return 0
    if not ((args.data or args.seeds) and args.model and args.out):
        ap.error("--data or --seeds, --model and --out are required (or --table)")
    os.environ["OMP_NUM_THREADS"] = "1"
    info = model_info(args.model)  # loaded and checked once; workers cache the model
    tasks = [(info, roe0, target) for roe0, target in _scenarios(args)]
    t0 = time.perf_counter()
    with Pool(args.workers) as pool:
        rows = list(tqdm(pool.imap(_scenario, tasks, chunksize=2), total=len(tasks),
                         desc="scenarios"))
    cols = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    np.savez(os.path.splitext(args.out)[0] + ".npz", **cols)
    summary = {"data": args.data or f"seeds {args.seeds}",
               "model": os.path.basename(args.model),
               "wall_s": time.perf_counter() - t0, **summarize(cols)}
    with open(args.out, "w") as f:
        json.dump(summary, f, indent=1)
    json.dump(summary, sys.stdout, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
