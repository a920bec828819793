"""Physics of the third referee: a chamber, a coupled thermal network, DS18B20 probes, gyro noise.

Written from the physics notes only (nothing from the product's simulator or analysis):

* chamber air follows a set-point program (soaks and ramps) through its controller, a first-order
  lag of ``air_tau_s`` with a little turbulence;
* a lumped network (case, base plate, one sensing node per channel, an electronics node) with
  conductances to its neighbours, integrated exactly per 1-s step (matrix exponential of the linear
  system, zero-order hold on the inputs: air temperature and electronics dissipation);
* DS18B20 probes glued to nodes: glue lag, a fixed offset, read noise and 0.0625 C quantisation;
* gyro noise at IEEE 952 Allan levels: white (angle random walk), flicker (bias instability,
  two-sided PSD B^2/(2 pi f), Allan floor 0.664 B) and rate random walk.

Every function is pure over numpy arrays and takes its random generator explicitly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

DS18B20_STEP_C = 0.0625


# ---------------------------------------------------------------- temperature program and chamber

def setpoint_program(segments: list[tuple[str, float, float]], start_c: float, dt: float = 1.0) -> np.ndarray:
    """Set point on a ``dt`` grid.  ``segments``: ("soak", minutes, _) or ("ramp", target_c, c_per_min)."""
    out = [np.array([start_c])]
    cur = start_c
    for kind, a, b in segments:
        if kind == "soak":
            n = int(round(a * 60.0 / dt))
            out.append(np.full(n, cur))
        elif kind == "ramp":
            target, rate = a, abs(b)
            n = max(1, int(round(abs(target - cur) / rate * 60.0 / dt)))
            out.append(np.linspace(cur, target, n + 1)[1:])
            cur = target
        else:
            raise ValueError(f"unknown program segment {kind!r}")
    return np.concatenate(out)


def chamber_air(setpoint: np.ndarray, rng: np.random.Generator, tau_s: float = 120.0,
                turbulence_c: float = 0.03, dt: float = 1.0) -> np.ndarray:
    """Chamber air: the controller's first-order response to the set point plus slow turbulence."""
    a = np.exp(-dt / tau_s)
    air = np.empty_like(setpoint)
    x = setpoint[0]
    for k, sp in enumerate(setpoint):
        x = a * x + (1 - a) * sp
        air[k] = x
    turb = lowpass(rng.standard_normal(setpoint.size), 60.0, dt)
    turb *= turbulence_c / max(np.std(turb), 1e-12)
    return air + turb


def lowpass(x: np.ndarray, tau_s: float, dt: float = 1.0, x0: float | None = None) -> np.ndarray:
    """First-order lag y' = (x - y)/tau, exact for a piecewise-constant input."""
    from scipy.signal import lfilter

    a = np.exp(-dt / tau_s)
    y0 = x[0] if x0 is None else x0
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * y0])
    return y


# ---------------------------------------------------------------- thermal network

@dataclass(frozen=True)
class Network:
    """Nodes and conductances.  ``heat_capacity`` J/K per node; ``links`` (i, j, W/K); ``to_air`` W/K
    per node; ``heated`` index of the node that dissipates the electronics power (or -1)."""
    names: tuple[str, ...]
    heat_capacity: np.ndarray
    links: tuple[tuple[int, int, float], ...]
    to_air: np.ndarray
    heated: int

    def index(self, name: str) -> int:
        return self.names.index(name)


def draw_network(rng: np.random.Generator, channels: tuple[str, ...]) -> Network:
    """A gyro unit: case (to air), base plate (to air and case), one sensing node per channel (to the
    case and the base), an electronics board (to the case; self-heating).  Time constants from a few
    minutes (case) to about an hour (sensing nodes, base)."""
    names = ("case", "base", *[f"sense_{c}" for c in channels], "board")
    n = len(names)
    cap = np.empty(n)
    to_air = np.zeros(n)
    links: list[tuple[int, int, float]] = []
    cap[0] = rng.uniform(400, 800)             # case
    to_air[0] = cap[0] / rng.uniform(300, 900)  # tau 5-15 min to air
    cap[1] = rng.uniform(800, 2000)            # base plate
    to_air[1] = cap[1] / rng.uniform(1500, 4000)
    links.append((0, 1, cap[1] / rng.uniform(1500, 3500)))
    for k in range(len(channels)):
        i = 2 + k
        cap[i] = rng.uniform(150, 400)
        links.append((0, i, cap[i] / rng.uniform(400, 1800)))      # case -> sensing node
        links.append((1, i, cap[i] / rng.uniform(1500, 6000)))     # base -> sensing node
    b = n - 1
    cap[b] = rng.uniform(60, 150)
    links.append((0, b, cap[b] / rng.uniform(300, 900)))
    return Network(names, cap, tuple(links), to_air, b)


