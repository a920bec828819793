"""Synthetic thermal runs with known truth, generated with numpy, for the close-loop tests.

The chamber air follows a set-point program with a +-5 C/min rate limit; four probes follow the air
through first-order lags of different time constants (so they disagree and lag during ramps); the
gyro bias is a declared static cubic in t1 plus whatever hidden effects a test asks for, plus white
noise.  Everything is deterministic for a given seed.
"""
from __future__ import annotations

import numpy as np

from bench.fit.base import Dataset
from bench.fit.effects import first_order_lag, relay_state

DT = 2.0
PROBE_TAUS = {"t1": 600.0, "t2": 900.0, "t3": 1500.0, "t4": 2400.0}
STATIC = (0.10, 0.02, 4e-4, 6e-6)       # A0..A3 about 25 C, deg/h
NOISE_DPH = 0.08                        # white noise per sample


def chamber_profile(segments, start_c=25.0, dt=DT):
    """segments: ("hold", seconds) or ("ramp", target_c, c_per_min)."""
    temps = [start_c]
    t = start_c
    for seg in segments:
        if seg[0] == "hold":
            temps.extend([t] * int(seg[1] / dt))
        else:
            target, rate = seg[1], abs(seg[2])
            step = rate / 60.0 * dt * np.sign(target - t)
            while abs(target - t) > abs(step):
                t += step
                temps.append(t)
            t = target
            temps.append(t)
    air = np.array(temps)
    return np.arange(len(air)) * dt, air


TRAIN_PROFILE = [("hold", 3600), ("ramp", 60, 1.0), ("hold", 5400), ("ramp", -20, 0.5), ("hold", 5400),
                 ("ramp", 45, 2.0), ("hold", 3600), ("ramp", 0, 1.0), ("hold", 3600), ("ramp", 30, 0.25),
                 ("hold", 3600)]
VALIDATE_PROFILE = [("hold", 1800), ("ramp", -10, 0.7), ("hold", 7200), ("ramp", 55, 1.5), ("hold", 3600),
                    ("ramp", 10, 0.3), ("hold", 5400), ("ramp", 40, 1.2), ("hold", 3600)]
# 3302 s of training and 1402 s of validation at dt=1: just above the close-loop minimum lengths
# (bench.fit.closeloop.MIN_TRAIN_S, MIN_VALIDATE_S), for tests about storage, jobs and pages rather than
# about what the analysis can resolve
SHORT_TRAIN_PROFILE = [("hold", 300), ("ramp", 55, 2.0), ("hold", 600), ("ramp", 15, 2.0), ("hold", 300)]
SHORT_VALIDATE_PROFILE = [("hold", 150), ("ramp", 45, 2.0), ("hold", 250), ("ramp", 35, 2.0), ("hold", 100)]


def make_run(profile, hidden: dict | None = None, seed: int = 0, power_cycles: int = 0, probes=PROBE_TAUS, dt=DT,
             positions: tuple[str, ...] = ("NUE",), table_rate_dps: float = 0.0) -> tuple[Dataset, np.ndarray]:
    """Returns the dataset and the true hidden-effect contribution (deg/h) on channel x."""
    hidden = hidden or {}
    rng = np.random.default_rng(seed)
    t, air = chamber_profile(profile, dt=dt)
    n = len(t)
    cols: dict[str, np.ndarray] = {"time_s": t, "chamber_pv": air}
    for name, tau in probes.items():
        true_t = first_order_lag(air, t, tau)
        cols[f"temp_{name}"] = np.round((true_t + rng.normal(0, 0.005, n)) / 0.0625) * 0.0625
    t1_true = first_order_lag(air, t, PROBE_TAUS["t1"])
    u = t1_true - 25.0
    bias = STATIC[0] + STATIC[1] * u + STATIC[2] * u ** 2 + STATIC[3] * u ** 3
    rate1 = np.gradient(t1_true, t) * 60.0
    extra = np.zeros(n)
    if "thermal_lag" in hidden:
        ts = first_order_lag(t1_true, t, hidden["thermal_lag"]) - 25.0
        extra += (STATIC[1] * ts + STATIC[2] * ts ** 2 + STATIC[3] * ts ** 3) - (STATIC[1] * u + STATIC[2] * u ** 2 + STATIC[3] * u ** 3)
    if "gradient" in hidden:
        extra += hidden["gradient"] * (t1_true - first_order_lag(air, t, probes["t3"]))
    if "rate" in hidden:
        extra += hidden["rate"] * rate1
    if "rate_squared" in hidden:
        extra += hidden["rate_squared"] * rate1 ** 2
    if "temp_rate_cross" in hidden:
        extra += hidden["temp_rate_cross"] * u * rate1
    if "hysteresis" in hidden:
        extra += hidden["hysteresis"] * relay_state(rate1, 0.05)
    if "time_drift" in hidden:
        extra += hidden["time_drift"] * t / 3600.0
    if "disturbance" in hidden:
        amp, period = hidden["disturbance"]
        extra += amp * np.sin(2 * np.pi * t / period + 0.3)
    power = np.ones(n)
    if power_cycles:
        edges = np.linspace(0, n, power_cycles + 1).astype(int)
        since = np.zeros(n)
        for a, b in zip(edges[:-1], edges[1:]):
            off = a + (b - a) // 10           # first tenth of each cycle: power off
            power[a:off] = 0
            since[off:b] = t[off:b] - t[off]
        if "warmup" in hidden:
            amp, tau = hidden["warmup"]
            extra += np.where(power > 0, amp * np.exp(-since / tau), 0.0)
    cols["power"] = power
    orient = np.array([positions[int(i)] for i in np.floor(np.arange(n) / n * len(positions))], dtype=object)
    cols["orientation"] = orient
    if "g_sensitivity" in hidden:
        from bench.fit.effects import body_axes_enu
        up = body_axes_enu(orient)[:, 0, 2]
        extra += hidden["g_sensitivity"] * up
    if table_rate_dps:
        rate_tbl = np.where((np.arange(n) // 900) % 2 == 0, table_rate_dps, -table_rate_dps)
        cols["table_rate_dps"] = rate_tbl
        omega = rate_tbl * 3600.0
        bias = bias + omega                                   # unit scale factor, sensed on x
        if "scale_factor_temperature" in hidden:
            extra += hidden["scale_factor_temperature"] * omega * u
    if "cross_channel_temperature" in hidden:
        # the y channel's own sensor (another place in the block, its own electronics heating)
        ty = first_order_lag(air, t, 2000.0) + 1.5 * np.sin(t / 7000.0)
        cols["temp_y"] = np.round(ty / 0.0625) * 0.0625
        v = ty - 25.0
        extra += hidden["cross_channel_temperature"] * (0.5 * v + 0.03 * v ** 2 + 1e-3 * v ** 3)
    y = bias + extra + rng.normal(0, NOISE_DPH, n)
    cols["gyro_x"] = y
    return Dataset(cols, {"gyro_id": "SYN-1", "sample_period_s": str(dt)}), extra
