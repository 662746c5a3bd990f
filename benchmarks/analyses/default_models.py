"""Which shipped model each passive-safety mode flies by default, chosen by what is flown.

Reads the summaries of warm-start analyses (`art-guidance evaluate --split all`) that ran the
candidate models on fresh scenarios of their mode, and prints per mode, per model:

- flown: the plan the node flies (`warm_start auto`: SCVx* from CVX, and from ART where the
  post hoc check accepts the proposal or CVX does not converge; the cheaper is kept) against
  SCVx* from CVX alone: the mean saving over all scenarios [mm/s], the largest, and the
  scenarios better / worse by more than 1 mm/s;
- the proposal's cost: its median time over all scenarios (rollout sweep + post hoc check);
- the warm start's quality: the suboptimality improvement of SCVx* from ART over SCVx* from
  CVX at C_CVX >= 40 and over all (ratio of sums), the infeasible-or-not-converged share at
  C_CVX >= 40 from CVX and from ART, the median total runtime (proposal + SCVx*) at C_CVX >= 30;
- the rollout metrics of the proposals (share with E_C = 0, median 100 E_R, share accepted).

The rule (`choose`): among the models never worse than CVX alone by more than 1 mm/s, those
whose mean flown saving is within the paired 95 % interval of the best's (the best's saving
minus theirs, per scenario, no more than 1.96 standard errors of that paired difference); of
these, the one with the cheapest proposal. That is what a node flying it saves, at the least
cost in the replan. The other figures are reported beside it, not used: the improvement of
SCVx* from ART is what a node that always solved both would get, and the rollout metrics judge
the proposal before SCVx* has corrected it (docs/results.md, "Shipped defaults").

A mode is chosen within one evaluation (the same scenarios for every candidate: the interval is
paired): give one summary per mode (`--eval MODE=PATH`) where several cover it. The interval
is computed from, in this order:

1. the summary's `flown_pairs` (the per-scenario difference of the two models' flown savings,
   its mean and standard error; `art-guidance evaluate` writes them from now on);
2. a `--paired` file's record of that difference for the same evaluation (its `out`) and the
   same two checkpoints (their sha256): the figures measured from an evaluation's rows for a
   summary written before (1) existed (the committed ones:
   `benchmarks/results/default_models/paired.json`);
3. none: a model without a paired figure against the best is not shown to be within its
   interval and does not join it (the rule then keeps the best).

The proposal's cost is its median time in that evaluation (`runtime_ms_median.ws_art`, all
scenarios; ties go to the larger saving). The evaluation runs the models in turn, so the times
share the machine's load only on a quiet machine: between models of the same architecture
(which cost the same) they differ by load alone. `bench slim` measures two models' proposals
paired, alternated scenario by scenario.

    python benchmarks/analyses/default_models.py \
        --eval deterministic=benchmarks/results/default_models/summary.json \
        --eval chance=benchmarks/results/slim/eval_slim1e40_s11s12_summary.json \
        --paired benchmarks/results/default_models/paired.json \
        --json benchmarks/results/default_models/choice.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

Z95 = 1.959964  # the two-sided 95 % normal quantile
MODES = ("chance", "deterministic")


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:+.1f} %"


def model_row(m: dict, eval_out: str = "") -> dict:
    """The comparison figures of one model's entry in an evaluation summary (`eval_out`: that
    evaluation's output directory, its identity for the paired figures)."""
    bins = m["bins"]
    high, all_, mid = bins.get(">=40", {}), bins[">=0"], bins.get(">=30", {})
    flown = m["auto_minus_scp_cvx_mps"]
    runtime = mid.get("runtime_ms_median", {})
    return {
        "model": m["name"], "mode": m["mode"], "n": m["n"], "sha256": m.get("sha256", ""),
        "eval": eval_out, "n_parameters": m.get("n_parameters"),
        "flown_saving_mean_mmps": -1e3 * flown["mean"] if flown.get("mean") is not None
        else None,
        "flown_saving_sem_mmps": 1e3 * flown["sem"] if flown.get("sem") is not None else None,
        "flown_saving_max_mmps": -1e3 * flown["min"] if flown.get("min") is not None else None,
        "flown_better_by_1mm": flown["n_better_by_1mm"],
        "flown_worse_by_1mm": flown["n_worse_by_1mm"],
        "proposal_ms_median": all_.get("runtime_ms_median", {}).get("ws_art"),
        "gain_high": high.get("improvement_ratio", {}).get("of_means"),
        "n_high": high.get("n", 0),
        "gain_all": all_["improvement_ratio"]["of_means"],
        "not_converged_high_cvx": high.get("infeasible_rate_cvx"),
        "not_converged_high_art": high.get("infeasible_rate_art"),
        "runtime_total_art_ms_c30": runtime.get("total_art"),
        "runtime_total_cvx_ms_c30": runtime.get("total_cvx"),
        "rollout_e_c_zero": m["c_art_zero"], "rollout_e_r_pct_median": m["e_r_pct_median"],
        "accepted_share": m["frac_accepted"]}


