"""Closed-loop rendezvous simulator: nonlinear truth, navigation and actuation errors, reporting.

Pure numpy/scipy (no rclpy); `art_guidance.ros.sim_node` wraps it in a ROS 2 process and
`art_guidance.sim.plot` draws a run.

Truth model: both spacecraft are integrated together (one 12-state) in the inertial frame under
two-body gravity plus the J2 zonal term (DOP853, rtol 1e-11). The acceleration and the
vectorised Cartesian -> Kepler conversion are written out here and do not reuse `dynamics`.

Mean versus osculating. The STM, B and Psi of the planner act on *mean* ROE with a chief whose
*mean* elements advance at the J2 secular rates. The truth has osculating elements: for the
paper's chief the osculating a differs from the mean a by up to ~6 km (J2 short-periodic term
3/2 J2 R^2/a sin^2 i cos 2u; at the paper's epoch the mean a is 5.96 km larger), and the
relative osculating ROE differ from the mean ROE by ~0.1-0.3 % of the separation. Hence, with
``mean_elements=True`` (the default):

* the chief starts from the given elements treated as *osculating* at t = 0, and the planner's
  chief model (`RendezvousSim.chief_mean_oe`) propagates its *orbit-averaged mean* elements at
  t = 0 with the J2 secular rates; the model's argument of latitude then stays within ~5e-6
  rad/orbit of the truth's mean one (treating the osculating elements as mean instead walks
  away by 8.3e-3 rad/orbit, which misdirects large burns through B by ~1 %);
* the navigation fix (`nav_estimate`) is built on the *mean* ROE (`mean_roe_m`: each
  spacecraft's osculating elements averaged over its own period of free motion centred on
  now), the quantity an ARTMS-type filter estimates and the STM propagates.

``mean_elements=False`` uses the given elements directly as the mean model and the exact
osculating ROE (`true_roe_m`) for navigation. Measured closed-loop effect (seed 0, perfect
navigation, replanning every node): final miss 20 m that way, 2 m with mean elements.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.integrate import solve_ivp

from art_guidance.checks import as_finite_array
from art_guidance.config import ScenarioConfig, UncertaintyConfig
from art_guidance.dynamics import (
    J2, MU_M3PS2, R_EARTH_M, Horizon, check_oe, eci_from_oe, eci_from_rtn, oe_from_eci,
    propagate_mean_oe, psi_matrix, roe_from_oe, rtn_frame, rtn_from_eci, time_grid_s,
)
from art_guidance.errors import InputError
from art_guidance.safety import PassiveSafety
from art_guidance.uncertainty import gates_covariance, nav_covariance

TRUTH_RTOL = 1e-11
TRUTH_ATOL = 1e-8      # [m], [m/s]; relative states are differences of two 7e6 m vectors
RECORD_STEP_S = 20.0   # largest spacing of the recorded truth trajectory (plots) [s]
EPOCH_MATCH_S = 1.0    # a node epoch within this of the sim time is "now" [s]
MEAN_SAMPLES = 128     # samples per orbit-averaging window (midpoint rule)
MEAN_ITERATIONS = 2    # fixed-point iterations of the averaging period


# --------------------------------------------------------------------------- truth dynamics
def _accel(pos: np.ndarray) -> np.ndarray:
    """Two-body + J2 acceleration [m/s^2] for inertial positions (..., 3) [m].

    Minus the gradient of U = -mu/r + mu J2 R^2 (3 z^2/r^2 - 1) / (2 r^3).
    """
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    r2 = x * x + y * y + z * z
    r = np.sqrt(r2)
    k = -MU_M3PS2 / (r2 * r)
    f = 1.5 * J2 * R_EARTH_M**2 / r2
    zz = 5.0 * z * z / r2
    return np.stack([k * x * (1.0 + f * (1.0 - zz)),
                     k * y * (1.0 + f * (1.0 - zz)),
                     k * z * (1.0 + f * (3.0 - zz))], axis=-1)


def _rhs(_t: float, y: np.ndarray) -> np.ndarray:
    s = y.reshape(-1, 6)
    return np.concatenate([s[:, 3:], _accel(s[:, :3])], axis=1).ravel()


def _integrate(y0: np.ndarray, dt_s: float, t_eval: np.ndarray | None = None,
               dense: bool = False):
    """Integrate stacked (B*6,) inertial states over [0, dt_s] (dt_s may be negative)."""
    sol = solve_ivp(_rhs, (0.0, dt_s), y0, method="DOP853", rtol=TRUTH_RTOL, atol=TRUTH_ATOL,
                    t_eval=t_eval, dense_output=dense)
    if not sol.success:  # pragma: no cover - DOP853 on a smooth field does not fail
        raise InputError("dt_s", f"truth integration failed: {sol.message}", dt_s)
    return sol


def propagate_truth(chief_eci: object, deputy_eci: object,
                    dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Propagate chief and deputy together under two-body + J2 gravity (inertial frame).

    Args:
        chief_eci: (6,) chief inertial position [m] and velocity [m/s].
        deputy_eci: (6,) deputy inertial position [m] and velocity [m/s].
        dt_s: duration [s], >= 0.

    Returns:
        (chief_eci, deputy_eci) at t + dt_s, each (6,).

    Raises:
        InputError: on NaN/inf, wrong shapes or a negative duration.
    """
    c = as_finite_array("chief_eci", chief_eci, (6,))
    d = as_finite_array("deputy_eci", deputy_eci, (6,))
    dt = _check_dt(dt_s)
    if dt == 0.0:
        return c.copy(), d.copy()
    y = _integrate(np.concatenate([c, d]), dt).y[:, -1]
    return y[:6].copy(), y[6:].copy()


