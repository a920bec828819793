"""Physics of the fourth referee: a chamber, a gyro's thermal network, DS18B20 probes and gyro noise.

Written from the physics, not from the product: nothing here imports ``bench``.

Chamber: the controller drives the air toward a piecewise-linear set point with a first-order lag and
a rate limit, plus the small limit cycle of its on/off refrigeration stage.

Gyro thermal network (linear, lumped): ``case`` (housing, coupled to the air and the mounting plate),
``core`` (sensing block, coupled to the case, heated by the gyro's own dissipation while powered) and
``plate`` (heavy mounting fixture, coupled to the air and the case).  Each node has its own time
constant; the network is integrated exactly for a zero-order-hold input (matrix exponential).

Probes: each DS18B20 sits at a mix of nodes, behind its glue (a first-order lag of 20-120 s), has a
calibration offset, converts every 2 s, is read as a 12-bit value (0.0625 C steps) and sometimes
fails to convert (the logger writes an empty cell).  The *true* probe temperature (smooth, no offset,
no quantisation) is what the gyro physics and the effects use; the recorded one is what the product
and the oracle see.

Gyro noise (IEEE 952 terms): white angle random walk N (deg/sqrt(h)), flicker bias instability B
(deg/h, ADEV floor 0.664 B), rate random walk K (deg/h/sqrt(h)) and, for pulse-output gyros, angle
quantisation Q (arcsec), accumulated so that it never drifts.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter

DS18B20_LSB_C = 0.0625
DS18B20_PERIOD_S = 2.0
SEC_PER_H = 3600.0


# --------------------------------------------------------------------------------------------
# chamber program

@dataclass
class Program:
    """Piecewise-linear set point (breakpoints) and the gyro's power intervals, in run seconds."""
    times: list[float] = field(default_factory=lambda: [0.0])
    temps: list[float] = field(default_factory=list)
    power: list[tuple[float, float]] = field(default_factory=list)   # (on, off) intervals

    @classmethod
    def start(cls, temp: float) -> "Program":
        return cls(times=[0.0], temps=[float(temp)])

    @property
    def end(self) -> float:
        return self.times[-1]

    def soak(self, minutes: float) -> "Program":
        self.times.append(self.end + 60.0 * minutes)
        self.temps.append(self.temps[-1])
        return self

    def ramp(self, target: float, rate_c_per_min: float) -> "Program":
        minutes = abs(target - self.temps[-1]) / rate_c_per_min
        self.times.append(self.end + 60.0 * minutes)
        self.temps.append(float(target))
        return self

    def power_on_at(self, t: float, off_at: float | None = None) -> "Program":
        self.power.append((float(t), float(off_at) if off_at is not None else np.inf))
        return self

    def setpoint(self, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self.times, self.temps)

    def powered(self, t: np.ndarray) -> np.ndarray:
        on = np.zeros(t.shape, dtype=bool)
        for a, b in self.power:
            on |= (t >= a) & (t < b)
        return on

    def power_on_times(self) -> list[float]:
        return [a for a, _ in self.power]


def chamber_air(t: np.ndarray, sp: np.ndarray, rng: np.random.Generator, *, tau_s: float,
                max_rate_c_per_min: float = 3.0, cycle_amp_c: float = 0.05,
                cycle_period_s: float = 600.0) -> np.ndarray:
    """Air temperature: rate-limited first-order follower of the set point plus the compressor's
    limit cycle and a little turbulence."""
    dt = float(t[1] - t[0])
    a = np.exp(-dt / tau_s)
    step_max = max_rate_c_per_min / 60.0 * dt
    out = np.empty_like(sp)
    x = float(sp[0])
    for i, s in enumerate(sp.tolist()):
        dx = (1.0 - a) * (s - x)
        if dx > step_max:
            dx = step_max
        elif dx < -step_max:
            dx = -step_max
        x += dx
        out[i] = x
    phase = rng.uniform(0, 2 * np.pi)
    period = cycle_period_s * (1.0 + 0.1 * np.sin(2 * np.pi * t / 7200.0 + rng.uniform(0, 6.3)))
    out += cycle_amp_c * np.sin(2 * np.pi * np.cumsum(dt / period) + phase)
    turb = lfilter([1 - np.exp(-dt / 60.0)], [1, -np.exp(-dt / 60.0)], rng.normal(0, 0.05, sp.size))
    return out + turb


