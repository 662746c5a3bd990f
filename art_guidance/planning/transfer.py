"""One transfer problem for every stage of a plan: the request and its
`optim.TransferProblem` (horizon, passive-safety model, boundary conditions).

CVX, the learned proposal, the post hoc check and SCVx* all solve the problem of the
`Transfer` that `Transfers.get` builds for a request; the horizon and the passive-safety
model are cached (their set-up costs milliseconds and a replan over the same chief and window
needs the same ones), so the pipeline and the proposal worker process, each with its own
`Transfers`, build the same problem from the same request.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from art_guidance.config import GuidanceConfig, ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import Horizon, time_grid_s
from art_guidance.optim import Scvx, TransferProblem
from art_guidance.optim.problem import SubproblemOptions, SubproblemPool
from art_guidance.planning.request import PlanRequest
from art_guidance.safety import PassiveSafety

CACHE_SIZE = 8  # transfers kept; the cache is emptied when it holds more


@dataclass(frozen=True)
class Transfer:
    """The problem of one plan.

    Attributes:
        request: what is planned.
        problem: its transfer problem: the passive-safety model (deterministic or
            chance-constrained) on the request's horizon, from the request's state to its
            RTN target mapped through the horizon's last Psi.
    """

    request: PlanRequest
    problem: TransferProblem

    @property
    def horizon(self) -> Horizon:
        """The time grid, dynamics and frames."""
        return self.problem.horizon

    @property
    def safety(self) -> PassiveSafety:
        """The passive-safety model."""
        return self.problem.safety

    @property
    def roe_f_m(self) -> np.ndarray:
        """(6,) terminal post-burn a-scaled ROE [m]."""
        return self.problem.roe_f_m

    def scvx(self, config: GuidanceConfig, subproblem: SubproblemOptions,
             pool: SubproblemPool | None = None) -> Scvx:
        """SCVx* on this transfer with the options of `config` (its SCP settings and samples
        per node) and `subproblem`: the planner's, built alike by the pipeline and by its
        proposal worker (`pool`: the caller's subproblems)."""
        return self.problem.scvx(config.scp, config.planning.samples_per_node, subproblem,
                                 pool)


class Transfers:
    """Builds the `Transfer` of a request under a scenario and an uncertainty model, keeping
    the last few horizons and passive-safety models."""

    def __init__(self, scenario: ScenarioConfig, uncertainty: UncertaintyConfig) -> None:
        self.scenario = scenario
        self.uncertainty = uncertainty
        self._cache: dict[tuple, tuple[Horizon, PassiveSafety]] = {}

    def get(self, request: PlanRequest) -> Transfer:
        """The transfer problem of `request` (its horizon and safety model cached)."""
        _, safety = self._models(request)
        return Transfer(request, TransferProblem.to_target(safety, request.roe0_m,
                                                           request.target_rtn,
                                                           request.terminal_set))

    def in_roe(self, request: PlanRequest, roe_f_m: np.ndarray) -> Transfer:
        """The transfer of `request` to the post-burn state `roe_f_m` [m] given in ROE (a
        window's: no RTN round trip); the request returned carries that state's RTN image as
        its target, for the record."""
        _, safety = self._models(request)
        roe_f_m = np.asarray(roe_f_m, dtype=float)
        target_rtn = safety.horizon.psi[-1] @ roe_f_m
        return Transfer(dataclasses.replace(request, target_rtn=target_rtn),
                        TransferProblem(safety, request.roe0_m, roe_f_m, target_rtn))

    def _models(self, request: PlanRequest) -> tuple[Horizon, PassiveSafety]:
        n_nodes = int(request.n_nodes or self.scenario.n_nodes)
        n_orbits = float(request.n_orbits or self.scenario.n_orbits)
        switch = self.scenario.ae_to_koz_node
        if request.koz_switch_node is not None:
            switch = int(min(request.koz_switch_node, n_nodes))
        # the exact elements (rounding a huge finite angle overflowed: 1e300 and 2e300 met)
        key = (tuple(request.chief_oe.tolist()), n_nodes, n_orbits, switch,
               request.chance_constrained)
        if key not in self._cache:
            if len(self._cache) > CACHE_SIZE:
                self._cache.clear()
            horizon = Horizon.build(request.chief_oe,
                                    time_grid_s(request.chief_oe[0], n_orbits, n_nodes))
            unc = self.uncertainty if request.chance_constrained else None
            self._cache[key] = (horizon, PassiveSafety(horizon, self.scenario, unc,
                                                       koz_switch_node=switch))
        return self._cache[key]