def integrate_network(net: Network, air: np.ndarray, power_w: np.ndarray, t0: np.ndarray | None = None,
                      dt: float = 1.0) -> np.ndarray:
    """Node temperatures (n_nodes, n_steps).  Exact discretisation of C dT/dt = -L T + g_air T_air + P e_b."""
    n = len(net.names)
    lap = np.diag(net.to_air.copy())
    for i, j, g in net.links:
        lap[i, i] += g
        lap[j, j] += g
        lap[i, j] -= g
        lap[j, i] -= g
    cinv = 1.0 / net.heat_capacity
    a = -cinv[:, None] * lap
    bmat = np.zeros((n, 2))
    bmat[:, 0] = cinv * net.to_air
    if net.heated >= 0:
        bmat[net.heated, 1] = cinv[net.heated]
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = a * dt
    m[:n, n:] = bmat * dt
    e = expm(m)
    ad, bd = e[:n, :n], e[:n, n:]
    u = np.vstack([air, power_w])
    if t0 is None:   # steady state at the first inputs
        t0 = np.linalg.solve(-a, bmat @ u[:, 0])
    out = np.empty((n, air.size))
    x = np.asarray(t0, dtype=float)
    bu = bd @ u
    for k in range(air.size):
        out[:, k] = x
        x = ad @ x + bu[:, k]
    return out


# ---------------------------------------------------------------- DS18B20 probes

@dataclass(frozen=True)
class Probe:
    name: str          # column name without temp_, e.g. "t1"
    node: str          # network node it is glued to
    glue_tau_s: float
    offset_c: float
    noise_c: float


def probe_physical(node_temp: np.ndarray, probe: Probe, dt: float = 1.0) -> np.ndarray:
    """The probe die's temperature: the node through the glue lag (no offset, no quantisation)."""
    return lowpass(node_temp, probe.glue_tau_s, dt)


def probe_reading(physical: np.ndarray, probe: Probe, rng: np.random.Generator) -> np.ndarray:
    """What the DS18B20 reports: offset + read noise, quantised to 0.0625 C."""
    raw = physical + probe.offset_c + probe.noise_c * rng.standard_normal(physical.size)
    return np.round(raw / DS18B20_STEP_C) * DS18B20_STEP_C


# ---------------------------------------------------------------- gyro noise

def flicker(n: int, b_dph: float, rng: np.random.Generator, dt: float = 1.0) -> np.ndarray:
    """Flicker (1/f) rate noise: two-sided PSD B^2/(2 pi f) (IEEE 952), i.e. one-sided B^2/(pi f), so that
    the Allan deviation floor is sqrt(2 ln 2 / pi) B = 0.664 B."""
    m = 1 << int(np.ceil(np.log2(4 * n)))          # generate longer, keep a stretch: no wrap-around
    f = np.fft.rfftfreq(m, dt)
    spec = np.zeros(f.size, dtype=complex)
    psd = np.zeros(f.size)
    psd[1:] = b_dph ** 2 / (np.pi * f[1:])
    # white of unit variance has one-sided PSD 2 dt; shape it to psd
    w = np.fft.rfft(rng.standard_normal(m))
    spec[:] = w * np.sqrt(psd / (2 * dt))
    x = np.fft.irfft(spec, m)
    start = int(rng.integers(0, m - n))
    return x[start:start + n]


def gyro_noise(n: int, white_dph: float, b_dph: float, k_rrw: float, rng: np.random.Generator,
               dt: float = 1.0) -> np.ndarray:
    """White (std per sample at ``dt``) + flicker (bias instability B) + rate random walk (K, deg/h/sqrt(s))."""
    white = white_dph * rng.standard_normal(n)
    rrw = np.cumsum(k_rrw * np.sqrt(dt) * rng.standard_normal(n))
    return white + flicker(n, b_dph, rng, dt) + rrw - rrw.mean()


def allan_dev(x: np.ndarray, m: int) -> float:
    """Non-overlapping Allan deviation of rate samples at cluster size ``m``."""
    k = x.size // m
    means = x[: k * m].reshape(k, m).mean(axis=1)
    return float(np.sqrt(0.5 * np.mean(np.diff(means) ** 2)))


# ---------------------------------------------------------------- memory operators

def play(x: np.ndarray, width: float) -> np.ndarray:
    """Backlash (play) operator of total width ``width``: the output follows x only when x is more than
    width/2 away.  x - play(x) is a gradual hysteresis bounded by +-width/2 (Prandtl-Ishlinskii cell)."""
    h = width / 2.0
    out = np.empty_like(x)
    p = x[0]
    for k, v in enumerate(x):
        if v > p + h:
            p = v - h
        elif v < p - h:
            p = v + h
        out[k] = p
    return out


def relay(x: np.ndarray, width: float, start: float = 0.0) -> np.ndarray:
    """Direction relay: +1 once x has risen ``width`` above its last minimum, -1 once it has fallen
    ``width`` below its last maximum (heating/cooling branch of a hysteresis loop)."""
    out = np.empty_like(x)
    state = start if start else 1.0
    lo = hi = x[0]
    for k, v in enumerate(x):
        lo = min(lo, v)
        hi = max(hi, v)
        if state < 0 and v > lo + width:
            state, hi = 1.0, v
        elif state > 0 and v < hi - width:
            state, lo = -1.0, v
        out[k] = state
    return out
