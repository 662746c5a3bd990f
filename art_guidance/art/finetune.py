"""Fine-tuning (`art-guidance train --init`): the checkpoint a run starts from must be of the
architecture the options describe, and the data of its dataset's mode and configuration."""
from __future__ import annotations

from art_guidance.art import checkpoint
from art_guidance.art.config import ArtConfig
from art_guidance.art.rollout import training_config
from art_guidance.config import GuidanceConfig
from art_guidance.errors import ConfigError, GuidanceError, InputError


def initial_model(path: str, cfg: ArtConfig) -> checkpoint.TrainedArt:
    """The checkpoint a fine-tuning starts from; its architecture must be `cfg`.

    Raises:
        InputError: a file that is not a readable model, or one of another architecture.
    """
    try:
        init = checkpoint.load(path)
    except GuidanceError as exc:
        raise InputError("--init", str(exc), path) from exc
    want, have = cfg.to_dict(), init.model.cfg.to_dict()
    diff = {k: (have.get(k), want.get(k)) for k in sorted(set(want) | set(have))
            if have.get(k) != want.get(k)}
    if diff:
        shown = ", ".join(f"{k}: model {a!r}, options {b!r}" for k, (a, b) in diff.items())
        raise InputError("--init", f"the model is not what --preset/--repr/--normalization/"
                         f"--burn-gate describe ({shown}); give the flags it was trained with",
                         path)
    return init


def check_init_data(path: str, init: checkpoint.TrainedArt, provenance: dict) -> None:
    """Raise InputError unless the data is of the initial model's mode and describes the same
    problem (`GuidanceConfig.data_json`: scenario, uncertainty, SCVx* and its samples per node;
    planning choices only flight uses may differ, e.g. a bundle written before one existed)."""
    data = init.meta.get("dataset", {})
    if data.get("mode") != provenance["mode"]:
        raise InputError("--init", f"the model was trained on {data.get('mode')} data, --data "
                         f"is {provenance['mode']} data", path)
    if data.get("config_sha256") == provenance["config_sha256"]:
        return
    try:
        config = training_config(init)
    except ConfigError as exc:
        raise InputError("--init", f"the model's record of its data's configuration is "
                         f"unusable ({exc})", path) from exc
    if config is None:
        raise InputError("--init", "the model records no configuration of its data", path)
    diff = config.data_differences(GuidanceConfig.from_json(provenance["guidance_config"]))
    if diff:
        raise InputError("--init", f"the model's data and --data differ in configuration "
                         f"({', '.join(diff)}: config {str(data.get('config_sha256'))[:12]} "
                         f"against {provenance['config_sha256'][:12]})", path)
