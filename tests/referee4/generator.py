"""From a program to a measured-data CSV: the bench hardware of one case, the physics of one run,
the gyro output of each channel and the data logger (sampling, averaging, outages)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from tests.referee4.effects import Signals
from tests.referee4.physics import (NoiseSpec, Probe, Program, ThermalNetwork, chamber_air,
                                    gyro_noise, quantise_output)

CHANNELS = ("x", "y", "z")
CHANNEL_PROBES = {"x": "t1", "y": "t2", "z": "t3"}
PROBES = ("t1", "t2", "t3", "t4")
LOGGERS = ("1s", "0.5s", "10s_avg")


@dataclass
class Hardware:
    """One gyro on its fixture in one chamber (kept for both runs of a case)."""
    network: ThermalNetwork
    probes: list[Probe]
    noise: NoiseSpec
    air_tau_s: float
    air_cycle_c: float
    air_cycle_s: float


def draw_hardware(rng: np.random.Generator, *, flicker_scale: float = 1.0) -> Hardware:
    net = ThermalNetwork(tau_case_air_s=rng.uniform(500, 1200), tau_core_case_s=rng.uniform(300, 900),
                         tau_plate_air_s=rng.uniform(2500, 6000), tau_case_plate_s=rng.uniform(1200, 3000),
                         self_heat_c=rng.uniform(1.5, 4.0))
    base = {"t1": (0.5, 0.4, 0.1, 0.0), "t2": (0.3, 0.6, 0.1, 0.0), "t3": (0.7, 0.2, 0.1, 0.0),
            "t4": (0.15, 0.0, 0.65, 0.2)}
    probes = []
    for name in PROBES:
        w = np.asarray(base[name]) * rng.uniform(0.8, 1.2, 4)
        w = w / w.sum()
        probes.append(Probe(name=name, weights=tuple(w), glue_tau_s=rng.uniform(20, 120),
                            offset_c=rng.uniform(-0.4, 0.4), fail_prob=rng.uniform(0.0005, 0.005)))
    noise = NoiseSpec(arw_dps_rth=float(np.exp(rng.uniform(np.log(0.002), np.log(0.008)))),
                      bias_inst_dph=flicker_scale * float(np.exp(rng.uniform(np.log(0.002), np.log(0.008)))),
                      rrw_dph_rth=float(np.exp(rng.uniform(np.log(0.0003), np.log(0.002)))),
                      quant_arcsec=float(rng.choice([0.0, 0.0, 0.2, 0.5])))
    return Hardware(network=net, probes=probes, noise=noise, air_tau_s=rng.uniform(120, 300),
                    air_cycle_c=rng.uniform(0.02, 0.12), air_cycle_s=rng.uniform(400, 900))


@dataclass
class Run:
    """The physics of one run at its physics step."""
    program: Program
    dt: float
    t: np.ndarray
    sp: np.ndarray
    air: np.ndarray
    powered: np.ndarray
    nodes: np.ndarray
    sig: Signals          # true probe temperatures and rates


def simulate(hw: Hardware, program: Program, dt: float, rng: np.random.Generator) -> Run:
    t = np.arange(0.0, program.end, dt)
    sp = program.setpoint(t)
    air = chamber_air(t, sp, rng, tau_s=hw.air_tau_s, cycle_amp_c=hw.air_cycle_c,
                      cycle_period_s=hw.air_cycle_s)
    powered = program.powered(t)
    nodes = hw.network.integrate(t, air, powered)
    temps = {p.name: p.true_temperature(dt, nodes, air) for p in hw.probes}
    rates = {k: np.gradient(v, t) * 60.0 for k, v in temps.items()}
    return Run(program=program, dt=dt, t=t, sp=sp, air=air, powered=powered, nodes=nodes,
               sig=Signals(t=t, temps=temps, rates=rates, power_on_s=program.power_on_times()))


def smooth_random(n: int, dt: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth random process (two cascaded first-order lags of white noise), unit std."""
    a = np.exp(-dt / tau_s)
    x = lfilter([1 - a], [1, -a], rng.normal(size=n + int(5 * tau_s / dt)))
    x = lfilter([1 - a], [1, -a], x)[-n:]
    return (x - x.mean()) / x.std()


