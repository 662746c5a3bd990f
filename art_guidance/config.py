"""Configuration as validated frozen dataclasses, loaded once from the YAML files in `config/`."""
from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from art_guidance.errors import ConfigError
from art_guidance.files import load_yaml

# The passive-safety modes as datasets, models, logs and reports name them (the planner and the
# ROS interface carry the same choice as the bool `chance_constrained`).
MODES = ("deterministic", "chance")


def mode_name(chance_constrained: bool) -> str:
    """"chance" or "deterministic" for a `chance_constrained` flag."""
    return MODES[1] if chance_constrained else MODES[0]


WAYPOINT_NAMES = ("plus_vbar", "minus_vbar", "plus_rbar", "minus_rbar")


def default_config_dir() -> Path:
    """Directory of scenario.yaml etc.: $ART_GUIDANCE_CONFIG_DIR, the source tree, or share/."""
    env = os.environ.get("ART_GUIDANCE_CONFIG_DIR")
    candidates = [Path(env)] if env else []
    here = Path(__file__).resolve()
    candidates.append(here.parent.parent / "config")  # source tree / editable install
    if len(here.parents) > 4:  # <prefix>/lib/pythonX.Y/site-packages/art_guidance/config.py
        candidates.append(here.parents[4] / "share" / "art_guidance" / "config")
    candidates.append(Path(sys.prefix) / "share" / "art_guidance" / "config")
    for cand in candidates:
        if (cand / "scenario.yaml").is_file():
            return cand
    raise ConfigError(f"no config directory found among {[str(c) for c in candidates]}")


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a positive finite number, got {value!r}")


