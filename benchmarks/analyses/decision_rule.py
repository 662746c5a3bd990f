"""Analysis: when is the second SCVx* (from the learned warm start) worth its time?

With `warm_start auto` the node solves SCVx* from CVX (the fallback) and, where the post hoc
check accepts the proposal, also from ART, and flies the cheaper plan (ART only when it is more
than `art_min_gain_mps` cheaper). The check's region thus decides whether the second solve is
made. This script asks how well that decision is made, and whether a small logistic rule fitted
on what the node knows before solving does better.

Data: the per-scenario rows of `benchmarks/analyses/sweep_candidates.py` (SCVx* from every
candidate of the sweep and from CVX; `.npz` next to its summary), of two disjoint seed sets:
the rule is fitted on one and judged on the other. The proposal is the provider's pick
(`best_candidate`, the check of the warm start). Per scenario where SCVx* from CVX converged:

- the gain of the second solve: J(SCVx* from CVX) - J(SCVx* from ART) where SCVx* from ART
  converged and is cheaper by more than `art_min_gain_mps`, else 0 [mm/s];
- the features the node has before the second solve: 100 E_R and E_C of the proposal (its
  terminal warm start), C_CVX and J_CVX (remaining nodes and margins are not in these rows:
  every scenario here is a whole 100-node transfer).

Policies, as (second solves, share of the gain of always solving both): always, never, the
region, and the rule `p(gain > 0) > t` over thresholds t (the trade-off curve). And whether the
rule could let the node solve once (SCVx* from ART alone, no CVX solve) where it is most
confident: the worst difference (ART alone - CVX) among the scenarios it would do so on.
Scenarios where SCVx* from CVX does not converge are left out: there the retry from ART is made
whatever the rule says.

    python benchmarks/analyses/decision_rule.py --fit A.npz --validate B.npz --out OUT.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from art_guidance.config import GuidanceConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep_candidates import _pick  # noqa: E402  (the provider's pick on these rows)

FEATURES = ("e_r_pct", "e_c", "log1p_c_cvx", "j_cvx_mps")
THRESHOLDS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def rows(path: str | Path) -> dict[str, np.ndarray]:
    """Features, gain [mm/s], the region's decision and ART-alone difference per scenario
    (those where SCVx* from CVX converged)."""
    d = dict(np.load(path))
    planning = GuidanceConfig().planning
    pick, inside = _pick(d["er_ws"], d["ec_ws"], d["j_cvx"], planning.posthoc)
    m = np.arange(d["j_cvx"].size)
    ok_art, ok_cvx = d["ok"][m, pick], d["ok_cvx"]
    diff = 1e3 * (d["j_scp_cvx"] - d["j_scp"][m, pick])  # > 0: ART cheaper [mm/s]
    gain = np.where(ok_art & (diff > 1e3 * planning.art_min_gain_mps), diff, 0.0)
    keep = ok_cvx
    x = np.column_stack([100.0 * d["er_ws"][m, pick], d["ec_ws"][m, pick],
                         np.log1p(d["c_cvx"]), d["j_cvx"]])
    # solving once from ART: what is flown is ART's plan (or nothing where it fails)
    alone = np.where(ok_art, diff, -np.inf)
    return {"x": x[keep], "gain": gain[keep], "inside": inside[keep], "alone": alone[keep],
            "n_all": int(m.size), "n_cvx_failed": int((~ok_cvx).sum())}


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1e-2,
                 iters: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ridge-regularised logistic regression by Newton's method on standardised features:
    (weights incl. intercept, feature means, feature scales)."""
    mu, sd = x.mean(0), x.std(0) + 1e-12
    z = np.column_stack([np.ones(len(x)), (x - mu) / sd])
    w = np.zeros(z.shape[1])
    reg = l2 * np.eye(z.shape[1])
    reg[0, 0] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-z @ w))
        grad = z.T @ (p - y) + reg @ w
        hess = (z * (p * (1 - p))[:, None]).T @ z + reg
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return w, mu, sd


def predict(model: tuple, x: np.ndarray) -> np.ndarray:
    """p(the second solve pays) of each row."""
    w, mu, sd = model
    z = np.column_stack([np.ones(len(x)), (x - mu) / sd])
    return 1.0 / (1.0 + np.exp(-z @ w))


def _point(sel: np.ndarray, gain: np.ndarray) -> dict:
    total = gain.sum()
    return {"second_solves": int(sel.sum()), "gain_mmps": float(gain[sel].sum()),
            "gain_share": float(gain[sel].sum() / total) if total > 0 else 1.0}


def evaluate(model: tuple, r: dict) -> dict:
    """The policies on one set of rows."""
    p, gain = predict(model, r["x"]), r["gain"]
    n = gain.size
    curve = {f"{t:g}": _point(p > t, gain) for t in THRESHOLDS}
    once = {}
    for t in (0.5, 0.7, 0.8, 0.9):
        sel = p > t
        once[f"{t:g}"] = {"scenarios": int(sel.sum()),
                          "worst_mmps": float(r["alone"][sel].min()) if sel.any() else None,
                          "art_failed": int(np.isinf(r["alone"][sel]).sum())}
    return {"n": n, "n_all": r["n_all"], "n_cvx_failed": r["n_cvx_failed"],
            "pays": int((gain > 0).sum()), "always": _point(np.ones(n, bool), gain),
            "region": _point(r["inside"], gain), "rule": curve, "solve_once": once}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit", required=True, help="rows (.npz) the rule is fitted on")
    ap.add_argument("--validate", required=True, help="rows (.npz) of other seeds")
    ap.add_argument("--out", help="JSON summary")
    args = ap.parse_args(argv)
    fit, val = rows(args.fit), rows(args.validate)
    model = fit_logistic(fit["x"], (fit["gain"] > 0).astype(float))
    w, mu, sd = model
    out = {"features": list(FEATURES), "weights_standardised": w.tolist(),
           "feature_mean": mu.tolist(), "feature_scale": sd.tolist(),
           "fit": {"file": Path(args.fit).name, **evaluate(model, fit)},
           "validation": {"file": Path(args.validate).name, **evaluate(model, val)}}
    text = json.dumps(out, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
