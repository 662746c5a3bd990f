"""Input checks shared by every module: shapes, finiteness, positive semi-definiteness."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from art_guidance.errors import InputError


def as_finite_array(field: str, value: object, shape: Sequence[int | None]) -> np.ndarray:
    """Return `value` as a float64 array of `shape` (None = any size), or raise InputError."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(field, f"not convertible to a float array: {exc}") from exc
    if arr.ndim != len(shape) or any(
        want is not None and have != want for have, want in zip(arr.shape, shape)
    ):
        want_txt = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(field, f"expected shape {want_txt}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(field, "contains NaN or infinite values", arr)
    return arr


def check_psd(field: str, cov: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """Check that `cov` (n, n) is symmetric positive semi-definite; return its symmetric part."""
    cov = as_finite_array(field, cov, (None, None))
    if cov.shape[0] != cov.shape[1]:
        raise InputError(field, f"covariance must be square, got {cov.shape}")
    scale = max(float(np.max(np.abs(cov))), 1e-300)
    if np.max(np.abs(cov - cov.T)) > 1e-6 * scale:
        raise InputError(field, "covariance is not symmetric")
    sym = 0.5 * (cov + cov.T)
    min_eig = float(np.linalg.eigvalsh(sym)[0])
    if min_eig < -rel_tol * scale:
        raise InputError(field, f"covariance is not positive semi-definite "
                                f"(min eig {min_eig:.3g})")
    return sym
