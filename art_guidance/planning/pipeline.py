"""`GuidancePipeline.plan(request) -> PlanResult`: warm start -> post hoc check -> SCP.

The warm start comes from a `WarmStartProvider`. The convex TPBVP ("CVX") is always solved: it is
the fallback and the post hoc reference. A learned provider (ART) plugs in through the same
interface; its rollout is accepted only if the post hoc check passes.
"""
from __future__ import annotations

import time

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import GuidanceConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.errors import ConfigError, InputError
from art_guidance.optim import Scvx, solve_cvx
from art_guidance.planning.posthoc import posthoc_check
from art_guidance.planning.types import (
    PlanRequest, PlanResult, PosthocDecision, WarmStartProvider,
)
from art_guidance.safety import PassiveSafety


class GuidancePipeline:
    """Plans with CVX -> (optional learned warm start + post hoc) -> SCVx*."""

    def __init__(self, config: GuidanceConfig | None = None,
                 provider: WarmStartProvider | None = None,
                 deadline_s: float | None = None) -> None:
        """Args:
            config: the configuration bundle (default: the packaged YAML files).
            provider: a learned warm-start provider, or None (CVX only).
            deadline_s: wall-clock budget of one SCP solve [s], or None.
        """
        self.config = config or GuidanceConfig.load()
        self.scenario = self.config.scenario
        self.uncertainty = self.config.uncertainty
        self.scp_config = self.config.scp
        self.samples_per_node = self.config.planning.samples_per_node
        self.posthoc = self.config.planning.posthoc
        self.provider = provider
        self.deadline_s = deadline_s
        self._cache: dict = {}

    def config_json(self) -> dict:
        """The configuration this pipeline plans with (recorded with every run)."""
        return {**self.config.to_json(), "deadline_s": self.deadline_s,
                "config_sha256": self.config.sha256()}

    @classmethod
    def from_config_json(cls, data: dict) -> "GuidancePipeline":
        """Rebuild a pipeline from `config_json` output (for replay)."""
        try:
            return cls(GuidanceConfig.from_json(data), deadline_s=data["deadline_s"])
        except (KeyError, TypeError, ConfigError) as exc:
            raise InputError("config", f"recorded configuration is malformed: {exc!r}") from exc

    def _setup(self, request: PlanRequest) -> tuple[Horizon, PassiveSafety]:
        n_nodes = int(request.n_nodes or self.scenario.n_nodes)
        n_orbits = float(request.n_orbits or self.scenario.n_orbits)
        switch = self.scenario.ae_to_koz_node
        if request.koz_switch_node is not None:
            switch = int(min(request.koz_switch_node, n_nodes))
        key = (tuple(request.chief_oe.round(12)), n_nodes, n_orbits, switch,
               request.chance_constrained)
        if key not in self._cache:
            if len(self._cache) > 8:
                self._cache.clear()
            horizon = Horizon.build(request.chief_oe,
                                    time_grid_s(request.chief_oe[0], n_orbits, n_nodes))
            unc = self.uncertainty if request.chance_constrained else None
            self._cache[key] = (horizon, PassiveSafety(horizon, self.scenario, unc,
                                                       koz_switch_node=switch))
        return self._cache[key]

    def plan(self, request: PlanRequest) -> PlanResult:
        """Plan one transfer; never raises for solver trouble (see `PlanResult.status`)."""
        t0 = time.perf_counter()
        horizon, safety = self._setup(request)
        t_setup = time.perf_counter()
        roe_f = np.linalg.solve(horizon.psi[-1], request.target_rtn)
        cvx = solve_cvx(horizon, request.roe0_m, roe_f)
        t_cvx = time.perf_counter()
        warm, source, posthoc, t_art, art_dv = cvx.dv_rtn_mps, "cvx", None, 0.0, None
        if request.warm_start in ("auto", "art") and self.provider is not None:
            ta = time.perf_counter()
            proposal = self.provider.propose(request, horizon, cvx)
            if proposal is not None:
                try:
                    art_dv = as_finite_array("warm start", proposal, (horizon.n_nodes, 3))
                except InputError:  # a broken model output is rejected, never flown
                    posthoc = PosthocDecision(float("nan"), float("nan"), False)
                else:
                    art_roe = horizon.propagate(request.roe0_m, art_dv)
                    posthoc = posthoc_check(art_dv, art_roe, cvx.cost_mps, safety,
                                            self.posthoc)
                    if posthoc.accepted or request.warm_start == "art":
                        warm, source = art_dv, "art"
            t_art = 1e3 * (time.perf_counter() - ta)
        elif request.warm_start == "art":
            raise InputError("warm_start", "no learned warm-start model is loaded", "art")
        if not np.all(np.isfinite(warm)):
            warm = np.zeros((horizon.n_nodes, 3))
        scvx = Scvx(safety, request.roe0_m, roe_f, self.scp_config,
                    samples_per_node=self.samples_per_node)
        res = scvx.solve(warm, deadline_s=self.deadline_s)
        t_end = time.perf_counter()
        margin = float(safety.evaluate(res.roe_m, res.dv_rtn_mps).margin_m.min())
        timings = {"setup": 1e3 * (t_setup - t0), "cvx": 1e3 * (t_cvx - t_setup),
                   "art": t_art, "scp": res.solve_time_ms, "total": 1e3 * (t_end - t0)}
        return PlanResult(res.status, request.chief_oe, horizon.epochs_s, res.dv_rtn_mps,
                          res.roe_m, horizon.to_rtn(res.roe_m), res.cost_mps, res, cvx, source,
                          posthoc, margin, timings, request, art_dv)
