"""Which shipped model each passive-safety mode flies by default, chosen by what is flown.

Reads the summary of a warm-start analysis (`art-guidance evaluate --split all`) that ran
every shipped model on fresh scenarios of its mode, and prints per mode, per model:

- flown: the plan the node flies (`warm_start auto`: SCVx* from CVX, and from ART where the
  post hoc check accepts the proposal or CVX does not converge; the cheaper is kept) against
  SCVx* from CVX alone: the mean saving over all scenarios [mm/s], the largest, and the
  scenarios better / worse by more than 1 mm/s;
- the warm start's quality: the suboptimality improvement of SCVx* from ART over SCVx* from
  CVX at C_CVX >= 40 and over all (ratio of sums), the infeasible-or-not-converged share at
  C_CVX >= 40 from CVX and from ART, the median total runtime (proposal + SCVx*) at C_CVX >= 30;
- the rollout metrics of the proposals (share with E_C = 0, median 100 E_R, share accepted).

The default of a mode is the model whose flown plans save the most fuel on average, among those
never worse than CVX alone by more than 1 mm/s: that is what a node flying it saves. The other
figures are reported beside it, not used: the improvement of SCVx* from ART is what a node that
always solved both would get, and the rollout metrics judge the proposal before SCVx* has
corrected it (docs/results.md, "Shipped defaults").

    python benchmarks/default_models.py --eval out/eval-2000 \
        --json benchmarks/results/default_models/choice.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:+.1f} %"


def model_row(m: dict) -> dict:
    """The comparison figures of one model's entry in an evaluation summary."""
    bins = m["bins"]
    high, all_, mid = bins.get(">=40", {}), bins[">=0"], bins.get(">=30", {})
    flown = m["auto_minus_scp_cvx_mps"]
    runtime = mid.get("runtime_ms_median", {})
    return {
        "model": m["name"], "mode": m["mode"], "n": m["n"],
        "flown_saving_mean_mmps": -1e3 * flown["mean"] if flown.get("mean") is not None
        else None,
        "flown_saving_max_mmps": -1e3 * flown["min"] if flown.get("min") is not None else None,
        "flown_better_by_1mm": flown["n_better_by_1mm"],
        "flown_worse_by_1mm": flown["n_worse_by_1mm"],
        "gain_high": high.get("improvement_ratio", {}).get("of_means"),
        "n_high": high.get("n", 0),
        "gain_all": all_["improvement_ratio"]["of_means"],
        "not_converged_high_cvx": high.get("infeasible_rate_cvx"),
        "not_converged_high_art": high.get("infeasible_rate_art"),
        "runtime_total_art_ms_c30": runtime.get("total_art"),
        "runtime_total_cvx_ms_c30": runtime.get("total_cvx"),
        "rollout_e_c_zero": m["c_art_zero"], "rollout_e_r_pct_median": m["e_r_pct_median"],
        "accepted_share": m["frac_accepted"]}


def choose(rows: list[dict]) -> dict[str, str]:
    """Mode -> the default model (most flown saving, never worse by > 1 mm/s)."""
    out = {}
    for mode in sorted({r["mode"] for r in rows}):
        ok = [r for r in rows if r["mode"] == mode and r["flown_worse_by_1mm"] == 0
              and r["flown_saving_mean_mmps"] is not None]
        if ok:
            out[mode] = max(ok, key=lambda r: r["flown_saving_mean_mmps"])["model"]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--eval", required=True, help="an `art-guidance evaluate` output directory")
    p.add_argument("--json", default=None, help="also write the rows and the choice here")
    args = p.parse_args(argv)
    summary = json.loads((Path(args.eval) / "summary.json").read_text())
    rows = [model_row(m) for m in summary["models"]]
    head = ("model", "n", "flown saving mean / max [mm/s]", "better / worse", "gain >=40 (n)",
            "gain all", "not conv. >=40 CVX -> ART", "total ms >=30 ART / CVX", "E_C = 0",
            "100 E_R", "accepted")
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        mean = "-" if r["flown_saving_mean_mmps"] is None \
            else f"{r['flown_saving_mean_mmps']:.2f}"
        print(f"| {r['model']} | {r['n']} | {mean} / "
              f"{r['flown_saving_max_mmps']:.0f} | {r['flown_better_by_1mm']} / "
              f"{r['flown_worse_by_1mm']} | {_pct(r['gain_high'])} ({r['n_high']}) | "
              f"{_pct(r['gain_all'])} | {_pct(r['not_converged_high_cvx'])[1:]} -> "
              f"{_pct(r['not_converged_high_art'])[1:]} | "
              f"{r['runtime_total_art_ms_c30'] or 0:.0f} / "
              f"{r['runtime_total_cvx_ms_c30'] or 0:.0f} | "
              f"{100 * r['rollout_e_c_zero']:.0f} % | {r['rollout_e_r_pct_median']:+.1f} % | "
              f"{100 * r['accepted_share']:.0f} % |")
    choice = choose(rows)
    for mode, name in choice.items():
        print(f"default, {mode}: {name}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"eval": args.eval, "rows": rows,
                                               "choice": choice}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
