"""Benchmark: thruster faults in the closed loop, Monte Carlo in truth (`sim/contingency.py`).

Seeds x configurations (chance-constrained / deterministic passive safety, ART in the loop
"auto" / CVX only), navigation and actuation errors on, two-body + J2 truth. Every node of every
flight is a thruster loss whose one-orbit truth drift is checked densely against the ellipsoid
in force; `missed_per_seed` extra flights per seed miss one burn and must still reach the
waypoint with no post-fault drift entering. Resumable in `out`; the figures and summary.json go
there too. Reports, per configuration, entries per 1,000 losses with the exact 95 % upper bound
(the design figure is the chance constraint's 1 per 1,000 per node), the smallest margins and the
missed-burn outcomes; the throughput is losses per CPU second.

    art-guidance bench contingency --workers 2 --out out/contingency
"""
from __future__ import annotations

from art_guidance.jobs import default_workers
from art_guidance.sim.contingency import ContingencySpec, run as run_mc


def run(repeats: int | None = None, out: str = "out/contingency", workers: int | None = None,
        engine: str = "local", ray_address: str | None = None, seeds: int | None = None,
        missed_per_seed: int | None = None, horizons: str | None = None,
        targets: str | None = None) -> dict:
    """Fly (or resume) the Monte Carlo; the headline numbers per configuration.

    `repeats` and `seeds` both set the seeds per configuration (default 24: >= 2,000 losses
    per configuration). `horizons` ("20" or "10,20"): the windowed replan instead, flown
    chance-constrained with ART in the loop ("auto") beside the full-horizon replan of the
    same seeds, its windows ending at `targets` (one of art, cvx; default art)."""
    base = ContingencySpec()
    configs, target = base.configs, base.terminal_target
    if horizons:
        configs = ((True, "auto"),) + tuple((True, "auto", int(h))
                                            for h in str(horizons).split(",") if h.strip())
        target = str(targets or target)
    spec = ContingencySpec(configs=configs, terminal_target=target,
                           n_seeds=int(seeds or repeats or base.n_seeds),
                           missed_per_seed=base.missed_per_seed if missed_per_seed is None
                           else int(missed_per_seed))
    summary = run_mc(out, spec, workers=workers or default_workers(), engine=engine,
                     ray_address=ray_address)
    report = {"out": str(out), "complete": summary["complete"],
              "flights": summary["flights_done"], "cpu_s": summary["cpu_s"],
              "losses_per_cpu_s": summary["losses_per_cpu_s"]}
    report["wall_s"] = sum(r["wall_s"] for r in summary.get("runs", []))
    for c in summary["configs"]:
        loss, missed = c["losses"], c["missed"]
        key = c["config"].replace("/", "_")
        report[f"{key}_losses"] = loss["n"]
        report[f"{key}_entries"] = loss.get("entries")
        report[f"{key}_upper_95_per_1000"] = loss.get("upper_95_per_1000")
        report[f"{key}_min_margin_m"] = loss.get("min_margin_m", {}).get("min")
        report[f"{key}_missed_reached_share"] = missed.get("reached_share")
        report[f"{key}_missed_entered"] = missed.get("entered")
    return report