def _check_dt(dt_s: float) -> float:
    dt = float(dt_s)
    if not (np.isfinite(dt) and dt >= 0.0):
        raise InputError("dt_s", "must be finite and >= 0 [s]", dt_s)
    return dt


def rtn_from_eci_batch(chief_eci: np.ndarray, deputy_eci: np.ndarray) -> np.ndarray:
    """Exact relative RTN states (S, 6) [m, m/s] of (S, 6) inertial chief/deputy pairs.

    The batched form of `dynamics.rtn_from_eci` (same frame: R along the chief's position, N
    along its angular momentum, rotating at |h| / r^2 about N).
    """
    r, v = chief_eci[:, :3], chief_eci[:, 3:]
    h = np.cross(r, v)
    r2 = np.sum(r * r, axis=1)
    r_hat = r / np.sqrt(r2)[:, None]
    n_hat = h / np.linalg.norm(h, axis=1)[:, None]
    basis = np.stack([r_hat, np.cross(n_hat, r_hat), n_hat], axis=1)  # (S, 3 rows, 3)
    dr = np.einsum("sij,sj->si", basis, deputy_eci[:, :3] - r)
    omega = np.linalg.norm(h, axis=1) / r2  # about N
    dv = np.einsum("sij,sj->si", basis, deputy_eci[:, 3:] - v)
    dv[:, 0] += omega * dr[:, 1]
    dv[:, 1] -= omega * dr[:, 0]
    return np.concatenate([dr, dv], axis=1)