# --------------------------------------------------------------------------------------------
# gyro thermal network

@dataclass
class ThermalNetwork:
    tau_case_air_s: float      # case <-> air
    tau_core_case_s: float     # core <-> case
    tau_plate_air_s: float     # plate <-> air
    tau_case_plate_s: float    # case <-> plate
    self_heat_c: float         # steady core rise over the case when powered (C)

    def matrices(self):
        """dx/dt = M x + N u, x = [case, core, plate], u = [air, power]."""
        ca, cc, pa, cp = (1 / self.tau_case_air_s, 1 / self.tau_core_case_s, 1 / self.tau_plate_air_s,
                          1 / self.tau_case_plate_s)
        m = np.array([[-(ca + cc + cp), cc, cp],
                      [cc * 0.5, -cc * 0.5, 0.0],          # the core is twice as heavy as the case
                      [cp * 0.3, 0.0, -(pa + cp * 0.3)]])   # the plate is heavier still
        heat = self.self_heat_c * cc * 0.5                   # W/C scaled: core rise ~ self_heat_c
        n = np.array([[ca, 0.0], [0.0, heat], [pa, 0.0]])
        return m, n

    def integrate(self, t: np.ndarray, air: np.ndarray, power: np.ndarray) -> np.ndarray:
        dt = float(t[1] - t[0])
        m, n = self.matrices()
        # exact ZOH discretisation through the augmented matrix
        aug = np.zeros((5, 5))
        aug[:3, :3] = m
        aug[:3, 3:] = n
        e = expm(aug * dt)
        ad, bd = e[:3, :3], e[:3, 3:]
        u = np.column_stack([air, power.astype(float)])
        # equilibrium at the first input
        x = np.linalg.solve(-m, n @ u[0])
        out = np.empty((t.size, 3))
        a = ad.tolist()
        b = bd.tolist()
        x0, x1, x2 = x.tolist()
        for i, (ua, up) in enumerate(u.tolist()):
            out[i, 0], out[i, 1], out[i, 2] = x0, x1, x2
            x0, x1, x2 = (a[0][0] * x0 + a[0][1] * x1 + a[0][2] * x2 + b[0][0] * ua + b[0][1] * up,
                          a[1][0] * x0 + a[1][1] * x1 + a[1][2] * x2 + b[1][0] * ua + b[1][1] * up,
                          a[2][0] * x0 + a[2][1] * x1 + a[2][2] * x2 + b[2][0] * ua + b[2][1] * up)
        return out


def first_order_lag(x: np.ndarray, dt: float, tau_s: float, x0: float | None = None) -> np.ndarray:
    """Exact first-order lag of a uniformly sampled signal (ZOH), starting at ``x0`` (default x[0])."""
    if tau_s <= 0:
        return x.copy()
    a = np.exp(-dt / tau_s)
    start = x[0] if x0 is None else x0
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * start])
    return y


