"""`GuidancePipeline.plan(request) -> PlanResult`: warm start -> post hoc check -> SCP.

The warm start comes from a `WarmStartProvider`. The convex TPBVP ("CVX") is always solved: it is
the fallback and the post hoc reference. A learned provider (ART) plugs in through the same
interface; its rollout is accepted only if the post hoc check passes.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig, ScpConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, check_oe, time_grid_s
from art_guidance.errors import InputError
from art_guidance.optim import ConvexSolution, ScpResult, ScpStatus, Scvx, solve_cvx
from art_guidance.safety import PassiveSafety

WARM_STARTS = ("auto", "cvx", "art")


@dataclass(frozen=True)
class PlanRequest:
    """What to plan.

    Attributes:
        chief_oe: (6,) chief mean elements at t0 (a [m], e, i, raan, argp, M [rad]).
        roe0_m: (6,) initial a-scaled ROE [m].
        target_rtn: (6,) terminal RTN state after the last burn [m, m/s].
        chance_constrained: False plans deterministic passive safety (covariance zero).
        warm_start: "auto" (ART if available and accepted, else CVX), "cvx" or "art".
        n_nodes, n_orbits: horizon; None uses the scenario's.
        koz_switch_node: node index where the approach ellipsoid switches to the keep-out zone;
            None uses the scenario's (a replan over the remaining horizon shifts it).
    """

    chief_oe: np.ndarray
    roe0_m: np.ndarray
    target_rtn: np.ndarray
    chance_constrained: bool = True
    warm_start: str = "auto"
    n_nodes: int | None = None
    n_orbits: float | None = None
    koz_switch_node: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "chief_oe", check_oe(self.chief_oe))
        object.__setattr__(self, "roe0_m", as_finite_array("roe0_m", self.roe0_m, (6,)))
        object.__setattr__(self, "target_rtn",
                           as_finite_array("target_rtn", self.target_rtn, (6,)))
        if self.warm_start not in WARM_STARTS:
            raise InputError("warm_start", f"must be one of {WARM_STARTS}", self.warm_start)
        if self.n_nodes is not None and not 3 <= int(self.n_nodes) <= 1000:
            raise InputError("n_nodes", "must be in [3, 1000]", self.n_nodes)
        if self.n_orbits is not None and not 0.01 <= float(self.n_orbits) <= 20:
            raise InputError("n_orbits", "must be in [0.01, 20] orbits", self.n_orbits)
        if self.koz_switch_node is not None and int(self.koz_switch_node) < 0:
            raise InputError("koz_switch_node", "must be >= 0", self.koz_switch_node)

    def to_json(self) -> dict:
        """Everything needed to solve this request again (see `from_json`)."""
        return {"chief_oe": self.chief_oe.tolist(), "roe0_m": self.roe0_m.tolist(),
                "target_rtn": self.target_rtn.tolist(),
                "chance_constrained": bool(self.chance_constrained),
                "warm_start": self.warm_start, "n_nodes": self.n_nodes,
                "n_orbits": self.n_orbits, "koz_switch_node": self.koz_switch_node}

    @classmethod
    def from_json(cls, data: dict) -> "PlanRequest":
        """Inverse of `to_json` (validated again)."""
        try:
            return cls(np.asarray(data["chief_oe"]), np.asarray(data["roe0_m"]),
                       np.asarray(data["target_rtn"]), bool(data["chance_constrained"]),
                       data["warm_start"], data.get("n_nodes"), data.get("n_orbits"),
                       data.get("koz_switch_node"))
        except (KeyError, TypeError) as exc:
            raise InputError("request_json", f"malformed: {exc!r}") from exc


@dataclass(frozen=True)
class PosthocDecision:
    """Post hoc check of a learned warm start (paper: E_R, E_C)."""

    e_r: float
    e_c: float
    accepted: bool


@dataclass(frozen=True)
class PosthocThresholds:
    """Acceptance region of the post hoc check (paper: -1.5 <= 100 E_R <= 3.5, 0 <= E_C <= 2)."""

    e_r_pct_min: float = -1.5
    e_r_pct_max: float = 3.5
    e_c_min: float = 0.0
    e_c_max: float = 2.0

    def __post_init__(self) -> None:
        if not (self.e_r_pct_min <= self.e_r_pct_max and self.e_c_min <= self.e_c_max):
            raise InputError("posthoc", "thresholds need min <= max", self)


def posthoc_check(dv_rtn_mps: np.ndarray, roe_m: np.ndarray, cvx_cost_mps: float,
                  safety: PassiveSafety, thresholds: PosthocThresholds) -> PosthocDecision:
    """Compare a rollout's realised performance with the desired one (paper eq. for E_P).

    The desired reward-to-go is the CVX lower bound (R_des = -J_CVX) and the desired
    constraint-violation budget is zero, so E_R = (R - R_des) / R_des and E_C = C(t1).

    Args:
        dv_rtn_mps: (N, 3) rollout controls [m/s].
        roe_m: (N, 6) rollout states [m] (dynamics in the loop).
        cvx_cost_mps: J_CVX [m/s].
        safety: the plan's passive-safety model (gives C(t1)).
        thresholds: acceptance region.
    """
    r_des = -float(cvx_cost_mps)
    r_art = -float(np.linalg.norm(dv_rtn_mps, axis=1).sum())
    e_r = (r_art - r_des) / r_des if abs(r_des) > 1e-12 else float("inf")
    e_c = float(safety.evaluate(roe_m, dv_rtn_mps).constraint_to_go[0])
    t = thresholds
    accepted = bool(t.e_r_pct_min <= 100.0 * e_r <= t.e_r_pct_max
                    and t.e_c_min <= e_c <= t.e_c_max)
    return PosthocDecision(float(e_r), e_c, accepted)


@dataclass(frozen=True)
class PlanResult:
    """A plan and everything needed to publish, record and replay it."""

    status: ScpStatus
    chief_oe: np.ndarray
    epochs_s: np.ndarray     # (N,) [s] from t0
    dv_rtn_mps: np.ndarray   # (N, 3)
    roe_m: np.ndarray        # (N, 6) pre-burn
    rtn: np.ndarray          # (N, 6) [m, m/s]
    cost_mps: float
    scp: ScpResult
    cvx: ConvexSolution
    warm_start: str          # "art" or "cvx"
    posthoc: PosthocDecision | None
    constraint_margin_m: float
    timings_ms: dict = field(default_factory=dict)
    request: PlanRequest | None = None
    art_dv_rtn_mps: np.ndarray | None = None  # (N, 3) learned warm start, if one was proposed

    def to_json(self) -> dict:
        """The plan as JSON-ready data (units in the names)."""
        ph = self.posthoc
        return {
            "chief_oe": self.chief_oe.tolist(),
            "epochs_s": self.epochs_s.tolist(),
            "dv_rtn_mps": self.dv_rtn_mps.tolist(),
            "roe_m": self.roe_m.tolist(),
            "rtn": self.rtn.tolist(),
            "cost_mps": self.cost_mps,
            "cvx_cost_mps": self.cvx.cost_mps,
            "status": self.status.name,
            "scp_iterations": self.scp.iterations,
            "warm_start": self.warm_start,
            "posthoc": None if ph is None else {"E_R": ph.e_r, "E_C": ph.e_c,
                                                "accepted": ph.accepted},
            "timings_ms": dict(self.timings_ms),
            "constraint_margin_m": self.constraint_margin_m,
        }


class WarmStartProvider(Protocol):
    """Proposes warm-start controls (N, 3) [m/s] for a request, or None (e.g. out of domain).

    The pipeline rolls them out through its own dynamics and applies the post hoc check.
    """

    def propose(self, request: PlanRequest, horizon: Horizon,
                cvx: ConvexSolution) -> np.ndarray | None:
        ...


class GuidancePipeline:
    """Plans with CVX -> (optional learned warm start + post hoc) -> SCVx*."""

    def __init__(self, scenario: ScenarioConfig | None = None,
                 uncertainty: UncertaintyConfig | None = None, scp: ScpConfig | None = None,
                 provider: WarmStartProvider | None = None, samples_per_node: int = 3,
                 deadline_s: float | None = None,
                 posthoc: PosthocThresholds | None = None) -> None:
        self.scenario = scenario or ScenarioConfig.from_yaml()
        self.uncertainty = uncertainty or UncertaintyConfig.from_yaml()
        self.scp_config = scp or ScpConfig.from_yaml()
        self.provider = provider
        self.samples_per_node = samples_per_node
        self.deadline_s = deadline_s
        self.posthoc = posthoc or PosthocThresholds()
        self._cache: dict = {}

    def config_json(self) -> dict:
        """The configuration this pipeline plans with (recorded with every run)."""
        from dataclasses import asdict

        return {"scenario": asdict(self.scenario), "uncertainty": asdict(self.uncertainty),
                "scp": asdict(self.scp_config), "samples_per_node": self.samples_per_node,
                "deadline_s": self.deadline_s, "posthoc": asdict(self.posthoc)}

    @classmethod
    def from_config_json(cls, data: dict) -> "GuidancePipeline":
        """Rebuild a pipeline from `config_json` output (for replay)."""
        try:
            return cls(ScenarioConfig(**data["scenario"]),
                       UncertaintyConfig(**data["uncertainty"]), ScpConfig(**data["scp"]),
                       samples_per_node=data["samples_per_node"],
                       deadline_s=data["deadline_s"],
                       posthoc=PosthocThresholds(**data.get("posthoc", {})))
        except (KeyError, TypeError) as exc:
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
            scenario = self.scenario.replace(n_nodes=max(n_nodes, self.scenario.n_nodes),
                                             ae_to_koz_node=switch)
            self._cache[key] = (horizon, PassiveSafety(horizon, scenario, unc))
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