# --------------------------------------------------------------------------- mean elements
def _nonsingular_from_eci(states: np.ndarray) -> np.ndarray:
    """Osculating (a, e cos w, e sin w, i, raan, u = w + M) of inertial states (..., 6)."""
    r, v = states[..., :3], states[..., 3:]
    rn = np.linalg.norm(r, axis=-1)
    v2 = np.sum(v * v, axis=-1)
    rv = np.sum(r * v, axis=-1)
    h = np.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    a = 1.0 / (2.0 / rn - v2 / MU_M3PS2)
    inc = np.arccos(np.clip(h[..., 2] / hn, -1.0, 1.0))
    raan = np.arctan2(h[..., 0], -h[..., 1])
    e_vec = ((v2 - MU_M3PS2 / rn)[..., None] * r - rv[..., None] * v) / MU_M3PS2
    node = np.stack([np.cos(raan), np.sin(raan), np.zeros_like(raan)], axis=-1)
    m_hat = np.cross(h / hn[..., None], node)
    ex, ey = np.sum(e_vec * node, axis=-1), np.sum(e_vec * m_hat, axis=-1)
    e = np.hypot(ex, ey)
    w = np.arctan2(ey, ex)
    u_true = np.arctan2(np.sum(r * m_hat, axis=-1), np.sum(r * node, axis=-1))
    nu = u_true - w
    ecc = 2.0 * np.arctan2(np.sqrt(1.0 - e) * np.sin(nu / 2), np.sqrt(1.0 + e) * np.cos(nu / 2))
    return np.stack([a, ex, ey, inc, raan, w + ecc - e * np.sin(ecc)], axis=-1)


def mean_elements(states: object) -> np.ndarray:
    """Orbit-averaged (mean) Keplerian elements of inertial states under free motion.

    Every body's osculating nonsingular elements (a, e cos w, e sin w, i, raan, u = w + M,
    angles unwrapped) are averaged over one of its *own* Keplerian periods (of its averaged a,
    fixed-point iterated) centred on now, sampling the two-body + J2 truth propagated forward
    and backward. First-order J2 short-periodic terms average to zero over the mean anomaly,
    so this is the (Brouwer/Kozai) mean element to first order in J2; the secular drift is
    linear over the window and a centred average returns its value now.

    Args:
        states: (B, 6) inertial states [m, m/s].

    Returns:
        (B, 6) mean elements (a [m], e, i, raan, argp, M [rad]).
    """
    s = as_finite_array("states", states, (None, 6))
    n_body = s.shape[0]
    period = 2.0 * np.pi / np.sqrt(MU_M3PS2 / _nonsingular_from_eci(s)[:, 0] ** 3)
    span = 0.6 * float(period.max())
    y0 = s.ravel()
    fwd, bwd = _integrate(y0, span, dense=True), _integrate(y0, -span, dense=True)
    offsets = (np.arange(MEAN_SAMPLES) + 0.5) / MEAN_SAMPLES - 0.5  # ascending, symmetric
    half = MEAN_SAMPLES // 2  # offsets[:half] < 0 <= offsets[half:]
    rows = np.arange(n_body)
    for _ in range(MEAN_ITERATIONS + 1):
        times = period[:, None] * offsets[None, :]  # (B, S)
        neg = bwd.sol(times[:, :half].ravel()).reshape(n_body, 6, n_body, half)
        pos = fwd.sol(times[:, half:].ravel()).reshape(n_body, 6, n_body, MEAN_SAMPLES - half)
        own = np.concatenate([neg[rows, :, rows], pos[rows, :, rows]], axis=-1)  # (B, 6, S)
        q = _nonsingular_from_eci(np.moveaxis(own, 1, -1))  # (B, S, 6)
        q[..., 4] = np.unwrap(q[..., 4], axis=-1)
        q[..., 5] = np.unwrap(q[..., 5], axis=-1)
        avg = q.mean(axis=1)  # (B, 6)
        period = 2.0 * np.pi / np.sqrt(MU_M3PS2 / avg[:, 0] ** 3)
    w = np.arctan2(avg[:, 2], avg[:, 1])
    two_pi = 2.0 * np.pi
    return np.column_stack([avg[:, 0], np.hypot(avg[:, 1], avg[:, 2]), avg[:, 3],
                            avg[:, 4] % two_pi, w % two_pi, (avg[:, 5] - w) % two_pi])


