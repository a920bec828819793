"""Gyro physics for the simulated bench and for offline dataset generation (one code path).

``GyroPhysics(scenario, clock_start, inputs)`` integrates, on a fixed grid of ``substep_s`` from
``clock_start``:

* a lumped linear thermal network (chamber air -> case/mount nodes where the probes are glued ->
  internal sensing-element nodes; self-heating while powered), discretised exactly: modal
  decomposition of the (symmetrisable) system matrix, each mode integrated in closed form with the
  inputs linear between grid points (first-order hold), so any step size is stable;
* the optional effect states (first-order thermal lag of the temperatures, Duhem-type heating /
  cooling hysteresis state) and the correlated noise (Gauss-Markov, rate random walk).

The gyro output (per channel, deg/h internally, deg/s in ``GyroSample`` like the KVH wire format):

    out_i = (1 + 1e-6 SF_i(T)) * (M @ (R^T Omega_ie_ENU + table_rate_body))_i + bias_i + noise_i

Omega_ie in ENU = 15.041 deg/h * [0, cos(lat), sin(lat)] (calibration-notes section 6), R =
body_to_level (columns = body axes in East-North-Up), M = installation matrix (seed 000 eq 1).
bias_i = intercept + declared terms of temperatures (C, centred on t0_c), their rates (C/min,
exact derivatives of the network state) and gradients (seed 000 eq 3-5, seed 001) + switched-on
effects (calibration-notes section 3).  HRG resonance frequency = cubic of the resonator node
temperature (seed 002 eq 2) + per-channel offset + white noise.

Thread-safe (one lock); state advances lazily and monotonically: ``advance_to(t)`` commits whole
grid steps, values at a time between grid points are computed exactly from the last committed
grid point without committing (correlated noise held).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from bench.errors import PlanError
from bench.signal.geometry import OrientationError, code_matrix, earth_rate_enu, validate_canonical_code
from bench.sim.noise import STREAM_ACCEL, STREAM_FREQ, CorrelatedNoise, first_order_recursion, RandomStepLevels, WhiteNoise, stream_rng
from bench.sim.scenario import ChannelBias, ChannelNoise, Factor, Scenario, ThermalNetwork, parse_term

_MAX_CHUNK = 200_000          # grid steps integrated per vectorised chunk (memory bound)


@dataclass(frozen=True)
class GyroSample:
    """One gyro output sample, the unit the gyro stream simulator turns into a frame.

    rate_dps: as output by the device in deg/s (bias, Earth rate, table rate through scale factor
    and installation matrix, noise); accel_g: specific force on body axes in g; temperature_c: the
    gyro's internal sensor; freq_hz: HRG resonance frequencies or None; valid: status bits.
    """

    rate_dps: tuple[float, float, float]
    accel_g: tuple[float, float, float]
    temperature_c: float
    freq_hz: tuple[float, float, float] | None = None
    valid: bool = True


# ------------------------------------------------------------------------------------------------
# Inputs from the rest of the bench
# ------------------------------------------------------------------------------------------------


@dataclass
class InputBatch:
    air_c: np.ndarray                 # (n,) chamber air, C
    body_to_level: np.ndarray         # (n, 3, 3) columns = body x, y, z in ENU
    table_rate_body_dps: np.ndarray   # (n, 3) deg/s
    powered: np.ndarray               # (n,) bool
    power_on_time: np.ndarray         # (n,) bench time of the last power-on, NaN when off


@dataclass
class PhysicsInputs:
    """Callables supplied by the integrator (chamber, turntable, power supply models).

    ``batch(times)`` evaluates them on an array of times; subclasses with array data (offline
    generation) override it with a vectorised version.
    """

    air_temp_c: Callable[[float], float]
    body_to_level: Callable[[float], Sequence[Sequence[float]]]
    table_rate_body_dps: Callable[[float], Sequence[float]]
    powered: Callable[[float], bool]
    power_on_time: Callable[[float], float | None]

    def batch(self, times: np.ndarray) -> InputBatch:
        times = np.asarray(times, dtype=float)
        on_times = [self.power_on_time(float(t)) for t in times]
        return InputBatch(
            air_c=np.array([float(self.air_temp_c(float(t))) for t in times]),
            body_to_level=np.array([np.asarray(self.body_to_level(float(t)), dtype=float) for t in times]).reshape(-1, 3, 3),
            table_rate_body_dps=np.array([np.asarray(self.table_rate_body_dps(float(t)), dtype=float) for t in times]).reshape(-1, 3),
            powered=np.array([bool(self.powered(float(t))) for t in times], dtype=bool),
            power_on_time=np.array([np.nan if v is None else float(v) for v in on_times]),
        )


def orientation_matrix(code: str) -> np.ndarray:
    """Body-to-level rotation for an orientation code such as ``NUE`` (body x North, y Up, z East).

    Letters as in seed 000's eight-position test and the measured-data CSV; columns = body axes in
    ENU (``bench.signal.geometry.code_matrix``).  Raises PlanError for anything that is not an
    upper-case right-handed code.
    """
    try:
        return code_matrix(validate_canonical_code(code))
    except OrientationError as exc:
        raise PlanError(str(exc)) from None


# ------------------------------------------------------------------------------------------------
# Exact first-order-hold discretisation
# ------------------------------------------------------------------------------------------------


def _foh_coeffs(lam: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For dz/dt = lam z + w(t), w linear over a step h: z1 = phi z0 + c0 w0 + c1 w1 (lam < 0)."""
    x = lam * h
    phi = np.exp(x)
    g1 = h * np.where(np.abs(x) < 1e-6, 1.0 + x / 2, np.expm1(x) / np.where(x == 0, 1.0, x))
    q = h * np.where(np.abs(x) < 1e-6, 0.5 + x / 6, (np.expm1(x) - x) / np.where(x == 0, 1.0, x * x))
    return phi, g1 - q, q