def _vector(name: str, value: Any, size: int) -> tuple[float, ...]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.size != size or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be {size} finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class ScenarioConfig:
    """Rendezvous scenario (paper Table I). Angles in radians, lengths in metres."""

    chief_oe: tuple[float, ...] = (6738e3, 5.58e-4, math.radians(51.64), math.radians(301.04),
                                   math.radians(26.18), math.radians(68.23))
    n_orbits: float = 1.29
    n_nodes: int = 100
    t_safety_orbits: float = 1.0
    n_safety: int = 20
    ae_semi_axes_m: tuple[float, ...] = (1000.0, 1000.0, 1000.0)
    koz_semi_axes_m: tuple[float, ...] = (200.0, 200.0, 200.0)
    ae_to_koz_node: int = 55
    rtn0_nominal: tuple[float, ...] = (-4000.0, -17500.0, 0.0, 0.0, 6.849, 0.0)
    rtn0_half_width: tuple[float, ...] = (1400.0, 3000.0, 0.0, 0.0, 1.0, 0.0)
    waypoints_rtn: Mapping[str, tuple[float, ...]] = field(default_factory=lambda: {
        "plus_vbar": (0.0, 750.0, 0.0, 0.0, 0.0, 0.0),
        "minus_vbar": (0.0, -750.0, 0.0, 0.0, 0.0, 0.0),
        "plus_rbar": (750.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        "minus_rbar": (-750.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    })

    def __post_init__(self) -> None:
        object.__setattr__(self, "chief_oe", _vector("chief_oe", self.chief_oe, 6))
        _positive("chief a_m", self.chief_oe[0])
        if not 0.0 <= self.chief_oe[1] < 1.0:
            raise ConfigError(f"chief eccentricity must be in [0, 1), got {self.chief_oe[1]}")
        _positive("n_orbits", self.n_orbits)
        if not (math.isfinite(self.t_safety_orbits) and self.t_safety_orbits >= 0):
            raise ConfigError(f"t_safety_orbits must be >= 0, got {self.t_safety_orbits}")
        if int(self.n_nodes) != self.n_nodes or self.n_nodes < 3:
            raise ConfigError(f"n_nodes must be an integer >= 3, got {self.n_nodes}")
        if int(self.n_safety) != self.n_safety or self.n_safety < 1:
            raise ConfigError(f"n_safety must be an integer >= 1, got {self.n_safety}")
        if not 0 <= self.ae_to_koz_node <= self.n_nodes:
            raise ConfigError(f"ae_to_koz_node must be in [0, n_nodes], got {self.ae_to_koz_node}")
        for name in ("ae_semi_axes_m", "koz_semi_axes_m"):
            vec = _vector(name, getattr(self, name), 3)
            for v in vec:
                _positive(name, v)
            object.__setattr__(self, name, vec)
        for name in ("rtn0_nominal", "rtn0_half_width"):
            object.__setattr__(self, name, _vector(name, getattr(self, name), 6))
        wps = {k: _vector(f"waypoint {k}", v, 6) for k, v in dict(self.waypoints_rtn).items()}
        if not wps:
            raise ConfigError("at least one waypoint is required")
        object.__setattr__(self, "waypoints_rtn", wps)

    @classmethod
    def from_yaml(cls, path: str | Path | None = None) -> "ScenarioConfig":
        """Load `scenario.yaml` (default: the packaged one)."""
        data = _load_yaml(path or default_config_dir() / "scenario.yaml")
        try:
            orb = data["chief_orbit"]
            return cls(
                chief_oe=(orb["a_m"], orb["e"], math.radians(orb["i_deg"]),
                          math.radians(orb["raan_deg"]), math.radians(orb["argp_deg"]),
                          math.radians(orb["mean_anomaly_deg"])),
                n_orbits=data["horizon"]["n_orbits"], n_nodes=data["horizon"]["n_nodes"],
                t_safety_orbits=data["safety"]["t_safety_orbits"],
                n_safety=data["safety"]["n_safety"],
                ae_semi_axes_m=data["safety"]["ae_semi_axes_m"],
                koz_semi_axes_m=data["safety"]["koz_semi_axes_m"],
                ae_to_koz_node=data["safety"]["ae_to_koz_node"],
                rtn0_nominal=data["initial_state"]["rtn_nominal"],
                rtn0_half_width=data["initial_state"]["rtn_half_width"],
                waypoints_rtn=data["waypoints_rtn"],
            )
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"scenario config is missing or malformed: {exc!r}") from exc

    def replace(self, **changes: Any) -> "ScenarioConfig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class UncertaintyConfig:
    """Uncertainty model (paper Table II)."""

    sigma_s: float = 2e-3
    sigma_p: float = 3e-4
    sigma_r: float = 3e-4
    sigma_a: float = 3e-4
    nav_s1: tuple[float, ...] = (4e-5, 4e-3, 4e-5, 2e-5, 2e-5, 4e-5)
    nav_s2: tuple[float, ...] = (1e-4, 4e-3, 4e-5, 2e-3, 2e-3, 2e-3)
    nav_rho1_m: float = 10000.0
    nav_rho2_m: float = 1000.0
    process_noise_m2: float = 1e-6
    q_sigma: float = 3.09

    def __post_init__(self) -> None:
        for name in ("sigma_s", "sigma_p", "sigma_r", "sigma_a", "process_noise_m2", "q_sigma"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ConfigError(f"{name} must be finite and >= 0, got {val!r}")
        for name in ("nav_s1", "nav_s2"):
            vec = _vector(name, getattr(self, name), 6)
            if min(vec) < 0:
                raise ConfigError(f"{name} must be >= 0, got {vec}")
            object.__setattr__(self, name, vec)
        if not 0 < self.nav_rho2_m < self.nav_rho1_m:
            raise ConfigError("navigation ranges need 0 < rho2_m < rho1_m")

    @classmethod
    def from_yaml(cls, path: str | Path | None = None) -> "UncertaintyConfig":
        """Load `uncertainty.yaml` (default: the packaged one)."""
        data = _load_yaml(path or default_config_dir() / "uncertainty.yaml")
        try:
            g, nav = data["gates"], data["navigation"]
            return cls(sigma_s=g["sigma_s"], sigma_p=g["sigma_p"], sigma_r=g["sigma_r"],
                       sigma_a=g["sigma_a"], nav_s1=nav["s1"], nav_s2=nav["s2"],
                       nav_rho1_m=nav["rho1_m"], nav_rho2_m=nav["rho2_m"],
                       process_noise_m2=data["process_noise_m2"], q_sigma=data["q_sigma"])
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"uncertainty config is missing or malformed: {exc!r}") from exc


@dataclass(frozen=True)
class ScpConfig:
    """SCVx* parameters (paper Table I; Oguri 2023)."""

    eps_opt: float = 1e-3
    eps_feas: float = 1e-3
    alpha1: float = 2.0
    alpha2: float = 3.0
    beta: float = 2.0
    gamma: float = 0.9
    rho0: float = 0.0
    rho1: float = 0.25
    rho2: float = 0.7
    trust_radius_min: float = 1e-6
    trust_radius_max: float = 5e3
    trust_radius0: float = 100.0
    w0: float = 10.0
    w_max: float = 1e8
    max_iterations: int = 20
    tightening: float = 1e-2

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            val = getattr(self, f.name)
            if not (isinstance(val, (int, float)) and math.isfinite(val)):
                raise ConfigError(f"scp.{f.name} must be a finite number, got {val!r}")
        if not (self.alpha1 > 1 and self.alpha2 > 1 and self.beta > 1 and 0 < self.gamma < 1):
            raise ConfigError("scp needs alpha1, alpha2, beta > 1 and 0 < gamma < 1")
        if not 0 <= self.rho0 < self.rho1 < self.rho2 < 1:
            raise ConfigError("scp needs 0 <= rho0 < rho1 < rho2 < 1")
        if not 0 < self.trust_radius_min <= self.trust_radius0 <= self.trust_radius_max:
            raise ConfigError("scp needs 0 < r_min <= r0 <= r_max")
        if self.max_iterations < 1:
            raise ConfigError("scp.max_iterations must be >= 1")
        if not 0 <= self.tightening < 0.5:
            raise ConfigError("scp.tightening must be in [0, 0.5)")

    @classmethod
    def from_yaml(cls, path: str | Path | None = None) -> "ScpConfig":
        """Load `scp.yaml` (default: the packaged one)."""
        return _from_mapping(cls, _load_yaml(path or default_config_dir() / "scp.yaml"), "scp")


def _load_yaml(path: str | Path) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            data = load_yaml(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read config {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"config {path} must hold a mapping")
    return data


@dataclass(frozen=True)
class PosthocThresholds:
    """Acceptance region of the post hoc check (paper: -1.5 <= 100 E_R <= 3.5, 0 <= E_C <= 2)."""

    e_r_pct_min: float = -1.5
    e_r_pct_max: float = 3.5
    e_c_min: float = 0.0
    e_c_max: float = 2.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            val = getattr(self, f.name)
            if not (isinstance(val, (int, float)) and math.isfinite(val)):
                raise ConfigError(f"posthoc.{f.name} must be a finite number, got {val!r}")
        if not (self.e_r_pct_min <= self.e_r_pct_max and self.e_c_min <= self.e_c_max):
            raise ConfigError(f"posthoc thresholds need min <= max, got {self}")

    def contains(self, e_r_pct: Any, e_c: Any) -> Any:
        """Whether (100 E_R, E_C) lies in the region; scalars or arrays (elementwise)."""
        return ((self.e_r_pct_min <= e_r_pct) & (e_r_pct <= self.e_r_pct_max)
                & (self.e_c_min <= e_c) & (e_c <= self.e_c_max))


# What the post hoc check judges: "warm_start", the rollout's controls corrected onto the
# terminal condition (`optim.terminal_warm_start`, what SCVx* starts from), or "rollout", the
# rollout as the model produced it (the paper's check; the rollout misses the target).
POSTHOC_SUBJECTS = ("warm_start", "rollout")


class ReplanWarmStart(enum.StrEnum):
    """`replan_warm_start`: a replan with a plan in force starts from it (CARRY,
    `planning.carry`) or solves afresh (FRESH); a string that equals its value."""

    CARRY = "carry"
    FRESH = "fresh"


REPLAN_WARM_STARTS = tuple(r.value for r in ReplanWarmStart)
NUMERICS = ("compiled", "numpy")  # `art_guidance.kernels`: numba kernels or their numpy oracles
# the end-game policy (`planning.endgame`): every replan put in force as before, or a replan
# the deviation triggers made only when the error matters (and, keep_cap, capped in cost)
ENDGAMES = ("none", "keep", "keep_cap")


@dataclass(frozen=True)
class PlanningConfig:
    """Planning choices of the pipeline (`planning.yaml`)."""

    samples_per_node: int = 3
    posthoc: PosthocThresholds = field(default_factory=PosthocThresholds)
    art_deadline_share: float = 0.6
    also_solve_from_cvx: bool = True
    also_solve_from_art: bool = False
    first_plan_from_both: bool = True
    posthoc_subject: str = "warm_start"
    art_min_gain_mps: float = 0.001
    skip_art_when_cvx_safe: bool = True
    propose_concurrently: bool = False
    numerics: str = "compiled"
    replan_warm_start: ReplanWarmStart = ReplanWarmStart.CARRY
    carry_guard_mps: float = 0.05
    endgame: str = "keep_cap"
    terminal_tolerance_m: float = 10.0
    terminal_tolerance_mps: float = 0.02
    terminal_tolerance_sigma: float = 0.0
    tolerance_growth_nodes: int = 10
    aim_within_tolerance: bool = False
    endgame_cost_cap_mps: float = 0.05
    endgame_cost_per_m: float = 0.01
    terminal_set_nodes: int = 10
    terminal_set_share: float = 0.5

    def __post_init__(self) -> None:
        for name, choices in (("endgame", ENDGAMES), ("replan_warm_start", REPLAN_WARM_STARTS),
                              ("numerics", NUMERICS), ("posthoc_subject", POSTHOC_SUBJECTS)):
            if getattr(self, name) not in choices:
                raise ConfigError(f"{name} must be one of {choices}, got "
                                  f"{getattr(self, name)!r}")
        object.__setattr__(self, "replan_warm_start", ReplanWarmStart(self.replan_warm_start))
        for name, least in (("tolerance_growth_nodes", 0), ("terminal_set_nodes", 0),
                            ("samples_per_node", 1)):
            g = getattr(self, name)
            if isinstance(g, bool) or not isinstance(g, int) or g < least:
                raise ConfigError(f"{name} must be an integer >= {least}, got {g!r}")
        for name in ("also_solve_from_cvx", "also_solve_from_art", "propose_concurrently",
                     "skip_art_when_cvx_safe", "aim_within_tolerance", "first_plan_from_both"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got "
                                  f"{getattr(self, name)!r}")
        for name in ("art_min_gain_mps", "carry_guard_mps", "terminal_tolerance_m",
                     "terminal_tolerance_mps", "terminal_tolerance_sigma",
                     "endgame_cost_cap_mps", "endgame_cost_per_m"):
            gain = getattr(self, name)
            unit = ("m/s per m" if name.endswith("_per_m") else "m" if name.endswith("_m")
                    else "sigma" if name.endswith("_sigma") else "m/s")
            if isinstance(gain, bool) or not isinstance(gain, (int, float)) \
                    or not 0.0 <= gain < float("inf"):
                raise ConfigError(f"{name} must be a finite number >= 0 [{unit}], got {gain!r}")
        for name, shut in (("terminal_set_share", True), ("art_deadline_share", False)):
            share = getattr(self, name)
            if isinstance(share, bool) or not isinstance(share, (int, float)) \
                    or not (0.0 < share < 1.0 or (shut and share == 1.0)):
                raise ConfigError(f"{name} must be in (0, 1{']' if shut else ')'}, got "
                                  f"{share!r}")
        if isinstance(self.posthoc, Mapping):
            thresholds = _from_mapping(PosthocThresholds, self.posthoc, "posthoc")
            object.__setattr__(self, "posthoc", thresholds)

    @classmethod
    def from_yaml(cls, path: str | Path | None = None) -> "PlanningConfig":
        """Load `planning.yaml` (default: the packaged one)."""
        return _from_mapping(cls, _load_yaml(path or default_config_dir() / "planning.yaml"),
                             "planning")


# Planning fields that the dataset generator does not use (the post hoc check and the
# in-flight choices between warm starts); `samples_per_node` shapes SCVx* and does matter.
FLIGHT_ONLY_PLANNING = tuple(f.name for f in dataclasses.fields(PlanningConfig)
                             if f.name != "samples_per_node")


# What the pipeline did before these planning fields existed: fly the cheaper plan whatever
# the gap, run ART even when the CVX plan is passively safe, and replan from scratch.
_BEFORE = {"art_min_gain_mps": 0.0, "skip_art_when_cvx_safe": False,
           "propose_concurrently": False, "also_solve_from_art": False,
           "replan_warm_start": "fresh", "endgame": "none", "first_plan_from_both": False,
           "terminal_set_nodes": 0}


@dataclass(frozen=True)
class GuidanceConfig:
    """Every configuration a plan depends on, as one bundle (the YAML files of a config dir).

    One `to_json` and one `sha256` serve the MCAP run metadata, the dataset header and the
    model checkpoint.
    """

    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    uncertainty: UncertaintyConfig = field(default_factory=lambda: UncertaintyConfig())
    scp: ScpConfig = field(default_factory=lambda: ScpConfig())
    planning: PlanningConfig = field(default_factory=PlanningConfig)

    @classmethod
    def load(cls, config_dir: str | Path | None = None) -> "GuidanceConfig":
        """Load scenario, uncertainty, scp and planning YAML from `config_dir` (default:
        the packaged config/)."""
        root = Path(config_dir) if config_dir else default_config_dir()
        return cls(ScenarioConfig.from_yaml(root / "scenario.yaml"),
                   UncertaintyConfig.from_yaml(root / "uncertainty.yaml"),
                   ScpConfig.from_yaml(root / "scp.yaml"),
                   PlanningConfig.from_yaml(root / "planning.yaml"))

    def to_json(self) -> dict:
        """The bundle as JSON-ready data (`from_json` inverts it)."""
        return {"scenario": dataclasses.asdict(self.scenario),
                "uncertainty": dataclasses.asdict(self.uncertainty),
                "scp": dataclasses.asdict(self.scp),
                "planning": dataclasses.asdict(self.planning)}

    @classmethod
    def from_json(cls, data: Mapping) -> "GuidanceConfig":
        """Rebuild a bundle from `to_json` output (validated again). A recorded planning
        section from before a flight choice existed gets the behaviour it was recorded with
        (`_BEFORE`), so that an older log replays as it was flown."""
        try:
            planning = {**_BEFORE, **data["planning"]}
            return cls(ScenarioConfig(**data["scenario"]),
                       UncertaintyConfig(**data["uncertainty"]), ScpConfig(**data["scp"]),
                       _from_mapping(PlanningConfig, planning, "planning"))
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"recorded configuration is malformed: {exc!r}") from exc

    def sha256(self) -> str:
        """Fingerprint of the bundle (canonical JSON)."""
        return hashlib.sha256(json.dumps(self.to_json(), sort_keys=True).encode()).hexdigest()

    def data_json(self) -> dict:
        """The part of the bundle that determines generated trajectories: all of it but the
        planning choices only flight uses (`FLIGHT_ONLY_PLANNING`), so that two bundles that
        differ in those alone describe the same data."""
        out = self.to_json()
        out["planning"] = {k: v for k, v in out["planning"].items()
                           if k not in FLIGHT_ONLY_PLANNING}
        return out

    def data_differences(self, other: "GuidanceConfig") -> list[str]:
        """The parts of `data_json` (scenario, uncertainty, scp, planning) in which two bundles
        describe different data, sorted ([]: the same data)."""
        have, want = self.data_json(), other.data_json()
        return sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))

    def replace(self, **changes: Any) -> "GuidanceConfig":
        """A copy with some parts replaced."""
        return dataclasses.replace(self, **changes)


def node_parameter_defaults(path: str | Path | None = None) -> dict[str, Any]:
    """The guidance node's ROS parameters and their defaults: `guidance_node.yaml`, the one
    table (the node declares exactly these, plus `samples_per_node` from `planning.yaml`)."""
    data = _load_yaml(path or default_config_dir() / "guidance_node.yaml")
    try:
        params = data["guidance_node"]["ros__parameters"]
    except (KeyError, TypeError) as exc:
        raise ConfigError(f"guidance_node.yaml needs guidance_node.ros__parameters: {exc!r}") \
            from exc
    if not isinstance(params, Mapping):
        raise ConfigError("guidance_node.ros__parameters must be a mapping")
    return dict(params)


def _from_mapping(cls: type, data: Any, name: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{name} config must be a mapping, got {data!r}")
    unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ConfigError(f"unknown {name} parameters: {sorted(unknown)}")
    return cls(**data)