def paired_record(best: dict, other: dict, pairs: list[dict]) -> dict | None:
    """The paired figure of `best`'s flown saving minus `other`'s in their evaluation:
    {"mean_mmps", "sem_mmps", "n", "source"} (None: no figure for the two)."""
    for p in pairs:
        if p.get("eval", best["eval"]) != best["eval"] or p.get("mode") != best["mode"]:
            continue
        names = {p.get("sha256_a") or p.get("a"): 1.0, p.get("sha256_b") or p.get("b"): -1.0}
        ids = (best["sha256"] or best["model"], other["sha256"] or other["model"])
        if set(names) != set(ids) or p.get("sem_mmps") is None:
            continue
        sign = names[ids[0]]  # the record is a minus b: flip it where best is b
        return {"mean_mmps": sign * p["saving_a_minus_b_mmps"], "sem_mmps": p["sem_mmps"],
                "n": p.get("n"), "source": p.get("source", "flown_pairs")}
    return None


def decide(rows: list[dict], pairs: list[dict] | None = None) -> dict[str, dict]:
    """Mode -> how the rule decided (module docstring): the default ("choice"), the best
    saving ("best"), the models within its paired 95 % interval ("within") and per candidate
    the paired figure it was judged by ("paired": mean and standard error of best minus it,
    the interval's half-width, or why none)."""
    pairs = pairs or []
    out = {}
    for mode in sorted({r["mode"] for r in rows}):
        ok = [r for r in rows if r["mode"] == mode and r["flown_worse_by_1mm"] == 0
              and r["flown_saving_mean_mmps"] is not None]
        if not ok:
            continue
        if len({r["eval"] for r in ok}) > 1:
            raise ValueError(f"{mode}: candidates from several evaluations "
                             f"({sorted({r['eval'] for r in ok})}); the interval is paired: "
                             "give one evaluation per mode (--eval MODE=PATH)")
        best = max(ok, key=lambda r: r["flown_saving_mean_mmps"])
        within, judged = [best], {}
        for r in ok:
            if r is best:
                continue
            p = paired_record(best, r, pairs)
            if p is None:
                judged[r["model"]] = {"within": False, "why": "no paired figure against the best"}
                continue
            half = Z95 * p["sem_mmps"]
            inside = p["mean_mmps"] <= half
            judged[r["model"]] = {**p, "half_width_95_mmps": half, "within": inside}
            if inside:
                within.append(r)
        cost = [r for r in within if r["proposal_ms_median"] is not None] or within
        choice = min(cost, key=lambda r: (r["proposal_ms_median"] or 0.0,
                                          -r["flown_saving_mean_mmps"]))
        out[mode] = {"choice": choice["model"], "best": best["model"],
                     "within": [r["model"] for r in within], "paired": judged,
                     "never_worse": [r["model"] for r in ok]}
    return out


