"""Physics of the held-out generator: chamber programs, a gyro's thermal nodes, probes and noise.

Written from the physics and the close-the-loop issue only (nothing is imported from ``bench``):

* the chamber air follows a set-point program of soaks and ramps (rate-limited, first-order
  controller lag);
* the gyro has a case node fed by the air, one sensing node per channel fed by the case (each with its
  own time constant and a self-heating rise after power-on) and a base-plate node fed by the air;
* a DS18B20 probe sits on each channel's node and one on the base plate: read every 2 s (sample and
  hold in the gyro's rows), 0.0625 C steps, read noise and a fixed offset;
* gyro noise per axis: white (angle random walk), flicker (bias instability, a sum of Gauss-Markov
  processes spread over four decades, scaled to the IEEE 952 level 0.664 B at 100 s) and rate random
  walk.

Every array is per sample of one run; ``t`` is seconds since power-on (each run starts powered off
after a soak at its start temperature).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

PROBE_STEP_C = 0.0625            # DS18B20 12-bit resolution
PROBE_PERIOD_S = 2.0             # one conversion every 2 s
MAX_RAMP_C_PER_MIN = 5.0


def first_order(u: np.ndarray, dt: float, tau: float, y0: float | None = None) -> np.ndarray:
    """Exact zero-order-hold discretisation of dy/dt = (u - y) / tau, starting at ``y0`` (default u[0])."""
    a = float(np.exp(-dt / tau))
    start = float(u[0]) if y0 is None else float(y0)
    y, _ = lfilter([1.0 - a], [1.0, -a], u, zi=[a * start])
    return y


def program(segments, start_c: float, dt: float) -> np.ndarray:
    """Chamber set point per sample.  ``segments``: ("soak", seconds) or ("ramp", target_c, c_per_min)."""
    out = [np.array([start_c])]
    t = start_c
    for seg in segments:
        if seg[0] == "soak":
            n = max(1, int(round(seg[1] / dt)))
            out.append(np.full(n, t))
        else:
            target, rate = float(seg[1]), min(abs(float(seg[2])), MAX_RAMP_C_PER_MIN)
            n = max(1, int(np.ceil(abs(target - t) / (rate / 60.0 * dt))))
            out.append(np.linspace(t, target, n + 1)[1:])
            t = target
    return np.concatenate(out)


@dataclass
class Unit:
    """One gyro's thermal and noise constants (drawn once per case, shared by its two runs)."""
    tau_air: float
    tau_case: float
    tau_node: dict[str, float]        # node name -> time constant from the case (base: from the air)
    self_heat_c: dict[str, float]     # node -> rise after power-on
    tau_self_heat: float
    probe_on: dict[str, str]          # probe -> node
    probe_offset: dict[str, float]
    probe_phase: dict[str, float]     # when in the 2-s cycle each probe is read
    white: dict[str, float]           # deg/h per 1-s sample
    bias_instability: dict[str, float]
    rate_rw: dict[str, float]         # deg/h per sqrt(s)


NODES = ("nx", "ny", "nz", "base")


def draw_unit(rng: np.random.Generator, channels=("x", "y", "z"), flicker_scale: float = 1.0) -> Unit:
    nodes_perm = list(rng.permutation(["t1", "t2", "t3"]))
    probe_on = {nodes_perm[0]: "nx", nodes_perm[1]: "ny", nodes_perm[2]: "nz", "t4": "base"}
    return Unit(
        tau_air=float(rng.uniform(60, 150)),
        tau_case=float(rng.uniform(300, 900)),
        tau_node={"nx": float(rng.uniform(150, 1200)), "ny": float(rng.uniform(150, 1200)),
                  "nz": float(rng.uniform(150, 1200)), "base": float(rng.uniform(900, 2500))},
        self_heat_c={"nx": float(rng.uniform(0.5, 2.5)), "ny": float(rng.uniform(0.5, 2.5)),
                     "nz": float(rng.uniform(0.5, 2.5)), "base": float(rng.uniform(0.0, 0.6))},
        tau_self_heat=float(rng.uniform(600, 1800)),
        probe_on=probe_on,
        probe_offset={p: float(rng.normal(0, 0.15)) for p in probe_on},
        probe_phase={p: float(rng.choice([0.0, 1.0])) for p in probe_on},
        white={c: float(rng.uniform(0.12, 0.30)) for c in channels},
        bias_instability={c: float(rng.uniform(0.004, 0.012)) * flicker_scale for c in channels},
        rate_rw={c: float(rng.uniform(2e-5, 8e-5)) for c in channels},
    )


def channel_probe_map(unit: Unit) -> dict[str, str]:
    node_probe = {n: p for p, n in unit.probe_on.items()}
    return {"x": node_probe["nx"], "y": node_probe["ny"], "z": node_probe["nz"]}


