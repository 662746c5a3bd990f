"""A terminal set: the post-burn state at the last node within a ball about the waypoint.

A plan normally ends exactly on the waypoint (the terminal equality of CVX and SCVx*). With a
`TerminalSet` it ends anywhere within `position_m` of the waypoint's position and
`velocity_mps` of its velocity (RTN, after the last burn): two second-order cones

    || Psi_N[:3] (z_N - x_f) ||_2 <= position_m,   || Psi_N[3:] (z_N - x_f) ||_2 <= velocity_mps

in place of the six equality rows (Psi_N the ROE -> RTN map at the last node). The end game
asks for it in the last replans (`planning.endgame`, `terminal_set_nodes`): a replan there
restores passive safety or removes a large error without paying to null, a few nodes before
the hold point, an error that the terminal tolerances already accept.

SCVx* keeps its single shooting: every iterate is projected onto the set (`aim`: the nearest
point of each ball in RTN, then the Gauss-Newton correction onto that point), so every
reference is in the set and every subproblem feasible.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from art_guidance.errors import InputError

INSIDE = 1.0 - 1e-6  # an iterate is aimed this far inside the set's boundary (rounding)


@dataclass(frozen=True)
class TerminalSet:
    """Where a plan may end about its waypoint, after the last burn.

    Attributes:
        position_m: radius of the position ball [m] (RTN).
        velocity_mps: radius of the velocity ball [m/s] (RTN).
    """

    position_m: float
    velocity_mps: float

    def __post_init__(self) -> None:
        for name in ("position_m", "velocity_mps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not 0.0 < value < math.inf:
                raise InputError(f"terminal_set.{name}", "must be a finite number > 0", value)

    def cone(self, psi_f: np.ndarray, scale_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The set as two cones on ROE in units of `scale_s` [s] (z~ = z / scale_s): (6, 6)
        rows R and the (2,) heads h with ``||R[:3] (z~ - x_f~)|| <= h[0]`` and ``||R[3:]
        (z~ - x_f~)|| <= h[1]``: Psi_N's position rows, its velocity rows times `scale_s`,
        so that with `scale_s` ~ 1/n every entry is O(1) (`psi_f`: the (6, 6) ROE -> RTN map
        at the last node)."""
        psi = np.asarray(psi_f, float)
        rows = np.concatenate([psi[:3], scale_s * psi[3:]])
        return rows, np.array([self.position_m / scale_s, self.velocity_mps])

    def error(self, psi_f: np.ndarray, roe_f_m: np.ndarray, z_f_m: np.ndarray
              ) -> tuple[float, float]:
        """Position [m] and velocity [m/s] distance of the post-burn ROE `z_f_m` from the
        waypoint `roe_f_m`."""
        err = np.asarray(psi_f, float) @ (np.asarray(z_f_m, float) - roe_f_m)
        return float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))

    def contains(self, psi_f: np.ndarray, roe_f_m: np.ndarray, z_f_m: np.ndarray) -> bool:
        """`z_f_m` in the set."""
        pos, vel = self.error(psi_f, roe_f_m, z_f_m)
        return pos <= self.position_m and vel <= self.velocity_mps

    def aim(self, psi_f: np.ndarray, roe_f_m: np.ndarray, z_f_m: np.ndarray) -> np.ndarray:
        """(6,) the point of the set nearest to `z_f_m` in RTN (each ball's radial clip, a
        hair inside): `z_f_m` itself (a copy) when it is in the set."""
        psi = np.asarray(psi_f, float)
        err = psi @ (np.asarray(z_f_m, float) - roe_f_m)
        out = err.copy()
        for part, radius in ((slice(0, 3), self.position_m), (slice(3, 6), self.velocity_mps)):
            size = float(np.linalg.norm(err[part]))
            if size > radius:
                out[part] *= INSIDE * radius / size
        if np.array_equal(out, err):
            return np.array(z_f_m, float)
        return roe_f_m + np.linalg.solve(psi, out)

    def to_json(self) -> dict:
        """{"position_m", "velocity_mps"}."""
        return {"position_m": float(self.position_m), "velocity_mps": float(self.velocity_mps)}

    @classmethod
    def from_json(cls, data: dict | None) -> "TerminalSet | None":
        """Inverse of `to_json` (None stays None: the terminal equality)."""
        if data is None:
            return None
        return cls(float(data["position_m"]), float(data["velocity_mps"]))
