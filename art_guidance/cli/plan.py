"""`art-guidance plan`: one randomised transfer as JSON."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from art_guidance.errors import InputError
from art_guidance.files import write_json_atomic


def run(args: argparse.Namespace) -> int:
    """Plan one randomised transfer of the paper scenario and write it as JSON."""
    from art_guidance.config import GuidanceConfig, ScenarioConfig, mode_name
    from art_guidance.scenarios import sample_scenario
    from art_guidance import kernels
    from art_guidance.planning import GuidancePipeline
    from art_guidance.planning.warm_up import seed_request

    scenario = ScenarioConfig.from_yaml(args.scenario)
    sample = sample_scenario(scenario, args.seed)
    target = None
    if args.waypoint:
        if args.waypoint not in scenario.waypoints_rtn:
            raise InputError("waypoint", f"unknown; choose from {sorted(scenario.waypoints_rtn)}",
                             args.waypoint)
        target = np.asarray(scenario.waypoints_rtn[args.waypoint])
    request = seed_request(scenario, args.seed, chance_constrained=not args.deterministic,
                           warm_start=args.warm_start, target_rtn=target)
    provider, model_text = _provider(args)
    pipeline = GuidancePipeline(GuidanceConfig.load().replace(scenario=scenario),
                                provider=provider)
    warm_up_ms = pipeline.warm_up()  # the process's one-time costs, before the timed solve
    result = pipeline.plan(request)
    data = result.to_json()
    data["timings_ms"] = {**data["timings_ms"], "warm_up": warm_up_ms}
    data["numerics"] = kernels.status()
    data.update(seed=args.seed, waypoint=args.waypoint or sample.waypoint,
                mode=mode_name(not args.deterministic), model=model_text,
                model_sha256=getattr(provider, "sha256", None),
                art_runtime=getattr(provider, "runtime", None),
                art_runtime_sha256=getattr(provider, "runtime_sha256", None))
    write_json_atomic(args.json, data)
    t = result.timings
    print(f"warm starts: CVX {result.cvx.cost_mps:.4f} m/s"
          + (f", ART {data['art_cost_mps']:.4f} m/s" if data["art_cost_mps"] is not None
             else "") + f" -> {result.warm_start.label}: {result.warm_start_reason}")
    print(f"{result.status.name}: cost {result.cost_mps:.4f} m/s, {result.scp.iterations} SCP "
          f"iterations, margin {result.constraint_margin_m:.2f} m, {t.total:.0f} ms "
          f"(CVX {t.cvx:.0f}, ART {t.art:.0f}, SCP {t.scp:.0f}) -> {args.json}")
    print(f"warm-up {warm_up_ms:.0f} ms before the solve (kernels loaded, one throwaway plan: "
          "the model runtime's first inference, the solver's set-up): one-time costs, not in "
          f"the solve's times; numerics: {data['numerics']}")
    return 0 if result.scp.feasible else 1


def _provider(args: argparse.Namespace) -> tuple[object | None, str]:
    """The learned warm start for --warm-start auto/art (torch is imported only then).

    auto with a model that does not load plans from CVX with a warning; art refuses.
    """
    if args.warm_start == "cvx":
        return None, "not loaded (--warm-start cvx)"
    from art_guidance.art.provider import ArtWarmStart, resolve_model_path
    from art_guidance.errors import GuidanceError

    path = resolve_model_path(args.model, chance_constrained=not args.deterministic)
    if path is None:
        if args.warm_start == "art":
            raise InputError("model", "--warm-start art needs a model", args.model)
        return None, "none (--model none)"
    try:
        provider = ArtWarmStart.load(path, runtime=args.art_runtime)
    except GuidanceError as exc:
        if args.warm_start == "art":
            raise
        print(f"warning: learned warm start unavailable, planning from CVX only: {exc}",
              file=sys.stderr)
        return None, f"failed to load: {exc}"
    return provider, provider.describe()


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("plan", help="plan one transfer and write JSON",
                       description=run.__doc__ + " The process's one-time costs (the "
                       "kernels loaded from their cache, or compiled in the background on a cold "
                       "one; the model runtime's first inference and the solver's set-up, by "
                       "one throwaway plan) are paid by a warm-up before the solve and "
                       "reported apart as timings_ms.warm_up: every other timing is the "
                       "solve's own. Exit 0 feasible, 1 infeasible, 2 bad input.")
    p.add_argument("--seed", type=int, required=True, help="scenario seed (initial state and "
                   "waypoint drawn from the paper's Table I ranges)")
    p.add_argument("--deterministic", action="store_true",
                   help="deterministic passive safety (default: chance-constrained)")
    p.add_argument("--warm-start", choices=["auto", "cvx", "art"], default="auto",
                   help="warm start for SCP: auto = ART if its rollout passes the post hoc "
                   "check, else CVX; art = ART even if the check fails; cvx = CVX (no model "
                   "loaded)")
    p.add_argument("--model", default="", help="ART checkpoint or exported .onnx file ('' = the "
                   "shipped default of the mode: chance-constrained or, with --deterministic, "
                   "deterministic; 'none' = no model)")
    p.add_argument("--art-runtime", default="auto", choices=["auto", "torch", "onnx"],
                   help="what runs the model: torch (the checkpoint), onnx (its exported .onnx "
                   "file beside it, on ONNX Runtime, no torch needed) or auto (onnx where ONNX "
                   "Runtime and the exported file are there, else torch)")
    p.add_argument("--waypoint", default=None, help="override the sampled waypoint")
    p.add_argument("--scenario", default=None, help="scenario YAML (default: packaged)")
    p.add_argument("--json", required=True, help="output path of the plan JSON")
    p.set_defaults(func=run)
