"""The guidance node's ROS parameters: what each means, its constraints, whether it may change.

Defaults come from `config/guidance_node.yaml` (`config.node_parameter_defaults`), plus
`samples_per_node` from `planning.yaml`; this module adds the descriptors. Importing it loads no
ROS module (the CLI's `node --help` lists the parameters from here); `descriptor` imports
rcl_interfaces when the node asks for one.

Dynamic parameters are applied at run time after validation (an invalid value is refused with a
reason and changes nothing); read-only ones are fixed at start-up and `ros2 param set` on them
is refused.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from art_guidance.config import ENDGAMES, NUMERICS, REPLAN_WARM_STARTS
from art_guidance.errors import ConfigError
from art_guidance.planning import WARM_STARTS
from art_guidance.guidance.replan import STAMP_CHECKS, ReplanSettings
from art_guidance.planning.request import TERMINAL_TARGETS
from art_guidance.record.seal import SHOWN_CHARS, shown

NAV_QOS = ("best_effort", "reliable")
KINDS = {"float": "a number", "int": "an integer", "bool": "a boolean (true or false)",
         "str": "a string"}  # a kind in words, as a refusal names it
VALUE_TYPES = ((bool, "a boolean"), (int, "an integer"), (float, "a floating-point number"),
               (str, "a string"), (bytes, "a byte array"))  # bool first: a bool is an int


def shown_value(value: Any) -> str:
    """A parameter value for a message: a string as `record.seal.shown` shows it, any other
    value as Python writes it, likewise cut to SHOWN_CHARS characters (with its length)."""
    if isinstance(value, str):
        return shown(value)
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else (
        f"{text[:SHOWN_CHARS]}... ({len(text)} characters)")


def type_of(value: Any) -> str:
    """The type of a parameter value in words ("an integer", "a string", ...)."""
    for cls, words in VALUE_TYPES:
        if isinstance(value, cls):
            return words
    return "an array"


@dataclass(frozen=True)
class ParamSpec:
    """One parameter's meaning and constraints.

    Attributes:
        description: what it does, with its unit.
        kind: "float", "int", "bool" or "str".
        choices: the allowed strings (kind "str"), or None for any.
        minimum: the smallest allowed number (kind "float" / "int"), or None.
        exclusive_minimum: the minimum itself is not allowed (a strict "> minimum").
        dynamic: may change at run time (applied after validation); else read-only.
    """

    description: str
    kind: str
    choices: tuple[str, ...] | None = None
    minimum: float | None = None
    exclusive_minimum: bool = False
    dynamic: bool = False

    @property
    def constraints(self) -> str:
        """The constraints in words (the descriptor's additional_constraints)."""
        if self.choices is not None:
            return "one of: " + ", ".join(self.choices)
        if self.minimum is not None:
            return f"{'>' if self.exclusive_minimum else '>='} {self.minimum:g}"
        return ""

    def coerce(self, name: str, value: Any) -> Any:
        """The value as this parameter's type, validated.

        Raises:
            ConfigError: naming the parameter, the constraint and the value (`shown_value`).
        """
        got = shown_value(value)
        if self.kind in ("float", "int"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{name} must be a number, got {got}")
            if self.kind == "int" and float(value) != int(value):
                raise ConfigError(f"{name} must be a whole number, got {got}")
            value = float(value) if self.kind == "float" else int(value)
            low = self.minimum
            if low is not None and (value <= low if self.exclusive_minimum else value < low) \
                    or value != value:
                raise ConfigError(f"{name} must be {self.constraints}, got {value!r}")
            return value
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise ConfigError(f"{name} must be true or false, got {got}")
            return value
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be a string, got {got}")
        if self.choices is not None and value not in self.choices:
            raise ConfigError(f"{name} must be {self.constraints}, got {got}")
        return str(value)  # a plain string (a configuration's enum member is one too)

    def type_refusal(self, name: str, value: Any) -> ConfigError:
        """The refusal of a value of another type than this parameter's (rclpy refuses it at
        declaration: `InvalidParameterTypeException`): the parameter, the type it must have
        (with its constraints) and the value given, with its type. YAML, which reads a
        command line's values, takes an unquoted true/false, yes/no or on/off for a boolean:
        for a string parameter the refusal says how to quote one."""
        limits = f" ({self.constraints})" if self.constraints else ""
        text = (f"{name} must be {KINDS[self.kind]}{limits}, got {shown_value(value)} "
                f"({type_of(value)})")
        if self.kind == "str" and isinstance(value, bool):
            text += (f"; YAML reads an unquoted true/false, yes/no or on/off as a boolean: "
                     f"quote the string, -p {name}:=\"'...'\"")
        return ConfigError(text)


SPECS: dict[str, ParamSpec] = {
    "config_dir": ParamSpec("directory with scenario/uncertainty/scp/planning YAML "
                            "('' = the packaged config/)", "str"),
    "default_waypoint": ParamSpec("target until a replan request names one (a waypoint of "
                                  "scenario.yaml)", "str"),
    "chance_constrained": ParamSpec("plan chance-constrained passive safety until a replan "
                                    "request says otherwise (false: deterministic)", "bool"),
    "warm_start": ParamSpec("SCP warm start until a replan request says otherwise", "str",
                            WARM_STARTS),
    "model_path": ParamSpec("ART checkpoint for the learned warm start, loaded and checked "
                            "once at start-up ('' = the shipped default model of the "
                            "chance_constrained mode, 'none' = CVX only); a model that fails "
                            "to load leaves the node in CVX-only mode with a warning", "str"),
    "art_runtime": ParamSpec("what runs the model: 'torch' (the checkpoint), 'onnx' (its "
                             "exported .onnx file beside it or given as model_path, on ONNX "
                             "Runtime, no torch needed) or 'auto' (onnx where ONNX Runtime and "
                             "the exported file are there, else torch; where one file of that "
                             "pair is damaged the other flies, with a warning naming it); an "
                             "unknown or missing runtime leaves the node in CVX-only mode with "
                             "a warning", "str"),
    "replan_sigma_threshold": ParamSpec("replan when any ROE axis deviates from the plan by "
                                        "more than this [navigation sigma]", "float",
                                        minimum=0.0, exclusive_minimum=True, dynamic=True),
    "replan_period_s": ParamSpec("also replan this often in stamp time [s]; 0 = off",
                                 "float", minimum=0.0, dynamic=True),
    "stamp_check": ParamSpec("wallclock: age/future limits and order; order: monotonic only "
                             "(simulated time); off", "str", STAMP_CHECKS, dynamic=True),
    "max_nav_age_s": ParamSpec("refuse a fix older than this (stamp_check wallclock) [s]",
                               "float", minimum=0.0, exclusive_minimum=True, dynamic=True),
    "max_nav_future_s": ParamSpec("refuse a fix stamped further ahead than this [s]", "float",
                                  minimum=0.0, exclusive_minimum=True, dynamic=True),
    "max_stamp_jump_s": ParamSpec("stamp_check order: refuse a fix stamped further ahead of "
                                  "the last accepted fix than this (a stamp from the future "
                                  "would otherwise become the floor every later fix is "
                                  "refused against) [s]", "float", minimum=0.0,
                                  exclusive_minimum=True, dynamic=True),
    "solve_deadline_s": ParamSpec("wall-clock budget of a whole replan up to its "
                                  "publication (CVX, ART proposal, every SCVx* run; the "
                                  "longest of the last 20 recordings, at most half of it, is "
                                  "kept for recording): on expiry the best feasible plan at "
                                  "hand is published [s]", "float",
                                  minimum=0.0, exclusive_minimum=True, dynamic=True),
    "propose_concurrently": ParamSpec("warm_start auto: make the learned proposal, and SCVx* "
                                      "from it, in a worker process (started at configure, "
                                      "~300 MB more memory) while SCVx* from CVX is solved: "
                                      "the same plans, sooner where a core is free; false: "
                                      "one after the other",
                                      "bool"),
    "min_remaining_nodes": ParamSpec("below this many nodes left the plan in force is flown "
                                     "out, not replanned", "int", minimum=2, dynamic=True),
    "replan_window_nodes": ParamSpec("H: a replan optimises the next H nodes (SCVx* with the "
                                     "passive-safety constraint) and ends at terminal_target's "
                                     "state there, replanning before half the window is "
                                     "flown; 0 = the whole remainder to the waypoint; else in "
                                     "[2, the horizon's nodes - 1] [nodes]", "int", minimum=0,
                                     dynamic=True),
    "terminal_target": ParamSpec("where a window ends: art (the learned proposal's state, "
                                 "CVX's where it is rejected or missing), cvx (the convex "
                                 "solution's state) or carry (the plan in force's own state: a "
                                 "tracking MPC; the whole remainder where there is none)",
                                 "str", TERMINAL_TARGETS, dynamic=True),
    "art_context": ParamSpec("give the learned proposal the steps flown since the target "
                             "was set (states, burns, R) as its context, T-MPC's closed loop; "
                             "false: each replan's rollout starts afresh from the fix", "bool",
                             dynamic=True),
    "nav_qos_reliability": ParamSpec("reliability of the nav subscription: best_effort matches "
                                     "both best-effort (sensor data) and reliable publishers",
                                     "str", NAV_QOS),
    "visualization": ParamSpec("publish the plan and the navigated deputy for RViz2/Foxglove "
                               "(guidance/viz/*, frame chief_rtn) and record them", "bool"),
    "record": ParamSpec("write every solve to MCAP (a rosbag2 bag folder)", "bool"),
    "record_dir": ParamSpec("bag folder ('' = <ROS_HOME>/art_guidance_logs/<run>)", "str"),
    "record_max_bytes": ParamSpec("rotate MCAP files at this size [bytes]", "int",
                                  minimum=4096),
    "record_max_total_bytes": ParamSpec("cap on the size of the bag's files [bytes]: at a "
                                        "rotation the oldest closed files are deleted so that "
                                        "they and a new file fit; 0 = no cap, else at least "
                                        "3 * record_max_bytes", "int", minimum=0),
    "samples_per_node": ParamSpec("drift samples linearised per node in SCP (default: "
                                  "planning.yaml)", "int", minimum=1),
    "numerics": ParamSpec("the per-step numerics: 'compiled' (numba kernels, loaded from "
                          "their cache at configure; on a cold cache the numpy path while a "
                          "background process compiles them) or 'numpy' (their oracles); numba "
                          "missing or failing is said at configure and the numpy path taken "
                          "(default: planning.yaml)", "str", NUMERICS),
    "replan_warm_start": ParamSpec("a replan with a plan in force: 'carry' starts SCVx* from "
                                   "that plan's burns (the fresh solve, from CVX and with "
                                   "warm_start auto from the learned proposal, runs where "
                                   "there is nothing to carry, where the carried run does not "
                                   "converge, and where the plan has grown far above a fresh "
                                   "one's); 'fresh' solves every replan from scratch (default: "
                                   "planning.yaml)", "str", REPLAN_WARM_STARTS),
    "endgame": ParamSpec("the end game: 'keep' makes a replan the deviation triggers only "
                         "when the error matters (the plan in force, flown from the fix, not "
                         "passively safe, or its predicted terminal error beyond "
                         "terminal_tolerance_m / terminal_tolerance_mps); 'keep_cap' also "
                         "leaves a replan costing more than endgame_cost_cap_mps above the "
                         "plan in force's remaining burns out of force while that plan is "
                         "passively safe from the fix; 'none' puts every usable replan in "
                         "force (default: planning.yaml)", "str", ENDGAMES),
    "terminal_tolerance_m": ParamSpec("endgame keep: the predicted terminal position error "
                                      "the plan in force may keep [m] (default: "
                                      "planning.yaml)", "float", minimum=0.0),
    "terminal_tolerance_mps": ParamSpec("endgame keep: the predicted terminal velocity error "
                                        "the plan in force may keep [m/s] (default: "
                                        "planning.yaml)", "float", minimum=0.0),
    "endgame_cost_cap_mps": ParamSpec("endgame keep_cap: a replan costing more than this, "
                                      "plus endgame_cost_per_m per metre of the terminal "
                                      "error it removes, above the plan in force's remaining "
                                      "burns stays out of force while that plan is passively "
                                      "safe from the fix [m/s] (default: planning.yaml)",
                                      "float", minimum=0.0),
    "endgame_cost_per_m": ParamSpec("endgame keep_cap: what a metre of predicted terminal "
                                    "error is worth [m/s per m] (default: planning.yaml)",
                                    "float", minimum=0.0),
    "terminal_set_nodes": ParamSpec("endgame: a replan it makes with this many nodes left or "
                                    "fewer ends anywhere within terminal_set_share of the "
                                    "terminal tolerances of the waypoint (a terminal set: two "
                                    "second-order cones in CVX and SCVx*) instead of on it; 0: "
                                    "every plan ends on the waypoint (default: planning.yaml)",
                                    "int", minimum=0),
}
# parameters whose defaults come from planning.yaml, not guidance_node.yaml
PLANNING_PARAMETERS = ("samples_per_node", "numerics", "replan_warm_start", "endgame",
                       "terminal_tolerance_m", "terminal_tolerance_mps", "endgame_cost_cap_mps",
                       "endgame_cost_per_m", "terminal_set_nodes")
# the replan policy's parameters (`guidance.replan.ReplanSettings`)
POLICY_PARAMETERS = ("replan_sigma_threshold", "replan_period_s", "stamp_check",
                     "max_nav_age_s", "max_nav_future_s", "max_stamp_jump_s",
                     "min_remaining_nodes", "replan_window_nodes", "terminal_target",
                     "art_context")


@dataclass(frozen=True)
class NodeParameters:
    """The guidance node's parameters, typed and validated (`SPECS`: meaning, unit and
    constraints of each), in the order of `SPECS`. The node reads them once at start-up
    (`from_values`) and replaces the whole object on an accepted run-time change (`changed`).
    """

    config_dir: str
    default_waypoint: str
    chance_constrained: bool
    warm_start: str
    model_path: str
    art_runtime: str
    replan_sigma_threshold: float
    replan_period_s: float
    stamp_check: str
    max_nav_age_s: float
    max_nav_future_s: float
    max_stamp_jump_s: float
    solve_deadline_s: float
    propose_concurrently: bool
    min_remaining_nodes: int
    replan_window_nodes: int
    terminal_target: str
    art_context: bool
    nav_qos_reliability: str
    visualization: bool
    record: bool
    record_dir: str
    record_max_bytes: int
    record_max_total_bytes: int
    samples_per_node: int
    numerics: str
    replan_warm_start: str
    endgame: str
    terminal_tolerance_m: float
    terminal_tolerance_mps: float
    endgame_cost_cap_mps: float
    endgame_cost_per_m: float
    terminal_set_nodes: int

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> "NodeParameters":
        """Every parameter of `SPECS` from `values` (name -> value), coerced and validated.

        Raises:
            ConfigError: naming the parameter, the constraint and the value.
        """
        return cls(**{name: spec.coerce(name, values[name]) for name, spec in SPECS.items()})

    def changed(self, changes: Mapping[str, Any]) -> "NodeParameters":
        """These parameters with run-time `changes` (name -> value) applied, all or none.

        Raises:
            ConfigError: a read-only or unknown parameter, or an invalid value (alone or for
                the replan policy).
        """
        new = {}
        for name, value in changes.items():
            spec = SPECS.get(name)
            if spec is None or not spec.dynamic:
                raise ConfigError(f"{name} is read-only (fixed at start-up)")
            new[name] = spec.coerce(name, value)
        out = dataclasses.replace(self, **new)
        out.replan_settings()
        return out

    def replan_settings(self, **extra: Any) -> ReplanSettings:
        """The replan policy's settings (`POLICY_PARAMETERS`, plus `extra` fields)."""
        return ReplanSettings(**{name: getattr(self, name) for name in POLICY_PARAMETERS},
                              **extra)

    def as_dict(self) -> dict[str, Any]:
        """Name -> value, in the order of `SPECS` (recorded with a run)."""
        return dataclasses.asdict(self)


def descriptor(name: str) -> Any:
    """The rcl_interfaces ParameterDescriptor of a parameter (floats accept whole numbers)."""
    from rcl_interfaces.msg import ParameterDescriptor

    spec = SPECS[name]
    return ParameterDescriptor(description=spec.description,
                               additional_constraints=spec.constraints,
                               read_only=not spec.dynamic,
                               dynamic_typing=spec.kind == "float")


def check_table(defaults: dict[str, Any]) -> None:
    """Every parameter of the YAML table has a spec and a valid default, and vice versa.

    Raises:
        ConfigError: on a missing, unknown or invalid parameter.
    """
    names = set(defaults) | set(PLANNING_PARAMETERS)
    if names != set(SPECS):
        raise ConfigError(f"guidance_node.yaml and the parameter specs differ: "
                          f"{sorted(names ^ set(SPECS))}")
    fields = [f.name for f in dataclasses.fields(NodeParameters)]
    if fields != list(SPECS):
        raise ConfigError(f"NodeParameters and the parameter specs differ: {fields} against "
                          f"{list(SPECS)}")
    for name, value in defaults.items():
        SPECS[name].coerce(name, value)


TABLE_BEGIN, TABLE_END = "<!-- parameter-table:begin -->", "<!-- parameter-table:end -->"


def parameter_table(defaults: dict[str, Any]) -> str:
    """The parameter table of the documentation (markdown), from `SPECS` and the YAML
    defaults (`config.node_parameter_defaults()`); `PLANNING_PARAMETERS` default to
    planning.yaml's values."""
    lines = ["| parameter | default | run time | meaning |", "|---|---|---|---|"]
    for name, spec in SPECS.items():
        value = defaults.get(name, "planning.yaml")
        text = str(value).lower() if isinstance(value, bool) else str(value)
        shown = "`''`" if value == "" else f"`{text}`"
        limits = f" ({spec.constraints})" if spec.constraints else ""
        lines.append(f"| `{name}` | {shown} | {'dynamic' if spec.dynamic else 'read-only'} | "
                     f"{spec.description}{limits} |")
    return "\n".join(lines) + "\n"
