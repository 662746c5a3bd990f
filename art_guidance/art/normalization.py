"""Per-feature z-scoring of the five token modalities, fitted on the training split only.

One mean and one standard deviation per feature, shared by every time step (as the RA-L ART
version): a replan that starts at node k > 0, or a horizon shorter than the training one, sees
the same scaling as a full-horizon plan. The original ART evaluation path z-scored per time step
instead; with end-aligned shorter horizons that would tie the scaling to an index the state has
no physical link to. A feature that is constant in the training data (e.g. C = 0 everywhere in a
dataset without violations) keeps std 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from art_guidance.art.config import MODALITIES

# Standard deviations at or below this are treated as a constant feature (std := 1).
_STD_FLOOR = 1e-8


@dataclass(frozen=True)
class Normalizer:
    """Feature-wise affine maps ``(x - mean) / std`` per modality.

    Attributes:
        mean: {modality: (F,) float64 mean}; F = 6 goal, 1 reward, 1 constraint, 6 state,
            3 control (units of the representation: [m], [m, m/s], [m/s], count).
        std: {modality: (F,) float64 standard deviation, > 0}.
    """

    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]

    @classmethod
    def fit(cls, arrays: dict[str, np.ndarray]) -> "Normalizer":
        """Statistics over every sample and time step of `arrays`.

        Args:
            arrays: {"goal": (M, 6), "reward": (M, N), "constraint": (M, N),
                "state": (M, N, 6), "control": (M, N, 3)} of the training trajectories.
        """
        mean, std = {}, {}
        for name in MODALITIES:
            x = np.asarray(arrays[name], dtype=np.float64)
            x = x.reshape(-1, 1) if name in ("reward", "constraint") else x.reshape(
                -1, x.shape[-1])
            mean[name] = x.mean(axis=0)
            s = x.std(axis=0)
            std[name] = np.where(s > _STD_FLOOR, s, 1.0)
        return cls(mean, std)

    def normalize(self, name: str, x: np.ndarray) -> np.ndarray:
        """``(x - mean) / std`` for modality `name`; `x` (..., F) (R, C: (...) or (..., 1))."""
        return (x - self.mean[name]) / self.std[name]

    def denormalize(self, name: str, z: np.ndarray) -> np.ndarray:
        """Inverse of `normalize`."""
        return z * self.std[name] + self.mean[name]

    def to_dict(self) -> dict[str, torch.Tensor]:
        """Tensors for the checkpoint: {"mean.<modality>": (F,), "std.<modality>": (F,)}."""
        out = {}
        for name in MODALITIES:
            out[f"mean.{name}"] = torch.from_numpy(self.mean[name].copy())
            out[f"std.{name}"] = torch.from_numpy(self.std[name].copy())
        return out

    @classmethod
    def from_dict(cls, data: dict[str, torch.Tensor]) -> "Normalizer":
        """Inverse of `to_dict`.

        Raises:
            ValueError: missing modality, wrong size, non-finite or non-positive std.
        """
        sizes = {"goal": 6, "reward": 1, "constraint": 1, "state": 6, "control": 3}
        mean, std = {}, {}
        for name in MODALITIES:
            m = np.asarray(data[f"mean.{name}"], dtype=np.float64).reshape(-1)
            s = np.asarray(data[f"std.{name}"], dtype=np.float64).reshape(-1)
            if m.size != sizes[name] or s.size != sizes[name]:
                raise ValueError(f"normalisation of {name} has {m.size}/{s.size} entries, "
                                 f"expected {sizes[name]}")
            if not (np.all(np.isfinite(m)) and np.all(np.isfinite(s)) and np.all(s > 0)):
                raise ValueError(f"normalisation of {name} is not finite or has std <= 0")
            mean[name], std[name] = m, s
        return cls(mean, std)
