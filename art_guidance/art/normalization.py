"""Z-scoring of the five token modalities, fitted on the training split only.

Two schemes (`ArtConfig.normalization`):

* ``feature``: one mean and one standard deviation per feature, shared by every time step (as
  the RA-L ART version).
* ``timestep``: states and controls z-scored per time-step index (as the original ART
  evaluation path): mean and std over the dataset at each of the K indices, so a quiet node
  (no burn in most plans) and a busy one are scaled by their own spread. Goal, R and C stay per
  feature. Time indices follow the end-aligned rule of `ArtConfig.context` (node i of an
  N-node training trajectory is index K - N + i); indices the data never fills take the
  per-feature statistics.

A feature that is constant in the training data (e.g. C = 0 everywhere in a dataset without
violations) keeps std 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from art_guidance.art.config import MODALITIES

# Standard deviations at or below this are treated as a constant feature (std := 1).
_STD_FLOOR = 1e-8
SCHEMES = ("feature", "timestep")
PER_STEP = ("state", "control")  # modalities z-scored per time step in the "timestep" scheme
_SIZES = {"goal": 6, "reward": 1, "constraint": 1, "state": 6, "control": 3}


@dataclass(frozen=True)
class Normalizer:
    """Feature-wise affine maps ``(x - mean) / std`` per modality.

    Attributes:
        mean: {modality: (F,) float64 mean, or (K, F) per time-step index for the `PER_STEP`
            modalities of the "timestep" scheme}; F = 6 goal, 1 reward, 1 constraint, 6 state,
            3 control (units of the representation: [m], [m, m/s], [m/s], count).
        std: {modality: same shapes, standard deviation, > 0}.
    """

    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]

    @classmethod
    def fit(cls, arrays: dict[str, np.ndarray], scheme: str = "feature",
            context: int | None = None) -> "Normalizer":
        """Statistics over every sample (and time step, "feature" scheme) of `arrays`.

        Args:
            arrays: {"goal": (M, 6), "reward": (M, N), "constraint": (M, N),
                "state": (M, N, 6), "control": (M, N, 3)} of the training trajectories.
            scheme: "feature" or "timestep".
            context: K, the model's time-step indices ("timestep" scheme; default N).
        """
        if scheme not in SCHEMES:
            raise ValueError(f"normalisation scheme must be one of {SCHEMES}, got {scheme!r}")
        mean, std = {}, {}
        for name in MODALITIES:
            x = np.asarray(arrays[name], dtype=np.float64)
            flat = x.reshape(-1, 1) if name in ("reward", "constraint") else x.reshape(
                -1, x.shape[-1])
            mean[name], std[name] = flat.mean(axis=0), _floor(flat.std(axis=0))
            if scheme == "timestep" and name in PER_STEP:
                n = x.shape[1]
                k = n if context is None else int(context)
                m, s = np.tile(mean[name], (k, 1)), np.tile(std[name], (k, 1))  # (K, F)
                m[k - n:], s[k - n:] = x.mean(axis=0), _floor(x.std(axis=0))
                mean[name], std[name] = m, s
        return cls(mean, std)

    def per_step(self, name: str) -> bool:
        """Whether modality `name` is z-scored per time-step index."""
        return self.mean[name].ndim == 2

    def _stats(self, name: str, t: object) -> tuple[np.ndarray, np.ndarray]:
        if not self.per_step(name):
            return self.mean[name], self.std[name]
        if t is None:
            raise ValueError(f"{name} is normalised per time step: give its time indices")
        idx = np.asarray(t, dtype=np.int64)
        return self.mean[name][idx], self.std[name][idx]  # (..., F)

    def normalize(self, name: str, x: np.ndarray, t: object = None) -> np.ndarray:
        """``(x - mean) / std`` for modality `name`; `x` (..., F) (R, C: (...) or (..., 1)).

        `t`: time-step indices broadcast against ``x.shape[:-1]`` (per-step modalities only).
        """
        mean, std = self._stats(name, t)
        return (x - mean) / std

    def denormalize(self, name: str, z: np.ndarray, t: object = None) -> np.ndarray:
        """Inverse of `normalize`."""
        mean, std = self._stats(name, t)
        return z * std + mean

    def to_dict(self) -> dict:
        """Tensors for the checkpoint: {"mean.<modality>": (F,), "std.<modality>": (F,)}."""
        import torch  # the checkpoint's; inference reads numpy (`from_dict`, `to_json`)
        out = {}
        for name in MODALITIES:
            out[f"mean.{name}"] = torch.from_numpy(self.mean[name].copy())
            out[f"std.{name}"] = torch.from_numpy(self.std[name].copy())
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Normalizer":
        """Inverse of `to_dict` (or of `to_json`: tensors, arrays or nested lists).

        Raises:
            ValueError: missing modality, wrong size, non-finite or non-positive std.
        """
        mean, std = {}, {}
        for name in MODALITIES:
            m = np.asarray(data[f"mean.{name}"], dtype=np.float64)
            s = np.asarray(data[f"std.{name}"], dtype=np.float64)
            f = _SIZES[name]
            ok = m.shape == s.shape and (m.size == f or (name in PER_STEP and m.ndim == 2
                                                         and m.shape[1] == f))
            if not ok:
                raise ValueError(f"normalisation of {name} has shapes {m.shape}/{s.shape}, "
                                 f"expected ({f},) or (K, {f})")
            if m.ndim != 2:
                m, s = m.reshape(-1), s.reshape(-1)
            if not (np.all(np.isfinite(m)) and np.all(np.isfinite(s)) and np.all(s > 0)):
                raise ValueError(f"normalisation of {name} is not finite or has std <= 0")
            mean[name], std[name] = m, s
        return cls(mean, std)

    def to_json(self) -> dict[str, list]:
        """`to_dict` as plain lists (an exported model's metadata), read back by `from_dict`."""
        out = {}
        for name in MODALITIES:
            out[f"mean.{name}"] = self.mean[name].tolist()
            out[f"std.{name}"] = self.std[name].tolist()
        return out


def _floor(s: np.ndarray) -> np.ndarray:
    return np.where(s > _STD_FLOOR, s, 1.0)
