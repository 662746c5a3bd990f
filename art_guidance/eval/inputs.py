"""What an evaluation reads: the checkpoints and datasets under evaluation (their identity),
their held-out scenarios, and (in a worker) a loaded model with its safety model.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from art_guidance.config import mode_name
from art_guidance.data.storage import MANIFEST, complete_shards, read_manifest, sha256_bytes
from art_guidance.errors import InputError


KIND = "evaluation"   # the manifest header's "mode" of an evaluation directory
FORMAT = 1
_LOADED: dict[tuple[str, bool], tuple] = {}


@dataclass(frozen=True)
class ModelInfo:
    """A checkpoint under evaluation.

    Attributes:
        path: checkpoint file.
        sha256: its payload checksum (workers refuse a file that changed since).
        mode: "deterministic" or "chance", the mode of its training data.
        representation: "roe" or "rtn", its state representation.
        train_n: trajectories it was trained on (train + validation share; 0: not recorded).
        n_parameters: its parameter count.
        trained_on: manifest sha256 of each dataset it was trained on.
        trained_seed_bases: the dataset seeds of its training scenarios, where recorded
            (`art.data.trained_seed_bases`).
    """

    path: str
    sha256: str
    mode: str
    representation: str
    train_n: int = 0
    n_parameters: int = 0
    trained_on: tuple[str, ...] = ()
    trained_seed_bases: tuple[int, ...] = ()

    def saw(self, dataset: "DatasetInfo") -> bool:
        """Whether it was trained on `dataset` or on other scenarios of the same seed."""
        return seen(self.trained_on, self.trained_seed_bases, dataset)

    @property
    def label(self) -> str:
        """Short name for figures and logs, e.g. "roe-chance (art.pt)"."""
        return f"{self.representation}-{self.mode} ({Path(self.path).name})"


@dataclass(frozen=True)
class DatasetInfo:
    """A dataset directory whose held-out split is evaluated."""

    path: str
    sha256: str  # of its manifest (which holds every shard's sha256)
    mode: str
    n_samples: int
    base_seed: int | None = None  # its dataset seed S (None: a DAgger directory)


def seen(trained_on: tuple[str, ...], trained_seed_bases: tuple[int, ...],
         dataset: DatasetInfo) -> bool:
    """Whether a model trained on the datasets of manifests `trained_on` and scenario seeds
    `trained_seed_bases` saw `dataset` or other scenarios of its seed."""
    return dataset.sha256 in trained_on or (
        dataset.base_seed is not None and dataset.base_seed in trained_seed_bases)


def dataset_info(path: str | Path) -> DatasetInfo:
    """Mode, size and checksum of a dataset directory (its manifest is read, not the shards).

    Raises:
        DatasetError: not a dataset directory, or a corrupt manifest.
        InputError: an evaluation directory given as a dataset.
    """
    header, _, valid = read_manifest(path)
    if header.get("mode") == KIND:
        raise InputError("--data", "is an evaluation output directory, not a dataset", str(path))
    digest = sha256_bytes((Path(path) / MANIFEST).read_bytes()[:valid])
    seed = None if "dagger" in header or header.get("base_seed") is None \
        else int(header["base_seed"])
    return DatasetInfo(str(path), digest, str(header["mode"]), int(header["n"]), seed)


def model_info(path: str | Path) -> ModelInfo:
    """Checksum, mode and representation of a checkpoint (loaded and verified once).

    Raises:
        CheckpointError: missing, corrupt or incompatible file.
    """
    from art_guidance.art.checkpoint import load
    from art_guidance.art.data import trained_manifests, trained_seed_bases
    from art_guidance.art.rollout import build_safety

    art = load(path)
    mode = mode_name(build_safety(art).uncertainty is not None)
    data = (art.meta or {}).get("dataset", {})
    train_n = int(data.get("n_train", 0)) + int(data.get("n_val", 0))
    return ModelInfo(str(path), str(art.sha256), mode, art.config.representation, train_n,
                     art.model.n_parameters(), trained_manifests(art.meta),
                     trained_seed_bases(art.meta))


def heldout(path: str | Path, split: str = "test") -> dict[str, np.ndarray]:
    """`eval.scoring.heldout_scenarios` of a complete dataset, read shard by shard so that only
    the held-out rows of the fields it selects are kept in memory (sorted by sample index).
    `split` "all" takes every scenario (a dataset no model under evaluation was trained on).

    Raises:
        DatasetError: an incomplete or corrupt dataset.
    """
    from art_guidance.eval.scoring import heldout_scenarios

    parts = [heldout_scenarios(arrays, split=split) for arrays in complete_shards(path)]
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(cols["index"], kind="stable")
    return {k: v[order] for k, v in cols.items()}


def load_model(info: ModelInfo, single_rollout: bool = False) -> tuple:
    """(ArtWarmStart on 1 thread, its PassiveSafety), cached per process; `single_rollout`:
    conditioned on R(t_1) = -J_CVX alone (the paper), else the provider's default sweep."""
    from art_guidance.art.provider import DEFAULT_REWARD_SCALES, ArtWarmStart
    from art_guidance.art.rollout import build_safety

    key = (info.sha256, single_rollout)
    if key not in _LOADED:
        scales = (1.0,) if single_rollout else DEFAULT_REWARD_SCALES
        provider = ArtWarmStart.load(info.path, expected_sha256=info.sha256, threads=1,
                                     reward_scales=scales)
        _LOADED[key] = (provider, build_safety(provider.art))
    return _LOADED[key]


def request_of(roe0_m: np.ndarray, target_rtn: np.ndarray, safety: object) -> object:
    """The plan request from `roe0_m` (6,) [m] to `target_rtn` (6,) [m, m/s] on `safety`'s
    horizon and mode."""
    from art_guidance.planning.request import PlanRequest

    return PlanRequest(safety.horizon.chief_oe[0], roe0_m, target_rtn,
                       chance_constrained=safety.uncertainty is not None)


def problem_of(roe0_m: np.ndarray, target_rtn: np.ndarray, safety: object) -> object:
    """The transfer problem from `roe0_m` (6,) [m] to `target_rtn` (6,) [m, m/s] on `safety`
    (`optim.TransferProblem`), its inputs validated as a plan request (`request_of`)."""
    from art_guidance.optim import TransferProblem

    request = request_of(roe0_m, target_rtn, safety)
    return TransferProblem.to_target(safety, request.roe0_m, request.target_rtn)
