"""What a contingency Monte Carlo flies and how its directory records it: the
`ContingencySpec`, the manifest header (its identity: a resume with other options is refused)
and the committed rows (see `sim.contingency` for the flights).

Row i of a directory is configuration `configs[i // n_seeds]`, seed `base_seed + i % n_seeds`;
each row holds the nominal outcome, up to `NODES_MAX` loss checks and `missed_per_seed`
missed-burn flights (`sim.contingency._flight_row` names the arrays and their units).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from art_guidance import __version__
from art_guidance.config import MODES, GuidanceConfig
from art_guidance.data.storage import load_dataset, read_manifest, sha256_bytes
from art_guidance.errors import InputError

KIND = "contingency"
FORMAT = 1
NODES_MAX = 128            # per-flight loss columns (a flight has n_nodes + 1 losses at most)
CONFIGS = ((True, "auto"), (True, "cvx"), (False, "auto"), (False, "cvx"))


@dataclass(frozen=True)
class ContingencySpec:
    """What a Monte Carlo flies (picklable; sent once to every worker).

    Attributes:
        configs: (chance_constrained, warm_start) per configuration, or (chance_constrained,
            warm_start, replan_window_nodes) for a windowed replan (`planning.window`).
        n_seeds: seeds per configuration: base_seed .. base_seed + n_seeds - 1.
        base_seed: the first seed.
        missed_per_seed: missed-burn flights per (configuration, seed).
        min_missed_dv_mps: smallest commanded burn a missed fault is drawn on [m/s].
        waypoint: the terminal waypoint.
        errors: navigation and actuation errors on.
        terminal_target: where the windows of windowed configurations end (art | cvx).
    """

    configs: tuple[tuple[bool, str], ...] = CONFIGS
    n_seeds: int = 24
    base_seed: int = 0
    missed_per_seed: int = 3
    min_missed_dv_mps: float = 0.01
    waypoint: str = "plus_vbar"
    errors: bool = True
    terminal_target: str = "art"

    @property
    def n_flights(self) -> int:
        """Rows of the output: one per (configuration, seed)."""
        return len(self.configs) * self.n_seeds

    def flight(self, index: int) -> tuple[int, int]:
        """(configuration index, seed) of row `index`."""
        return index // self.n_seeds, self.base_seed + index % self.n_seeds

    def label(self, config: int) -> str:
        """"chance/auto", "deterministic/cvx", "chance/auto/H20_art" ..."""
        chance, warm, window = config_fields(self.configs[config])
        mode = f"{'chance' if chance else 'deterministic'}/{warm}"
        return mode if not window else f"{mode}/H{window}_{self.terminal_target}"


def config_fields(config: tuple) -> tuple[bool, str, int]:
    """(chance_constrained, warm_start, replan_window_nodes) of a configuration (window 0 =
    the whole remainder, for a configuration of two fields)."""
    chance, warm, *rest = config
    return bool(chance), str(warm), int(rest[0]) if rest else 0


def header(spec: ContingencySpec, config: GuidanceConfig) -> dict:
    """The output directory's manifest header; a resume with other options is refused."""
    from art_guidance.art.provider import default_model_path, pinned_sha256
    from art_guidance.sim.inprocess import default_settings

    models = {mode: pinned_sha256(default_model_path(mode))
              for mode in MODES}
    identity = {"format": FORMAT, "spec": asdict(spec), "models": models,
                "guidance_config_sha256": config.sha256(),
                "replan": asdict(default_settings(config.scenario))}  # what `fly` replans by
    return {"mode": KIND, "base_seed": spec.base_seed, "n": spec.n_flights,
            "seed_rule": "row i: configs[i // n_seeds], seed base_seed + i % n_seeds",
            "config_sha256": sha256_bytes(json.dumps(identity, sort_keys=True).encode()),
            "contingency": identity, "art_guidance_version": __version__,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def spec_of(head: dict) -> ContingencySpec:
    """The `ContingencySpec` a contingency directory's header records."""
    stored = head["contingency"]["spec"]
    return ContingencySpec(**dict(stored, configs=tuple(tuple(c) for c in stored["configs"])))


def read_rows(out: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and the committed rows of a contingency directory."""
    head = read_manifest(out)[0]
    if head.get("mode") != KIND:
        raise InputError("--out", "does not hold a contingency Monte Carlo", str(out))
    return head, load_dataset(out, require_complete=False)
