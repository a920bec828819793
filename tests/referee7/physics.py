"""Referee 7 physics: chamber, thermal network, effect regressors, unrecorded drivers, gyro noise.

Conventions of this module (our own, not the product's):

* Everything is simulated on a 1-s grid ``k = 0..n-1`` (seconds since the start of a run).  Sampling,
  averaging and logging artefacts are applied afterwards by ``logger.py``.
* Temperatures are degrees C, rates of change are C/min (``rate`` columns), gyro bias is deg/h.
* A *unit* (one gyro with three channels x, y, z and four probes) is a dict of physical constants drawn
  once per case and shared by its TRAIN and VALIDATE runs (same hardware, two different tests).
* Thermal network nodes: ``air`` (chamber, an input), ``mount`` (t4, heavy structure), ``case``,
  ``bx``/``by``/``bz`` (boards carrying probes t1/t2/t3), plus hidden "element" nodes used for
  thermal-lag effects (first-order lag of one probe node, started in equilibrium).
* Probe node temperatures returned here are TRUE temperatures (no offset, noise or quantisation).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

PROBES = ("t1", "t2", "t3", "t4")
NODE_OF_PROBE = {"t1": "bx", "t2": "by", "t3": "bz", "t4": "mount"}


# ----------------------------------------------------------------------------- chamber setpoint
def setpoint_profile(kind: str, n: int, lo: float, hi: float, rng) -> np.ndarray:
    """Chamber setpoint (C) on the 1-s grid.  kind: stair | ramp | sine | random."""
    t = np.arange(n, dtype=float)
    if kind == "stair":
        steps = int(rng.integers(3, 6))
        up = np.linspace(lo, hi, steps)
        levels = np.concatenate([up, up[-2::-1]]) if rng.random() < 0.6 else up
        dwell = n / len(levels)
        sp = levels[np.minimum((t / dwell).astype(int), len(levels) - 1)]
        return sp
    if kind == "ramp":
        rate = rng.uniform(0.25, 0.9) / 60.0          # C/s
        hold = rng.uniform(900, 1800)
        out, cur, goal, t_hold = np.empty(n), lo, hi, hold
        for k in range(n):                             # triangle with holds at the ends
            if t_hold > 0:
                t_hold -= 1
            else:
                step = np.sign(goal - cur) * rate
                cur = cur + step
                if (step > 0 and cur >= goal) or (step < 0 and cur <= goal):
                    cur, goal, t_hold = goal, (lo if goal == hi else hi), hold
            out[k] = cur
        return out
    if kind == "sine":
        period = rng.uniform(7200, 14400)
        mid, amp = 0.5 * (lo + hi), 0.5 * (hi - lo)
        return mid - amp * np.cos(2 * np.pi * t / period + rng.uniform(-0.3, 0.3))
    if kind == "random":
        out, k = np.empty(n), 0
        while k < n:
            dur = int(rng.uniform(1800, 5400))
            out[k:k + dur] = rng.uniform(lo, hi)
            k += dur
        return out
    raise ValueError(kind)


def chamber_air(sp: np.ndarray, rng, room: float = 22.0) -> np.ndarray:
    """Air temperature from a PI-controlled chamber: heater/compressor limits, overshoot, compressor
    ripple when cooling below room, and turbulence."""
    n = len(sp)
    heat_max, cool_max = rng.uniform(2.0, 3.5) / 60, rng.uniform(1.2, 2.2) / 60   # C/s
    kp, ki, leak = 0.02, 0.02 / rng.uniform(250, 500), 1 / 3000.0
    ripple_amp, ripple_p = rng.uniform(0.1, 0.3), rng.uniform(300, 700)
    ta, integ, out = sp[0], 0.0, np.empty(n)
    for k in range(n):
        e = sp[k] - ta
        u = kp * e + ki * integ
        u_sat = min(max(u, -cool_max), heat_max)
        if u == u_sat:                                 # anti-windup
            integ += e
        ta += u_sat + (room - ta) * leak
        out[k] = ta
    ripple = ripple_amp * np.sin(2 * np.pi * np.arange(n) / ripple_p) * (out < room - 2)
    turb = lfilter([np.sqrt(1 - 0.98 ** 2) * 0.05], [1, -0.98], rng.standard_normal(n))
    return out + ripple + turb


# ----------------------------------------------------------------------------- thermal network
def draw_unit_thermal(rng) -> dict:
    """Conductances (1/s) of the network, each drawn around a nominal value."""
    f = lambda nom: nom * rng.uniform(0.7, 1.4)
    return {
        "mount": {"air": f(1 / 4000), "case": f(1 / 6000)},      # heavy fixture: slow
        "case": {"air": f(1 / 700), "mount": f(1 / 2000)},
        "bx": {"case": f(1 / 150)},                              # t1: deep in the case
        "by": {"case": f(1 / 600), "mount": f(1 / 500)},         # t2: on the base plate
        "bz": {"case": f(1 / 400), "air": f(1 / 250)},           # t3: under the lid vent: fast
        "self_heat": {"case": rng.uniform(2.0, 3.5) / 1800, "bx": 0.6 / 600, "by": 0.4 / 600,
                      "bz": 0.5 / 600},      # C/s injected when powered
    }


def simulate_network(air: np.ndarray, g: dict, power: np.ndarray | None = None) -> dict:
    """Forward-Euler (1 s) integration; nodes start in equilibrium with the first air value.
    Returns node temperatures and their derivatives (C/s)."""
    names = ("mount", "case", "bx", "by", "bz")
    n = len(air)
    x = {k: air[0] for k in names}
    out = {k: np.empty(n) for k in names}
    dout = {k: np.empty(n) for k in names}
    pw = np.ones(n) if power is None else power
    heat = g["self_heat"]
    # pre-warm when the run starts powered (the unit had been on before logging)
    if power is None:
        for _ in range(20000):
            x = _step(x, air[0], g, heat, 1.0)[0]
    for k in range(n):
        x, dx = _step(x, air[k], g, heat, pw[k])
        for nm in names:
            out[nm][k] = x[nm]
            dout[nm][k] = dx[nm]
    out["air"] = air
    return {"T": out, "dT": dout}


def _step(x, ta, g, heat, pw):
    env = dict(x, air=ta)
    dx = {}
    for nm in ("mount", "case", "bx", "by", "bz"):
        d = sum(c * (env[o] - x[nm]) for o, c in g[nm].items())
        d += pw * heat.get(nm, 0.0)
        dx[nm] = d
    return {nm: x[nm] + dx[nm] for nm in dx}, dx


# ----------------------------------------------------------------------------- effect regressors
def first_order_lag(x: np.ndarray, tau: float) -> np.ndarray:
    a = np.exp(-1.0 / tau)
    y, _ = lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    return y


def relay_state(T: np.ndarray, width: float) -> np.ndarray:
    """+1 after the temperature has risen `width` above its last minimum, -1 after falling `width`
    below its last maximum (a direction relay with dead band). Starts at -1 (unit came from cold)."""
    s, lo, hi, out = -1.0, T[0], T[0], np.empty(len(T))
    for k, v in enumerate(T):
        lo, hi = min(lo, v), max(hi, v)
        if s < 0 and v > lo + width:
            s, hi = 1.0, v
        elif s > 0 and v < hi - width:
            s, lo = -1.0, v
        out[k] = s
    return out


def gradual_state(T: np.ndarray, width: float) -> np.ndarray:
    """State moving exponentially (in temperature, scale `width`) toward +1 when heating, -1 when
    cooling; unchanged while T is constant."""
    dT = np.diff(T, prepend=T[0])
    s, out = -1.0, np.empty(len(T))
    for k, d in enumerate(dT):
        target = 1.0 if d > 0 else -1.0
        s += (target - s) * min(abs(d) / width, 1.0)
        out[k] = s
    return out


def schmitt_mode(T: np.ndarray, t_up: float, t_down: float, rng, jitter: float = 0.8) -> np.ndarray:
    """Mode hop: 1 above t_up (jittered per crossing), back to 0 below t_down."""
    s, out = 0.0, np.empty(len(T))
    up, dn = t_up + rng.normal(0, jitter), t_down + rng.normal(0, jitter)
    for k, v in enumerate(T):
        if s == 0 and v > up:
            s, up = 1.0, t_up + rng.normal(0, jitter)
        elif s == 1 and v < dn:
            s, dn = 0.0, t_down + rng.normal(0, jitter)
        out[k] = s
    return out


def humidity(T_air: np.ndarray, rng) -> np.ndarray:
    """Relative humidity (%): own slow cycle (building HVAC, 3-6 h) + random walk + partial
    dependence on chamber temperature; the gyro sees it through a 40-min moisture uptake lag."""
    n = len(T_air)
    t = np.arange(n)
    cyc = 12 * np.sin(2 * np.pi * t / rng.uniform(10800, 21600) + rng.uniform(0, 6.3))
    walk = np.cumsum(rng.standard_normal(n)) * 0.02
    rh = 45 + cyc + walk - 0.4 * (T_air - T_air.mean())
    return first_order_lag(np.clip(rh, 5, 95), 2400.0)


def supply_sag(n: int, rng) -> np.ndarray:
    """Supply voltage deviation (V): 3-6 sags from other equipment on the same bus, 5-40 min long,
    with exponential recovery."""
    v = np.zeros(n)
    for _ in range(int(rng.integers(3, 7))):
        s = int(rng.integers(0, n - 600))
        dur = int(rng.uniform(300, 2400))
        depth = rng.uniform(0.1, 0.35)
        v[s:s + dur] -= depth
    return lfilter([1 - np.exp(-1 / 60)], [1, -np.exp(-1 / 60)], v)


# ----------------------------------------------------------------------------- gyro noise
def draw_noise(rng) -> dict:
    return {"arw": rng.uniform(0.06, 0.12),          # deg/sqrt(h)
            "bias_inst": rng.uniform(0.08, 0.2),       # deg/h (flicker level)
            "rrw": rng.uniform(0.005, 0.02),           # deg/h/sqrt(h)
            "count": float(rng.choice([0.0183, 0.0366, 0.0732]))}   # deg/h per LSB


def gyro_noise(n: int, noise: dict, rng) -> np.ndarray:
    """1-s noise (deg/h): white + flicker (sum of AR(1) at log-spaced time constants) + RRW."""
    white = noise["arw"] * 60.0 * rng.standard_normal(n)
    flick = np.zeros(n)
    for tau in np.logspace(1, 4.5, 8):
        a = np.exp(-1 / tau)
        flick += lfilter([np.sqrt(1 - a * a)], [1, -a], rng.standard_normal(n))
    flick *= noise["bias_inst"] / np.sqrt(8) * 1.6
    rrw = np.cumsum(rng.standard_normal(n)) * noise["rrw"] * np.sqrt(1 / 3600.0)
    return white + flick + rrw