def heater_node(run: Run, rng: np.random.Generator, *, period_scale: float) -> np.ndarray:
    """Temperature of an unmeasured electronics board held by its own bang-bang heater: a sawtooth
    whose duty cycle follows the case temperature (the board's ambient)."""
    tau = rng.uniform(300, 700) * period_scale
    a = np.exp(-run.dt / tau)
    setp = float(np.max(run.nodes[:, 0])) + 5.0
    band, heat = rng.uniform(0.3, 0.8), 25.0
    x, on = setp, False
    out = np.empty(run.t.size)
    for i, amb in enumerate(run.nodes[:, 0].tolist()):
        if x < setp - band:
            on = True
        elif x > setp + band:
            on = False
        target = amb + (heat if on else 0.0)
        x = a * x + (1 - a) * target
        out[i] = x
    return out - out.mean()


def gyro_output(run: Run, signal_dph: np.ndarray, noise: NoiseSpec, rng: np.random.Generator) -> np.ndarray:
    """What the gyro puts out (deg/h): signal + noise through the pulse quantiser; NaN while off."""
    out = quantise_output(signal_dph + gyro_noise(run.t.size, run.dt, noise, rng), run.dt,
                          noise.quant_arcsec, rng)
    return np.where(run.powered, out, np.nan)


@dataclass
class Logger:
    mode: str                                # "1s", "0.5s" or "10s_avg"
    outages: list[tuple[float, float]]       # (start, end) in run seconds: no rows at all

    @property
    def physics_dt(self) -> float:
        return 0.5 if self.mode == "0.5s" else 1.0

    @property
    def period_s(self) -> float:
        return {"1s": 1.0, "0.5s": 0.5, "10s_avg": 10.0}[self.mode]


def draw_outages(rng, duration_s: float) -> list[tuple[float, float]]:
    if rng.random() > 0.35:
        return []
    out = []
    for _ in range(int(rng.integers(1, 4))):
        start = rng.uniform(0.1, 0.9) * duration_s
        out.append((start, start + rng.uniform(60, 900)))
    return out


def log_run(run: Run, hw: Hardware, gyro: dict[str, np.ndarray], logger: Logger,
            rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The logged columns (NaN = empty cell)."""
    rec = {p.name: p.record(run.t, run.sig.temps[p.name], rng) for p in hw.probes}
    pv_idx = (np.floor(run.t / 5.0) * 5.0 / run.dt).astype(np.int64)
    pv = np.round(run.air[np.minimum(pv_idx, run.t.size - 1)] * 10.0) / 10.0
    cols = {"time_s": run.t.copy()}
    cols.update({f"gyro_{ch}": g for ch, g in gyro.items()})
    cols.update({f"temp_{k}": v for k, v in rec.items()})
    cols["power"] = run.powered.astype(float)
    cols["chamber_pv"] = pv
    cols["chamber_sp"] = np.round(run.sp * 10.0) / 10.0
    if logger.mode == "10s_avg":
        cols = _average(cols, int(round(logger.period_s / run.dt)))
    keep = np.ones(cols["time_s"].size, dtype=bool)
    for a, b in logger.outages:
        keep &= ~((cols["time_s"] >= a) & (cols["time_s"] < b))
    return {k: v[keep] for k, v in cols.items()}


def _average(cols: dict[str, np.ndarray], m: int) -> dict[str, np.ndarray]:
    n = cols["time_s"].size // m
    out = {}
    for k, v in cols.items():
        blk = v[: n * m].reshape(n, m)
        if k == "power":
            out[k] = blk.min(axis=1)
        elif k.startswith("gyro_"):
            out[k] = blk.mean(axis=1)                 # NaN when the gyro was off in any part
        elif k in ("chamber_pv", "chamber_sp"):
            out[k] = blk[:, -1]
        elif k == "time_s":
            out[k] = blk.mean(axis=1)
        else:
            with np.errstate(invalid="ignore"):
                cnt = np.sum(~np.isnan(blk), axis=1)
                s = np.nansum(blk, axis=1)
            out[k] = np.where(cnt > 0, s / np.maximum(cnt, 1), np.nan)
    return out


def format_csv(cols: dict[str, np.ndarray], meta: dict[str, str]) -> str:
    """Measured-data CSV v1 text: metadata lines, header, rows; NaN written as an empty cell."""
    fmt = {"time_s": "{:.1f}", "power": "{:.0f}", "chamber_pv": "{:.1f}", "chamber_sp": "{:.1f}"}
    lines = [f"# {k}: {v}" for k, v in meta.items()]
    names = list(cols)
    lines.append(",".join(names))
    columns = []
    for name in names:
        f = fmt.get(name, "{:.4f}" if name.startswith("temp_") else "{:.5f}")
        columns.append(["" if np.isnan(x) else f.format(x) for x in cols[name].tolist()])
    lines.extend(",".join(row) for row in zip(*columns))
    return "\n".join(lines) + "\n"