def node_temperatures(unit: Unit, sp: np.ndarray, dt: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Air and node temperatures of one run (the unit soaked at the start temperature before power-on)."""
    n = len(sp)
    # the chamber's controller: rate limit then first-order air lag
    air = first_order(sp, dt, unit.tau_air)
    case = first_order(air, dt, unit.tau_case)
    t_on = np.arange(n) * dt
    heat = 1.0 - np.exp(-t_on / unit.tau_self_heat)
    nodes = {}
    for name in NODES:
        src = air if name == "base" else case
        nodes[name] = first_order(src, dt, unit.tau_node[name]) + unit.self_heat_c[name] * heat
    return air, nodes


def probe_truth(unit: Unit, nodes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The temperature at each probe's location (noise-free, continuous)."""
    return {p: nodes[node] for p, node in unit.probe_on.items()}


def probe_readings(unit: Unit, truth: dict[str, np.ndarray], t: np.ndarray,
                   rng: np.random.Generator) -> dict[str, np.ndarray]:
    """What the DS18B20s report: sampled every 2 s and held, offset, read noise, 0.0625 C steps."""
    out = {}
    for p, x in truth.items():
        conv = np.floor((t - unit.probe_phase[p]) / PROBE_PERIOD_S) * PROBE_PERIOD_S + unit.probe_phase[p]
        conv = np.clip(conv, t[0], None)
        held = np.interp(conv, t, x)
        noisy = held + unit.probe_offset[p] + rng.normal(0, 0.01, len(t))
        out[p] = np.round(noisy / PROBE_STEP_C) * PROBE_STEP_C
    return out


def _gm_allan_var(q: float, T: float, tau: float) -> float:
    """Allan variance at ``tau`` of a first-order Gauss-Markov process of variance q, time constant T."""
    x = tau / T
    return q * (T / tau) ** 2 * (4 * np.exp(-x) - np.exp(-2 * x) + 2 * x - 3)


def gyro_noise(unit: Unit, ch: str, n: int, dt: float, rng: np.random.Generator) -> np.ndarray:
    """White + flicker + rate random walk for one axis, deg/h per sample of period ``dt``."""
    white = rng.normal(0, unit.white[ch] / np.sqrt(dt), n)
    taus = np.logspace(1, 5, 9)              # 10 s .. 1e5 s, two per decade: ~1/f over the band
    gm = np.zeros(n)
    for T in taus:
        a = np.exp(-dt / T)
        e = rng.normal(0, np.sqrt(1 - a * a), n)
        gm += lfilter([1.0], [1.0, -a], e, zi=[a * rng.normal()])[0]
    # scale: Allan deviation of the flicker part at 100 s equals 0.664 B
    avar100 = sum(_gm_allan_var(1.0, T, 100.0) for T in taus)
    flicker = gm * (0.664 * unit.bias_instability[ch] / np.sqrt(avar100))
    rrw = np.cumsum(rng.normal(0, unit.rate_rw[ch] * np.sqrt(dt), n))
    return white + flicker + rrw


def derivative_per_min(x: np.ndarray, dt: float, window_s: float = 60.0) -> np.ndarray:
    """dx/dt in units per minute, central difference over ``window_s``."""
    k = max(1, int(round(window_s / dt / 2)))
    xp = np.concatenate([np.full(k, x[0]), x, np.full(k, x[-1])])
    return (xp[2 * k:] - xp[:-2 * k]) / (2 * k * dt) * 60.0


def relay(x: np.ndarray, width: float) -> np.ndarray:
    """Relay hysteresis: +1 once x has risen ``width`` above its last minimum, -1 once it has fallen
    ``width`` below its last maximum; before the first such move the state is the opposite of it."""
    out = np.empty(len(x))
    state = 0.0
    lo = hi = float(x[0])
    first = None
    for i, v in enumerate(x):
        if v > hi:
            hi = v
        if v < lo:
            lo = v
        if state <= 0 and v - lo >= width:
            state, hi = 1.0, v
        elif state >= 0 and hi - v >= width:
            state, lo = -1.0, v
        if first is None and state != 0:
            first = (i, state)
        out[i] = state
    if first is None:
        out[:] = 0.0
    else:
        out[:first[0]] = -first[1]
    return out


def duhem(x: np.ndarray, width: float) -> np.ndarray:
    """Gradual (Duhem) hysteresis: dm = |dx| / width * (sign(dx) - m): a memory in [-1, 1] that
    saturates over an excursion of a few ``width``; starts saturated opposite to the first move."""
    dx = np.diff(x, prepend=x[0])
    moves = np.flatnonzero(np.abs(x - x[0]) > width)
    m = -np.sign(x[moves[0]] - x[0]) if moves.size else 0.0
    out = np.empty(len(x))
    for i, d in enumerate(dx.tolist()):
        if d:
            m += abs(d) / width * ((1.0 if d > 0 else -1.0) - m)
        out[i] = m
    return out
