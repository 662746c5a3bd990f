"""Held-out scenarios of the shipped models' datasets, as plan requests."""
from __future__ import annotations

import numpy as np

from art_guidance.art.provider import DEFAULT_MODEL, shipped_models
from art_guidance.config import ScenarioConfig
from art_guidance.scenarios import sample_scenario, sample_seed
from art_guidance.data.storage import train_test_split
from art_guidance.dynamics import roe_from_rtn_linear
from art_guidance.planning import PlanRequest


def heldout_requests(n: int, name: str = DEFAULT_MODEL) -> list[PlanRequest]:
    """The first n held-out scenarios of the dataset the shipped model `name` was trained on,
    as requests of its mode (a model trained on several datasets: their test splits in the
    order models.json lists them under "parts")."""
    data = shipped_models()[name]["dataset"]
    scenario = ScenarioConfig.from_yaml()
    chief = np.array(scenario.chief_oe)
    parts = data.get("parts") or [{"base_seed": data.get("base_seed", 0), "n": data["n"]}]
    out = []
    for part in parts:
        base = int(part["base_seed"])
        _, test = train_test_split(base, int(part["n"]))
        for index in test[:n - len(out)]:
            s = sample_scenario(scenario, sample_seed(base, int(index)))
            out.append(PlanRequest(chief, roe_from_rtn_linear(chief, s.rtn0), s.target_rtn,
                                   chance_constrained=data["mode"] == "chance"))
    return out


def runtimes_agree(torch_provider, onnx_provider, requests: list[PlanRequest],
                   dv_tol_mps: float) -> int:
    """Assert that the learned step (sweep, C update, judging, post hoc check) of the same model
    on torch and on ONNX Runtime makes the same decision, the same constraint-to-go and
    controls within `dv_tol_mps` [m/s] on every request whose CVX problem is feasible; returns
    how many were compared."""
    from art_guidance.config import GuidanceConfig
    from art_guidance.planning import GuidancePipeline
    from art_guidance.planning.learned import CvxSafety, learned_warm_start

    config = GuidanceConfig.load()
    pipeline = GuidancePipeline(config)
    compared = 0
    for request in requests:
        transfer = pipeline.transfer(request)
        cvx = transfer.problem.cvx()
        if not cvx.status.feasible:
            continue
        asked = CvxSafety.answered(False)  # both asked, whatever CVX's safety
        a = learned_warm_start(torch_provider, transfer, cvx, config.planning, cvx_safe=asked)
        b = learned_warm_start(onnx_provider, transfer, cvx, config.planning, cvx_safe=asked)
        assert a.source is b.source and a.posthoc.accepted == b.posthoc.accepted
        assert np.array_equal(a.proposal.constraint_to_go, b.proposal.constraint_to_go)
        assert np.abs(a.proposal.dv_rtn_mps - b.proposal.dv_rtn_mps).max() <= dv_tol_mps
        compared += 1
    return compared