@dataclass
class Probe:
    name: str
    weights: tuple[float, float, float, float]   # case, core, plate, air
    glue_tau_s: float
    offset_c: float
    fail_prob: float                             # per conversion

    def true_temperature(self, dt: float, nodes: np.ndarray, air: np.ndarray) -> np.ndarray:
        w = np.asarray(self.weights)
        mix = nodes @ w[:3] + air * w[3]
        return first_order_lag(mix, dt, self.glue_tau_s)

    def record(self, t: np.ndarray, true_c: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """What the logger writes at times ``t``: the last completed 2-s conversion, offset, 12-bit
        quantised, NaN when that conversion failed (single failures and short bus-glitch bursts)."""
        conv_idx = np.floor(t / DS18B20_PERIOD_S).astype(np.int64)
        n_conv = int(conv_idx.max()) + 1
        conv_t = np.arange(n_conv) * DS18B20_PERIOD_S
        vals = np.interp(conv_t, t, true_c) + self.offset_c
        vals = np.round(vals / DS18B20_LSB_C) * DS18B20_LSB_C
        fail = rng.random(n_conv) < self.fail_prob
        n_bursts = rng.poisson(n_conv * self.fail_prob / 40.0)
        for start in rng.integers(0, n_conv, n_bursts):
            fail[start:start + int(rng.integers(5, 30))] = True
        vals[fail] = np.nan
        return vals[conv_idx]


# --------------------------------------------------------------------------------------------
# gyro noise

@dataclass
class NoiseSpec:
    arw_dps_rth: float       # N, deg/sqrt(h)
    bias_inst_dph: float     # B, deg/h (flicker, ADEV floor 0.664 B)
    rrw_dph_rth: float       # K, deg/h/sqrt(h)
    quant_arcsec: float      # Q, angle quantum (0 = none)

    def white_sigma_dph(self, dt: float) -> float:
        """Std of one dt-sample of the white term in deg/h: N / sqrt(tau in h)."""
        return self.arw_dps_rth / np.sqrt(dt / SEC_PER_H)


def flicker_noise(n: int, dt: float, b_dph: float, rng: np.random.Generator) -> np.ndarray:
    """Flicker rate noise with one-sided PSD B^2 / (pi f) (IEEE 952 writes the two-sided
    B^2 / (2 pi f)), i.e. ADEV = sqrt(2 ln 2 / pi) B = 0.664 B on its floor (FFT shaping of white
    noise over twice the length, first half kept: no wrap-around)."""
    if b_dph <= 0:
        return np.zeros(n)
    m = 2 * n
    w = rng.normal(0.0, 1.0, m)                  # unit white: one-sided PSD 2 dt
    spec = np.fft.rfft(w)
    f = np.fft.rfftfreq(m, dt)
    shape = np.zeros_like(f)
    shape[1:] = np.sqrt(b_dph ** 2 / (np.pi * f[1:]) / (2 * dt))
    return np.fft.irfft(spec * shape, m)[:n]


def gyro_noise(n: int, dt: float, spec: NoiseSpec, rng: np.random.Generator) -> np.ndarray:
    """White + flicker + rate random walk, deg/h, at the physics step (quantisation is applied by
    :func:`quantise_output` after the signal is added)."""
    white = rng.normal(0.0, spec.white_sigma_dph(dt), n)
    flick = flicker_noise(n, dt, spec.bias_inst_dph, rng)
    k_per_s = spec.rrw_dph_rth / 60.0            # deg/h per sqrt(s)
    rrw = np.cumsum(rng.normal(0.0, k_per_s * np.sqrt(dt), n))
    return white + flick + rrw


def quantise_output(rate_dph: np.ndarray, dt: float, quant_arcsec: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Pulse output: the angle is accumulated and read as whole quanta; the rate of each sample is
    the difference of two readings over dt (the error never accumulates)."""
    if quant_arcsec <= 0:
        return rate_dph
    q_deg = quant_arcsec / 3600.0
    angle = np.cumsum(rate_dph / SEC_PER_H * dt) + rng.uniform(0, q_deg)
    counts = np.floor(angle / q_deg)
    counts = np.concatenate([[np.floor((angle[0] - rate_dph[0] / SEC_PER_H * dt) / q_deg)], counts])
    return np.diff(counts) * q_deg / dt * SEC_PER_H


def allan_deviation(y: np.ndarray, dt: float, taus_s) -> np.ndarray:
    """Overlapping Allan deviation of a rate series (for the generator's own checks)."""
    phase = np.concatenate([[0.0], np.cumsum(y) * dt])
    out = []
    for tau in taus_s:
        m = int(round(tau / dt))
        d = phase[2 * m:] - 2 * phase[m:-m] + phase[:-2 * m]
        out.append(np.sqrt(np.mean(d ** 2) / (2 * (m * dt) ** 2)))
    return np.asarray(out)