# --------------------------------------------------------------------------- simulator
class NodeRecord(NamedTuple):
    """One executed plan node (a burn, possibly of zero size).

    Attributes:
        t_s: sim time of the burn [s].
        rtn: (6,) true pre-burn relative RTN state [m, m/s].
        dv_mps: (3,) executed delta-v in the chief RTN axes [m/s] (commanded + Gates error).
        dv_cmd_mps: (3,) commanded delta-v [m/s].
        roe_post_m: (6,) post-burn ROE [m] in the simulator's model (mean or osculating).
    """

    t_s: float
    rtn: np.ndarray
    dv_mps: np.ndarray
    dv_cmd_mps: np.ndarray
    roe_post_m: np.ndarray


def _gaussian(rng: np.random.Generator, cov: np.ndarray) -> np.ndarray:
    """A zero-mean sample with covariance `cov` (n, n), PSD (singular allowed)."""
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    return v @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(w.size))


class RendezvousSim:
    """Truth state of a chief (target) and a deputy (servicer), with error models.

    Attributes:
        scenario: the scenario (chief orbit, ellipsoids, waypoints).
        uncertainty: error model for navigation and actuation, or None (perfect).
        mean_elements: see the module docstring.
        chief_oe0: (6,) chief elements at t = 0, the truth chief's *osculating* initial state.
        chief_mean_oe0: (6,) the planner's chief model at t = 0: the orbit-averaged mean
            elements of the truth chief (`mean_elements=True`) or `chief_oe0` itself.
        rng: the simulator's random generator (seeded), used when a method gets no `rng`.
        t_s: sim time since the start [s].
        chief_eci, deputy_eci: (6,) truth inertial states [m, m/s].
        history: executed nodes (`NodeRecord`; its first three fields are (t, true RTN,
            executed dv)), in time order.
        trajectory_t_s, trajectory_rtn: recorded truth samples (floats [s], (6,) RTN), at
            most RECORD_STEP_S apart and at every burn.
    """

    def __init__(self, scenario: ScenarioConfig, uncertainty: UncertaintyConfig | None,
                 rtn0: object, seed: int, chief_oe0: object | None = None,
                 mean_elements: bool = True) -> None:
        """Place chief and deputy.

        Args:
            scenario: scenario configuration.
            uncertainty: navigation (ARTMS) and actuation (Gates) model; None = no errors.
            rtn0: (6,) initial relative RTN state [m, m/s], converted exactly to the deputy's
                inertial state.
            seed: seed of `rng`.
            chief_oe0: (6,) chief elements at t = 0 (default `scenario.chief_oe`), the
                osculating truth state of the chief.
            mean_elements: mean-element chief model and mean-ROE navigation (True) or the
                given elements as the mean model and osculating ROE (False).

        Raises:
            InputError: on bad elements or a non-finite `rtn0`.
        """
        self.scenario = scenario
        self.uncertainty = uncertainty
        self.mean_elements = bool(mean_elements)
        self.chief_oe0 = check_oe(scenario.chief_oe if chief_oe0 is None else chief_oe0)
        rtn0 = as_finite_array("rtn0", rtn0, (6,))
        self.rng = np.random.default_rng(int(seed))
        self.t_s = 0.0
        self.chief_eci = eci_from_oe(self.chief_oe0)
        self.deputy_eci = eci_from_rtn(self.chief_eci, rtn0)
        self.chief_mean_oe0 = (mean_elements_of_chief(self.chief_eci) if self.mean_elements
                               else self.chief_oe0.copy())
        self.history: list[NodeRecord] = []
        self.trajectory_t_s: list[float] = [0.0]
        self.trajectory_rtn: list[np.ndarray] = [self.true_rtn()]
        self._mean_cache: tuple[bytes, np.ndarray] | None = None

    # ------------------------------------------------------------------ truth views
    def chief_mean_oe(self) -> np.ndarray:
        """Planner's chief model at t_s: `chief_mean_oe0` with the J2 secular rates, (6,)."""
        return propagate_mean_oe(self.chief_mean_oe0, self.t_s)

    def true_rtn(self) -> np.ndarray:
        """Exact relative RTN state [m, m/s] of the deputy in the chief frame, (6,)."""
        return rtn_from_eci(self.chief_eci, self.deputy_eci)

    def true_roe_m(self) -> np.ndarray:
        """Exact a-scaled ROE [m], (6,), from the *osculating* elements of both spacecraft.

        Not the mean ROE the STM propagates: they carry the difference of the two spacecraft's
        J2 short-periodic terms (~0.1-0.3 % of the separation). Scale: the chief's osculating a.
        """
        return roe_from_oe(oe_from_eci(self.chief_eci), oe_from_eci(self.deputy_eci))

    def mean_roe_m(self) -> np.ndarray:
        """A-scaled ROE [m], (6,), from the orbit-averaged mean elements of both spacecraft.

        Each spacecraft's free motion is averaged over its own period centred on now
        (`mean_elements`); scale: the chief's mean a. About 20 ms; cached per state.
        """
        key = np.concatenate([self.chief_eci, self.deputy_eci]).tobytes()
        if self._mean_cache is None or self._mean_cache[0] != key:
            mean = mean_elements(np.vstack([self.chief_eci, self.deputy_eci]))
            self._mean_cache = (key, roe_from_oe(mean[0], mean[1]))
        return self._mean_cache[1].copy()

    def model_roe_m(self) -> np.ndarray:
        """The ROE [m] the guidance model works with: `mean_roe_m` or `true_roe_m`."""
        return self.mean_roe_m() if self.mean_elements else self.true_roe_m()

    # ------------------------------------------------------------------ sensors, actuators
    def nav_estimate(self, rng: np.random.Generator | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """A navigation fix: the model ROE (`model_roe_m`) plus an ARTMS-model error sample.

        The covariance is `uncertainty.nav_covariance` at the current state (a one-node
        horizon: its range is ||D Psi x|| with Psi at the planner's chief mean elements).
        Without an uncertainty model the estimate is exact with zero covariance.

        Args:
            rng: random generator (default: the simulator's).

        Returns:
            mean_roe_m (6,) [m] and its covariance (6, 6) [m^2].
        """
        rng = self.rng if rng is None else rng
        truth = self.model_roe_m()
        if self.uncertainty is None:
            return truth, np.zeros((6, 6))
        psi = psi_matrix(self.chief_mean_oe())
        cov = nav_covariance(truth[None], psi[None], self.uncertainty)[0]
        return truth + _gaussian(rng, cov), cov

    def execute_burn(self, dv_rtn_mps: object,
                     rng: np.random.Generator | None = None) -> np.ndarray:
        """Apply an impulsive burn with a Gates-model execution error to the deputy.

        The executed delta-v ``dv + e``, ``e ~ N(0, gates_covariance(dv))``, is added to the
        deputy's inertial velocity along the chief's current RTN axes, so the relative RTN
        velocity changes by exactly the executed delta-v. The node is appended to `history`
        with its post-burn model ROE (mean: pre-burn mean ROE plus the exact osculating change,
        whose first-order J2 error is ~1e-3 of the burn's ROE change).

        Args:
            dv_rtn_mps: (3,) commanded delta-v in RTN [m/s].
            rng: random generator (default: the simulator's).

        Returns:
            (3,) executed delta-v [m/s].

        Raises:
            InputError: on NaN/inf or a wrong shape.
        """
        rng = self.rng if rng is None else rng
        cmd = as_finite_array("dv_rtn_mps", dv_rtn_mps, (3,))
        executed = cmd.copy()
        if self.uncertainty is not None:
            executed = cmd + _gaussian(rng, gates_covariance(cmd[None], self.uncertainty)[0])
        pre_rtn = self.true_rtn()
        pre_osc = self.true_roe_m()
        pre_model = self.model_roe_m()
        basis, _ = rtn_frame(self.chief_eci)
        self.deputy_eci = self.deputy_eci.copy()
        self.deputy_eci[3:] += basis @ executed
        post_osc = self.true_roe_m()
        post_model = pre_model + (post_osc - pre_osc) if self.mean_elements else post_osc
        self.history.append(NodeRecord(self.t_s, pre_rtn, executed, cmd, post_model))
        self.trajectory_t_s.append(self.t_s)
        self.trajectory_rtn.append(self.true_rtn())
        return executed

    def skip_burn(self, dv_rtn_mps: object) -> None:
        """A burn that does not fire (a missed-burn fault): the node is recorded with the
        commanded delta-v and a zero executed one; the state is unchanged.

        Raises:
            InputError: on NaN/inf or a wrong shape.
        """
        cmd = as_finite_array("dv_rtn_mps", dv_rtn_mps, (3,))
        self.history.append(NodeRecord(self.t_s, self.true_rtn(), np.zeros(3), cmd,
                                       self.model_roe_m()))

    def advance(self, dt_s: float) -> None:
        """Propagate the truth by `dt_s` [s] (>= 0), recording samples for plots.

        Raises:
            InputError: on a negative or non-finite duration.
        """
        dt = _check_dt(dt_s)
        if dt == 0.0:
            return
        n_rec = max(1, int(np.ceil(dt / RECORD_STEP_S)))
        t_eval = np.linspace(0.0, dt, n_rec + 1)[1:]
        sol = _integrate(np.concatenate([self.chief_eci, self.deputy_eci]), dt, t_eval)
        for k, tk in enumerate(sol.t):
            self.trajectory_t_s.append(self.t_s + float(tk))
            self.trajectory_rtn.append(rtn_from_eci(sol.y[:6, k], sol.y[6:, k]))
        self.chief_eci = sol.y[:6, -1].copy()
        self.deputy_eci = sol.y[6:, -1].copy()
        self.t_s += dt

    def node_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """History as arrays: t (K,), pre-burn RTN (K, 6), executed dv (K, 3), post ROE (K, 6)."""
        if not self.history:
            return np.zeros(0), np.zeros((0, 6)), np.zeros((0, 3)), np.zeros((0, 6))
        return (np.array([h.t_s for h in self.history]),
                np.array([h.rtn for h in self.history]),
                np.array([h.dv_mps for h in self.history]),
                np.array([h.roe_post_m for h in self.history]))


def mean_elements_of_chief(chief_eci: object) -> np.ndarray:
    """Orbit-averaged mean elements (6,) of one inertial state (see `mean_elements`)."""
    return mean_elements(as_finite_array("chief_eci", chief_eci, (6,))[None])[0]


# --------------------------------------------------------------------------- reporting
def koz_switch_time_s(scenario: ScenarioConfig, chief_a_m: float, t0_s: float = 0.0) -> float:
    """Sim time [s] where the approach ellipsoid switches to the keep-out zone.

    Node `scenario.ae_to_koz_node` of the nominal grid (`n_orbits`, `n_nodes` over periods of
    `chief_a_m`) started at `t0_s` (the first plan's epoch), the planner's rule by node index;
    inf if the switch node is beyond the grid.
    """
    if scenario.ae_to_koz_node >= scenario.n_nodes:
        return float("inf")
    grid = time_grid_s(float(chief_a_m), scenario.n_orbits, scenario.n_nodes)
    return float(t0_s + grid[int(scenario.ae_to_koz_node)])


def run_safety_model(sim: RendezvousSim, uncertainty: UncertaintyConfig | None = None,
                     koz_switch_t_s: float | None = None) -> PassiveSafety | None:
    """PassiveSafety on a horizon at the run's executed node epochs (None if < 2 nodes).

    The horizon uses the planner's chief model (`chief_mean_oe0` at t = 0), so the drift
    maps are the ones the planner uses. The keep-out zone applies from the first node at or
    after `koz_switch_t_s` (within EPOCH_MATCH_S; default `koz_switch_time_s` from t = 0);
    before it, the approach ellipsoid.

    Args:
        sim: a simulator with executed nodes (strictly increasing epochs).
        uncertainty: None for the deterministic margin of the realised states (default); a
            model adds the q-sigma term of the chance constraint.
        koz_switch_t_s: sim time of the AE -> KOZ switch [s].
    """
    t = sim.node_arrays()[0]
    if t.size < 2 or np.any(np.diff(t) <= 0):
        return None
    if koz_switch_t_s is None:
        koz_switch_t_s = koz_switch_time_s(sim.scenario, sim.chief_mean_oe0[0])
    n_nodes = max(t.size, 3)
    switch = int(np.searchsorted(t, float(koz_switch_t_s) - EPOCH_MATCH_S, side="left"))
    return PassiveSafety(Horizon.build(sim.chief_mean_oe0, t), sim.scenario, uncertainty,
                         koz_switch_node=min(switch, n_nodes))


def run_outcome(sim: RendezvousSim, target_rtn: object,
                safety_model: PassiveSafety | None = None, n_replans: int = 0) -> dict:
    """Outcome of a run, as JSON-ready numbers.

    Passive safety of the *realised* trajectory: at every executed node the post-burn state
    (the simulator's model ROE of the truth) drifts freely for `t_safety` with the linear
    model, and the smallest margin ``min_tau (d - 1 - q sigma) * min semi-axis`` [m] over nodes
    and the whole drift arc (the continuous minimum of `PassiveSafety.evaluate`) is reported
    (AE before the switch, KOZ after; >= 0 is safe).

    Args:
        sim: the simulator after the run.
        target_rtn: (6,) the waypoint [m, m/s].
        safety_model: evaluator built on the run's node epochs (`run_safety_model`), or None
            to build the deterministic one (q sigma = 0: the truth is known).
        n_replans: number of plans the guidance sent.

    Returns:
        dict: miss_m (position error to the waypoint at the end [m]), velocity_error_mps,
        total_dv_mps (executed), commanded_dv_mps, min_safety_margin_m (None if < 2 nodes),
        min_range_m (over the recorded truth), n_burns, n_replans, final_t_s, final_rtn,
        target_rtn.

    Raises:
        InputError: on a bad target or a safety model whose node count does not match.
    """
    target = as_finite_array("target_rtn", target_rtn, (6,))
    rtn = sim.true_rtn()
    t, _, dv, roe_post = sim.node_arrays()
    model = run_safety_model(sim) if safety_model is None else safety_model
    margin = None
    if model is not None:
        if model.n_nodes != t.size:
            raise InputError("safety_model", f"has {model.n_nodes} nodes, the run {t.size}")
        margin = float(model.evaluate(roe_post, np.zeros((t.size, 3))).margin_m.min())
    cmd = np.array([h.dv_cmd_mps for h in sim.history]).reshape(-1, 3)
    traj = np.array(sim.trajectory_rtn)
    return {
        "miss_m": float(np.linalg.norm(rtn[:3] - target[:3])),
        "velocity_error_mps": float(np.linalg.norm(rtn[3:] - target[3:])),
        "total_dv_mps": float(np.linalg.norm(dv, axis=1).sum()),
        "commanded_dv_mps": float(np.linalg.norm(cmd, axis=1).sum()),
        "min_safety_margin_m": margin,
        "min_range_m": float(np.linalg.norm(traj[:, :3], axis=1).min()),
        "n_burns": int(t.size),
        "n_replans": int(n_replans),
        "final_t_s": float(sim.t_s),
        "final_rtn": rtn.tolist(),
        "target_rtn": target.tolist(),
    }