def _foh_step(lam: np.ndarray, dt: np.ndarray, z0: np.ndarray, w0: np.ndarray, w1: np.ndarray) -> np.ndarray:
    """One exact step per row: dt (n, 1), z0/w0/w1 (n, m)."""
    phi, c0, c1 = _foh_coeffs(lam[None, :], dt)
    return phi * z0 + c0 * w0 + c1 * w1


def _foh_filter(lam: np.ndarray, h: float, z0: np.ndarray, w0: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Propagate modes ``lam`` (m,) from state z0 over n steps of h with inputs w (n, m); w0 = input at z0."""
    phi, c0, c1 = _foh_coeffs_cached(lam, h)
    prev = np.vstack([w0[None, :], w[:-1]])
    x = c1 * w + c0 * prev
    return first_order_recursion(phi, x, z0)


_FOH_CACHE: dict[tuple[bytes, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _foh_coeffs_cached(lam: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_foh_coeffs`` for a fixed grid step: the same few (modes, step) pairs on every instant."""
    key = (lam.tobytes(), float(h))
    hit = _FOH_CACHE.get(key)
    if hit is None:
        if len(_FOH_CACHE) > 64:
            _FOH_CACHE.clear()
        hit = _FOH_CACHE[key] = _foh_coeffs(lam, h)
    return hit


class ThermalModel:
    """Linear network of ``ThermalNetwork``: C dT/dt = -K T + g_air T_air + P powered.

    K = Laplacian(links) + diag(g_air) is symmetric positive definite (every node has a path to the
    air, checked by the scenario), so A = -C^-1 K has real negative eigenvalues: with
    S = C^-1/2 K C^-1/2 = Q diag(s) Q^T, modes z = Q^T C^1/2 T, lam = -s.
    """

    def __init__(self, network: ThermalNetwork) -> None:
        self.names = list(network.nodes)
        idx = {n: i for i, n in enumerate(self.names)}
        n = len(self.names)
        cap = np.array([network.nodes[k].capacity_j_per_k for k in self.names])
        g_air = np.array([network.nodes[k].to_air_w_per_k for k in self.names])
        heat = np.array([network.nodes[k].heat_w for k in self.names])
        k_mat = np.diag(g_air)
        for link in network.links:
            a, b = idx[link.a], idx[link.b]
            k_mat[a, a] += link.w_per_k
            k_mat[b, b] += link.w_per_k
            k_mat[a, b] -= link.w_per_k
            k_mat[b, a] -= link.w_per_k
        self.k_mat = k_mat
        self.cap = cap
        self.a_mat = -k_mat / cap[:, None]
        self.b_mat = np.column_stack([g_air / cap, heat / cap])      # inputs u = [T_air, powered]
        c_half = np.sqrt(cap)
        s_mat = k_mat / np.outer(c_half, c_half)
        s, q = np.linalg.eigh(s_mat)
        self.lam = -s
        self.v = q / c_half[:, None]              # T = V z
        self.v_inv = q.T * c_half[None, :]        # z = V^-1 T
        self.bm = self.v_inv @ self.b_mat         # modal input matrix (m, 2)
        self.g_air, self.heat = g_air, heat
        self.size = n

    def steady_state(self, air_c: float, powered: bool) -> np.ndarray:
        return np.linalg.solve(self.k_mat, self.g_air * air_c + self.heat * float(powered))

    def time_constants_s(self) -> np.ndarray:
        return -1.0 / self.lam

    def inputs(self, air_c: np.ndarray, powered: np.ndarray) -> np.ndarray:
        return np.column_stack([air_c, powered.astype(float)])

    def propagate(self, z0: np.ndarray, u0: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
        """Modal states after each of n steps (n, m); u (n, 2) inputs at the step ends."""
        return _foh_filter(self.lam, h, z0, self.bm @ u0, u @ self.bm.T)

    def temperatures(self, z: np.ndarray) -> np.ndarray:
        return z @ self.v.T

    def rates_c_per_min(self, temps: np.ndarray, u: np.ndarray) -> np.ndarray:
        return 60.0 * (temps @ self.a_mat.T + u @ self.b_mat.T)


# ------------------------------------------------------------------------------------------------
# The gyro
# ------------------------------------------------------------------------------------------------


@dataclass
class _State:
    """Committed state at grid time ``t``."""

    t: float
    z: np.ndarray             # thermal modes
    u: np.ndarray             # thermal inputs (air, powered) at t
    temps: np.ndarray         # node temperatures at t
    lag: np.ndarray           # lagged node temperatures at t
    hyst: float               # hysteresis state in [-1, 1]
    hyst_rate: float          # driver rate at t (C/min)
    corr: np.ndarray          # correlated noise per channel at t (deg/h)


@dataclass
class _GridStates:
    """Committed states at a run of grid times (arrays indexed by time first)."""

    t: np.ndarray
    z: np.ndarray
    u: np.ndarray
    temps: np.ndarray
    lag: np.ndarray
    hyst: np.ndarray
    hyst_rate: np.ndarray
    corr: np.ndarray

    def extend(self, more: "_GridStates") -> "_GridStates":
        return _GridStates(*(np.concatenate([getattr(self, f), getattr(more, f)])
                             for f in ("t", "z", "u", "temps", "lag", "hyst", "hyst_rate", "corr")))


@dataclass
class Trajectory:
    """Everything the outputs depend on, at n times (arrays indexed by time first)."""

    times: np.ndarray
    inputs: InputBatch
    temps: np.ndarray          # (n, nodes) C
    rates: np.ndarray          # (n, nodes) C/min
    lag: np.ndarray            # (n, nodes) C (equal to temps when no lag effect)
    lag_rates: np.ndarray      # (n, nodes) C/min
    hyst: np.ndarray           # (n,)
    corr: np.ndarray           # (n, 3) deg/h
    z: np.ndarray | None = None    # (n, m) thermal modes (grid trajectories only)
    u: np.ndarray | None = None    # (n, 2) thermal inputs (grid trajectories only)


@dataclass
class Outputs:
    """Vectorised outputs at the times of a trajectory (units in names)."""

    times: np.ndarray
    rate_dph: np.ndarray       # (n, 3) gyro output, deg/h
    bias_dph: np.ndarray       # (n, 3) true bias incl. effects and correlated noise, no white noise
    accel_g: np.ndarray        # (n, 3)
    sensor_c: np.ndarray       # (n,) internal temperature
    probes_c: dict[str, np.ndarray]
    freq_hz: np.ndarray | None  # (n, 3)
    valid: np.ndarray          # (n,) bool
    powered: np.ndarray        # (n,) bool
    trajectory: Trajectory


class _Term:
    def __init__(self, coef: float, factors: tuple[Factor, ...], node_index: Callable[[str], int]) -> None:
        self.coef = coef
        self.factors = [(f.kind, node_index(f.a), node_index(f.b) if f.b else -1, f.power) for f in factors]

    def evaluate(self, temps: np.ndarray, rates: np.ndarray, t0: float) -> np.ndarray:
        value = np.full(temps.shape[0], self.coef)
        for kind, a, b, power in self.factors:
            if kind == "temp":
                base = temps[:, a] - t0
            elif kind == "rate":
                base = rates[:, a]
            elif kind == "grad":
                base = temps[:, a] - temps[:, b]
            else:
                base = rates[:, a] - rates[:, b]
            value = value * base ** power
        return value


class GyroPhysics:
    """The simulated gyro.  See module docstring for the model and units.

    ``output_period_s``: averaging period of one output sample, sets the white-noise level
    (60*ARW/sqrt(period) deg/h); the stream server passes 1/data_rate.  ``substep_s`` overrides
    the scenario's fixed integration step.
    """

    def __init__(self, scenario: Scenario, clock_start: float, inputs: PhysicsInputs, *,
                 output_period_s: float | None = None, substep_s: float | None = None) -> None:
        self.scenario = scenario
        self.inputs = inputs if hasattr(inputs, "batch") else PhysicsInputs(
            inputs.air_temp_c, inputs.body_to_level, inputs.table_rate_body_dps, inputs.powered,
            inputs.power_on_time)
        self.h = float(substep_s if substep_s is not None else scenario.thermal.substep_s)
        if self.h <= 0:
            raise ValueError(f"substep_s must be > 0, got {self.h}")
        self.output_period_s = float(output_period_s if output_period_s is not None else self.h)
        self.clock_start = float(clock_start)
        self.thermal = ThermalModel(scenario.thermal)
        self._lock = threading.RLock()
        self._node_idx = {n: i for i, n in enumerate(self.thermal.names)}
        self.channels = scenario.channels
        self._setup_model()
        first = self.inputs.batch(np.array([self.clock_start]))
        u0 = self.thermal.inputs(first.air_c, first.powered)[0]
        temps0 = self.thermal.steady_state(float(first.air_c[0]), bool(first.powered[0]))
        hyst_rate0 = 0.0
        self._state = _State(self.clock_start, self.thermal.v_inv @ temps0, u0, temps0, temps0.copy(), 0.0,
                             hyst_rate0, np.array([c.value for c in self._corr]))
        self._t_now = self.clock_start
        self._cache: tuple[float, Trajectory] | None = None

    # -- model set-up ------------------------------------------------------------------------------

    def node_index(self, name: str) -> int:
        return self._node_idx[self.scenario.node_of(name)]

    def _setup_model(self) -> None:
        sc, eff = self.scenario, self.scenario.effects
        names = sc.temperature_names()
        self._terms: list[list[_Term]] = []
        self._bias: list[ChannelBias] = []
        for ch in self.channels:
            spec = sc.bias.get(ch, ChannelBias())
            self._bias.append(spec)
            self._terms.append([_Term(c, parse_term(t, names), self.node_index) for t, c in spec.terms.items()])
        lag = eff.thermal_lag
        self._lag_tau = lag.tau_s if lag else None
        self._lag_channels = set(lag.channels or self.channels) if lag else set()
        seed = sc.seed
        self._corr = [CorrelatedNoise(sc.noise.get(ch, ChannelNoise()), seed, i) for i, ch in enumerate(self.channels)]
        self._white = [WhiteNoise(sc.noise.get(ch, ChannelNoise()), seed, i) for i, ch in enumerate(self.channels)]
        self._rng_accel = stream_rng(seed, STREAM_ACCEL)
        self._rng_freq = stream_rng(seed, STREAM_FREQ)
        steps = eff.unexplained.random_steps if eff.unexplained else None
        self._steps = RandomStepLevels(steps, seed, self.clock_start, len(steps.channels)) if steps else None
        inst = eff.installation
        self._install = np.array(inst.matrix, dtype=float) if inst else np.eye(3)
        self._earth_enu = earth_rate_enu(sc.latitude_deg)
        self._probe_idx = {p: self._node_idx[n] for p, n in sc.probes.items()}
        self._sensor_idx = self.node_index(sc.sensor_node)
        self._own_idx = [self.node_index(sc.channel_nodes[ch]) for ch in self.channels]

    # -- integration -------------------------------------------------------------------------------

    def _advance_grid(self, n: int) -> Trajectory:
        """Integrate and commit n grid steps; return the trajectory at the new grid points."""
        st, th, h = self._state, self.thermal, self.h
        times = st.t + h * np.arange(1, n + 1)
        batch = self.inputs.batch(times)
        u = th.inputs(batch.air_c, batch.powered)
        z = th.propagate(st.z, st.u, u, h)
        temps = th.temperatures(z)
        rates = th.rates_c_per_min(temps, u)
        lag, lag_rates = self._lagged(st.lag, st.temps, temps, rates, h)
        hyst, hyst_rate = self._hysteresis(st.hyst, st.hyst_rate, temps, rates, h)
        corr = np.column_stack([c.advance(n, h) for c in self._corr])
        self._state = _State(float(times[-1]), z[-1].copy(), u[-1].copy(), temps[-1].copy(), lag[-1].copy(),
                             float(hyst[-1]), hyst_rate, corr[-1].copy())
        return Trajectory(times, batch, temps, rates, lag, lag_rates, hyst, corr, z, u)

    def _between(self, times: np.ndarray, base: "_GridStates") -> Trajectory:
        """Exact states at ``times`` from the grid states ``base`` (each time from the latest grid
        point at or before it), without committing; correlated noise is held at the grid value."""
        th = self.thermal
        times = np.asarray(times, dtype=float)
        b = np.clip(np.searchsorted(base.t, times + 1e-9, side="right") - 1, 0, base.t.size - 1)
        dt = np.maximum(times - base.t[b], 0.0)[:, None]
        batch = self.inputs.batch(times)
        u = th.inputs(batch.air_c, batch.powered)
        z = _foh_step(th.lam, dt, base.z[b], base.u[b] @ th.bm.T, u @ th.bm.T)
        temps = th.temperatures(z)
        rates = th.rates_c_per_min(temps, u)
        if self._lag_tau is None:
            lag, lag_rates = temps, rates
        else:
            lam = np.full(temps.shape[1], -1.0 / self._lag_tau)
            lag = _foh_step(lam, dt, base.lag[b], base.temps[b] / self._lag_tau, temps / self._lag_tau)
            lag_rates = self._lag_rates(temps, lag, rates)
        hyst = base.hyst[b].copy()
        hy = self.scenario.effects.hysteresis
        if hy is not None:
            r_mid = 0.5 * (base.hyst_rate[b] + rates[:, self.node_index(hy.driver)]) / 60.0
            sign = np.sign(r_mid)
            moved = sign != 0
            hyst[moved] = sign[moved] + (hyst[moved] - sign[moved]) * np.exp(-np.abs(r_mid[moved]) * dt[moved, 0] / hy.width_c)
        return Trajectory(times, batch, temps, rates, lag, lag_rates, hyst, base.corr[b].copy())

    @staticmethod
    def _on_grid(times: np.ndarray, traj: Trajectory) -> Trajectory | None:
        """The rows of a just-integrated grid trajectory at ``times`` when every time is one of its
        grid points (frames on the integration grid: nothing to interpolate), else None."""
        idx = np.minimum(np.searchsorted(traj.times, times), traj.times.size - 1)
        if not np.array_equal(traj.times[idx], times):
            return None
        return _select(traj, idx)

    def _committed(self) -> "_GridStates":
        st = self._state
        return _GridStates(np.array([st.t]), st.z[None, :], st.u[None, :], st.temps[None, :], st.lag[None, :],
                           np.array([st.hyst]), np.array([st.hyst_rate]), st.corr[None, :])

    def _lag_rates(self, temps, lag, rates):
        if self._lag_tau is None:
            return rates
        return 60.0 * (temps - lag) / self._lag_tau

    def _lagged(self, lag0, temps0, temps, rates, h):
        if self._lag_tau is None:
            return temps, rates
        lam = np.full(temps.shape[1], -1.0 / self._lag_tau)
        lag = _foh_filter(lam, h, lag0, temps0 / self._lag_tau, temps / self._lag_tau)
        return lag, self._lag_rates(temps, lag, rates)

    def _hysteresis(self, h0: float, r0: float, temps, rates, h) -> tuple[np.ndarray, float]:
        """Duhem state: dh/dt = (r - |r| h)/W; r taken as the mean of the step's end-point rates."""
        hy = self.scenario.effects.hysteresis
        n = temps.shape[0]
        if hy is None:
            return np.zeros(n), 0.0
        r_end = rates[:, self.node_index(hy.driver)] / 60.0          # C/s
        r_mid = 0.5 * (np.concatenate([[r0 / 60.0], r_end[:-1]]) + r_end)
        decay = np.exp(-np.abs(r_mid) * h / hy.width_c).tolist()
        sign = np.sign(r_mid).tolist()
        out = [0.0] * n
        state = h0
        for k in range(n):
            if sign[k] != 0.0:
                state = sign[k] + (state - sign[k]) * decay[k]
            out[k] = state
        return np.array(out), float(r_end[-1] * 60.0)

    # -- outputs -----------------------------------------------------------------------------------

    def _outputs(self, traj: Trajectory, period_s: float) -> Outputs:
        sc, eff = self.scenario, self.scenario.effects
        n = traj.times.size
        b = traj.inputs
        on = b.powered
        # time since power-on; +inf when powered with an unknown on-time (long warmed up), NaN when off
        t_on = np.where(on & np.isnan(b.power_on_time), np.inf, traj.times - b.power_on_time)
        bias = np.zeros((n, 3))
        for i, ch in enumerate(self.channels):
            spec = self._bias[i]
            use_lag = ch in self._lag_channels
            temps = traj.lag if use_lag else traj.temps
            rates = traj.lag_rates if use_lag else traj.rates
            col = np.full(n, spec.intercept_dph)
            for term in self._terms[i]:
                col += term.evaluate(temps, rates, spec.t0_c)
            if eff.hysteresis and ch in eff.hysteresis.amplitude_dph:
                col += eff.hysteresis.amplitude_dph[ch] * traj.hyst
            if eff.warmup and ch in eff.warmup.amplitude_dph:
                col += eff.warmup.amplitude_dph[ch] * np.where(on, np.exp(-np.where(np.isnan(t_on), np.inf, t_on) / eff.warmup.tau_s), 0.0)
            if eff.cross_channel_temperature and ch in eff.cross_channel_temperature:
                cc = eff.cross_channel_temperature[ch]
                src = self._own_idx[self.channels.index(cc.source_channel)]
                col += cc.dph_per_c * (traj.temps[:, src] - spec.t0_c)
            if eff.time_drift and ch in eff.time_drift.dph_per_h:
                col += eff.time_drift.dph_per_h[ch] * (traj.times - self.clock_start) / 3600.0
            if eff.unexplained:
                for s in eff.unexplained.sinusoids:
                    if s.channel == ch:
                        col += s.amplitude_dph * np.sin(2 * np.pi * (traj.times - self.clock_start) / s.period_s + s.phase_rad)
            bias[:, i] = col
        if self._steps is not None:
            levels = self._steps.levels(traj.times)
            for j, ch in enumerate(eff.unexplained.random_steps.channels):
                bias[:, self.channels.index(ch)] += levels[:, j]
        force = b.body_to_level[:, 2, :]                         # R^T [0,0,1]: +1 g along body up
        if eff.g_sensitivity:
            for i, ch in enumerate(self.channels):
                k = eff.g_sensitivity.dph_per_g.get(ch)
                if k is not None:
                    bias[:, i] += force @ np.asarray(k)
        bias += traj.corr
        body_rate = np.einsum("nji,j->ni", b.body_to_level, self._earth_enu) + 3600.0 * b.table_rate_body_dps
        chan_in = body_rate @ self._install.T
        sf = self._scale_factor_ppm(traj)
        white = np.column_stack([w.draw(n, period_s) for w in self._white])
        rate = (1.0 + 1e-6 * sf) * chan_in + bias + white
        accel = force + sc.accel_noise_g * self._rng_accel.standard_normal((n, 3)) if sc.accel_noise_g else force.copy()
        freq = None
        if sc.hrg is not None:
            freq = np.column_stack([
                np.polyval(np.asarray(sc.hrg.channel_coefficients.get(ch, sc.hrg.coefficients)),
                           traj.temps[:, self.node_index(sc.sensing_nodes[ch])]) + sc.hrg.offsets_hz.get(ch, 0.0)
                for ch in self.channels])
            if sc.hrg.noise_hz > 0:
                freq = freq + sc.hrg.noise_hz * self._rng_freq.standard_normal((n, 3))
        valid = on & (np.where(np.isnan(t_on), -np.inf, t_on) >= sc.startup_invalid_s)
        probes = {p: traj.temps[:, k] for p, k in self._probe_idx.items()}
        return Outputs(traj.times, rate, bias, accel, traj.temps[:, self._sensor_idx], probes, freq, valid, on, traj)

    def _scale_factor_ppm(self, traj: Trajectory) -> np.ndarray:
        sf = self.scenario.effects.scale_factor_temperature
        out = np.zeros((traj.times.size, 3))
        if sf is None:
            return out
        for i, ch in enumerate(self.channels):
            idx = self.node_index(sf.driver) if sf.driver else self._own_idx[i]
            out[:, i] = sf.ppm.get(ch, 0.0) + sf.ppm_per_c.get(ch, 0.0) * (traj.temps[:, idx] - sf.t0_c)
        return out

    # -- public API --------------------------------------------------------------------------------

    def advance_to(self, t: float) -> None:
        """Integrate up to bench time t (whole grid steps committed; later times never rewind)."""
        with self._lock:
            t = float(t)
            n = int(math.floor((t - self._state.t) / self.h + 1e-9))
            while n > 0:
                chunk = min(n, _MAX_CHUNK)
                self._advance_grid(chunk)
                n -= chunk
            if t > self._t_now:
                self._t_now = t

    def _current(self) -> Trajectory:
        if self._cache is None or self._cache[0] != self._t_now:
            self._cache = (self._t_now, self._between(np.array([max(self._t_now, self._state.t)]), self._committed()))
        return self._cache[1]

    def sample(self, t: float) -> GyroSample:
        """Advance to t and return one output sample (white noise drawn fresh per call)."""
        return self.sample_many([t])[0]

    def sample_many(self, times: Sequence[float]) -> list[GyroSample]:
        """Samples at non-decreasing ``times`` (e.g. all frames due since the last call), vectorised:
        same values as calling ``sample`` for each time in turn, at a fraction of the cost."""
        times = np.asarray(times, dtype=float)
        if times.size == 0:
            return []
        if np.any(np.diff(times) < 0):
            raise ValueError("sample_many needs non-decreasing times")
        with self._lock:
            base = self._committed()
            t_end = float(times[-1])
            n = int(math.floor((t_end - self._state.t) / self.h + 1e-9))
            grid = None
            if 0 < n <= _MAX_CHUNK:
                grid = self._advance_grid(n)
            elif n > 0:                                  # a long jump: commit, then sample from the end
                self.advance_to(t_end)
                base = self._committed()
            self._t_now = max(self._t_now, t_end)
            ts = np.maximum(times, base.t[0])
            traj = self._on_grid(ts, grid) if grid is not None else None
            if traj is None:
                if grid is not None:
                    hy = self.scenario.effects.hysteresis
                    hyst_rate = grid.rates[:, self.node_index(hy.driver)] if hy else np.zeros(n)
                    base = base.extend(_GridStates(grid.times, grid.z, grid.u, grid.temps, grid.lag, grid.hyst,
                                                   hyst_rate, grid.corr))
                traj = self._between(ts, base)
            if t_end == self._state.t:     # the state at the newest instant, for probe_temperatures
                self._cache = (t_end, _select(traj, np.array([times.size - 1])))
            return gyro_samples(self._outputs(traj, self.output_period_s), range(times.size))

    def run_grid(self, n_steps: int) -> Outputs:
        """Integrate and commit ``n_steps`` grid steps; the outputs at every new grid point with the
        white noise of one output period each (frames on the integration grid: the values
        ``sample_many`` gives for those times, computed for a whole block at once)."""
        with self._lock:
            traj = self._advance_grid(n_steps)
            self._t_now = max(self._t_now, self._state.t)
            return self._outputs(traj, self.output_period_s)

    def checkpoint(self) -> tuple:
        """Everything ``advance_to`` / ``sample_many`` change (committed state and the random
        streams' positions), for ``rollback``; the random steps only grow in time order and need none."""
        with self._lock:
            return (self._state, self._t_now, self._cache,
                    [c.get_state() for c in self._corr], [w.get_state() for w in self._white],
                    self._rng_accel.bit_generator.state, self._rng_freq.bit_generator.state)

    def rollback(self, cp: tuple) -> None:
        """Back to a ``checkpoint`` (the caller then integrates again from there)."""
        with self._lock:
            self._state, self._t_now, self._cache, corr, white, accel, freq = cp
            for c, st in zip(self._corr, corr):
                c.set_state(st)
            for w, st in zip(self._white, white):
                w.set_state(st)
            self._rng_accel.bit_generator.state = accel
            self._rng_freq.bit_generator.state = freq

    def probe_temperatures(self) -> dict[str, float]:
        """True temperature at each probe position (C) at the last advance time."""
        with self._lock:
            traj = self._current()
            return {p: float(traj.temps[0, k]) for p, k in self._probe_idx.items()}

    def node_temperatures(self) -> dict[str, float]:
        with self._lock:
            traj = self._current()
            return {n: float(traj.temps[0, i]) for n, i in self._node_idx.items()}

    def record(self, n_steps: int, *, period_s: float | None = None, every: int = 1) -> Outputs:
        """Vectorised: integrate n_steps grid steps from the committed state and return the outputs
        at every ``every``-th new grid point (offline generation; same code as ``advance_to`` +
        ``sample``).  ``period_s``: output averaging period for the white noise (default every*h)."""
        if n_steps <= 0:
            raise ValueError("record needs at least one step")
        with self._lock:
            pieces = []
            remaining = n_steps
            done = 0
            while remaining > 0:
                chunk = min(remaining, _MAX_CHUNK - (_MAX_CHUNK % every))
                traj = self._advance_grid(chunk)
                sel = np.arange(chunk)[(np.arange(chunk) + done + 1) % every == 0]
                pieces.append(self._outputs(_select(traj, sel), period_s or every * self.h))
                remaining -= chunk
                done += chunk
            self._t_now = max(self._t_now, self._state.t)
            return _concat(pieces)


def gyro_samples(out: Outputs, rows) -> list[GyroSample]:
    """The ``GyroSample`` (wire units: deg/s, zero rate while unpowered) of each row of ``out``."""
    table = SampleRows(out)
    return [table[k] for k in rows]


class SampleRows:
    """The ``GyroSample`` of each row of ``out`` (``gyro_samples``), its columns converted to Python numbers
    in one pass: a lockstep block serves a row or two per instant for hundreds of instants, and numpy's
    per-element conversions cost more than the samples themselves.  The same values: a rate is the row's
    deg/h divided by 3600 (one IEEE division, in numpy or in Python alike), (0, 0, 0) while unpowered."""

    __slots__ = ("_rate", "_accel", "_sensor", "_freq", "_valid")

    def __init__(self, out: Outputs) -> None:
        self._rate = np.where(out.powered[:, None], out.rate_dph / 3600.0, 0.0).tolist()
        self._accel = out.accel_g.tolist()
        self._sensor = out.sensor_c.tolist()
        self._freq = None if out.freq_hz is None else out.freq_hz.tolist()
        self._valid = out.valid.tolist()

    def __getitem__(self, k: int) -> GyroSample:
        freq = self._freq
        return GyroSample(tuple(self._rate[k]), tuple(self._accel[k]), self._sensor[k],
                          None if freq is None else tuple(freq[k]), self._valid[k])


def _select(traj: Trajectory, idx: np.ndarray) -> Trajectory:
    b = traj.inputs
    return Trajectory(traj.times[idx], InputBatch(b.air_c[idx], b.body_to_level[idx], b.table_rate_body_dps[idx],
                                                  b.powered[idx], b.power_on_time[idx]),
                      traj.temps[idx], traj.rates[idx], traj.lag[idx], traj.lag_rates[idx], traj.hyst[idx],
                      traj.corr[idx])


def _concat(parts: list[Outputs]) -> Outputs:
    if len(parts) == 1:
        return parts[0]
    cat = np.concatenate
    tr = [p.trajectory for p in parts]
    ib = [t.inputs for t in tr]
    traj = Trajectory(cat([t.times for t in tr]),
                      InputBatch(cat([b.air_c for b in ib]), cat([b.body_to_level for b in ib]),
                                 cat([b.table_rate_body_dps for b in ib]), cat([b.powered for b in ib]),
                                 cat([b.power_on_time for b in ib])),
                      cat([t.temps for t in tr]), cat([t.rates for t in tr]), cat([t.lag for t in tr]),
                      cat([t.lag_rates for t in tr]), cat([t.hyst for t in tr]), cat([t.corr for t in tr]))
    return Outputs(traj.times, cat([p.rate_dph for p in parts]), cat([p.bias_dph for p in parts]),
                   cat([p.accel_g for p in parts]), cat([p.sensor_c for p in parts]),
                   {k: cat([p.probes_c[k] for p in parts]) for k in parts[0].probes_c},
                   None if parts[0].freq_hz is None else cat([p.freq_hz for p in parts]),
                   cat([p.valid for p in parts]), cat([p.powered for p in parts]), traj)