def choose(rows: list[dict], pairs: list[dict] | None = None) -> dict[str, str]:
    """Mode -> the default model: among the models never worse than CVX alone by > 1 mm/s,
    those whose mean flown saving is within the paired 95 % interval of the best's; of these,
    the one with the cheapest proposal (`decide`; module docstring)."""
    return {mode: d["choice"] for mode, d in decide(rows, pairs).items()}


def read_summary(spec: str) -> tuple[str | None, Path, dict]:
    """(mode or None, path, summary) of an `--eval` value: [MODE=]PATH, PATH an evaluation
    directory (its summary.json) or a summary file."""
    mode, sep, path = spec.partition("=")
    if not sep or mode not in MODES:
        mode, path = None, spec
    p = Path(path)
    p = p / "summary.json" if p.is_dir() else p
    return mode or None, p, json.loads(p.read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--eval", required=True, action="append",
                   help="[MODE=]PATH: an `art-guidance evaluate` output directory or its "
                        "summary.json (MODE: take only that mode's models from it); repeatable")
    p.add_argument("--paired", default=None, help="a file of paired flown-saving figures "
                   "for summaries without `flown_pairs` (module docstring)")
    p.add_argument("--json", default=None, help="also write the rows and the choice here")
    args = p.parse_args(argv)
    rows, pairs, evals = [], [], []
    for spec in args.eval:
        mode, path, summary = read_summary(spec)
        out = summary.get("out", str(path))
        evals.append({"path": str(path), "out": out, "mode": mode or "all"})
        rows += [model_row(m, out) for m in summary["models"] if mode in (None, m["mode"])]
        pairs += [dict(q, eval=out) for q in summary.get("flown_pairs", [])]
    if args.paired:
        pairs += json.loads(Path(args.paired).read_text())["pairs"]
    head = ("model", "n", "flown saving mean / max [mm/s]", "better / worse",
            "proposal ms (median)", "gain >=40 (n)", "gain all", "not conv. >=40 CVX -> ART",
            "total ms >=30 ART / CVX", "E_C = 0", "100 E_R", "accepted")
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        mean = "-" if r["flown_saving_mean_mmps"] is None \
            else f"{r['flown_saving_mean_mmps']:.2f}"
        print(f"| {r['model']} | {r['n']} | {mean} / "
              f"{r['flown_saving_max_mmps']:.0f} | {r['flown_better_by_1mm']} / "
              f"{r['flown_worse_by_1mm']} | {r['proposal_ms_median'] or 0:.0f} | "
              f"{_pct(r['gain_high'])} ({r['n_high']}) | "
              f"{_pct(r['gain_all'])} | {_pct(r['not_converged_high_cvx'])[1:]} -> "
              f"{_pct(r['not_converged_high_art'])[1:]} | "
              f"{r['runtime_total_art_ms_c30'] or 0:.0f} / "
              f"{r['runtime_total_cvx_ms_c30'] or 0:.0f} | "
              f"{100 * r['rollout_e_c_zero']:.0f} % | {r['rollout_e_r_pct_median']:+.1f} % | "
              f"{100 * r['accepted_share']:.0f} % |")
    decided = decide(rows, pairs)
    for mode, d in decided.items():
        print(f"{mode}: best flown saving {d['best']}")
        for name, j in d["paired"].items():
            if "mean_mmps" in j:
                print(f"  {name}: best minus it {j['mean_mmps']:+.2f} +/- {j['sem_mmps']:.2f} "
                      f"mm/s (95 % half-width {j['half_width_95_mmps']:.2f}): "
                      f"{'within' if j['within'] else 'outside'}")
            else:
                print(f"  {name}: {j['why']}")
        print(f"default, {mode}: {d['choice']} (cheapest proposal of {', '.join(d['within'])})")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(
            {"eval": evals[0]["out"] if len(evals) == 1 else evals, "rows": rows,
             "rule": decided, "choice": {m: d["choice"] for m, d in decided.items()}},
            indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
