"""Plain physics for the referee corpus, written from first principles and independent of the product
(nothing here imports ``bench.fit.effects`` or ``bench.sim``).

* Chamber: a set-point program (soaks and ramps) followed by the air through a rate limit and a
  first-order lag, with a small control ripple.
* Coupled thermal network: air -> case -> three sensing coils and a base plate (which also leaks
  to the room through the table shaft), plus an electronics board that can self-heat.  Node temperatures obey C dT/dt = G (T_neighbour - T) (+ heat input);
  integrated exactly (zero-order hold) by diagonalising the system and filtering each mode.
* DS18B20 probes glued on nodes (placement drawn per unit): glue lag of a few seconds, constant offset, read noise, 0.0625 C
  quantisation.
* Gyro noise: angle random walk (white rate noise), bias instability (1/f, flicker) and rate random
  walk, at the Allan levels of IEEE 952 (ARW N: sigma = N / sqrt(tau); flicker floor 0.664 B; RRW K:
  sigma = K sqrt(tau / 3)).
* Earth rate projected on the body axes from an orientation code (three letters E W N S U D giving
  the directions of body x, y, z).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

EARTH_RATE_DPH = 7.2921158553e-5 * 180.0 / np.pi * 3600.0
QUANTUM_C = 0.0625
NODES = ("case", "coil_x", "coil_y", "coil_z", "base", "board")
_DIRECTIONS = {"E": (1.0, 0.0, 0.0), "W": (-1.0, 0.0, 0.0), "N": (0.0, 1.0, 0.0), "S": (0.0, -1.0, 0.0),
               "U": (0.0, 0.0, 1.0), "D": (0.0, 0.0, -1.0)}


# ---------------------------------------------------------------------------------------- filters

def lag(x: np.ndarray, tau_s: float, dt: float = 1.0) -> np.ndarray:
    """First-order lag (exact for a signal held over each sample), started in equilibrium."""
    a = float(np.exp(-dt / tau_s))
    y, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])
    return y


def slope_c_per_min(x: np.ndarray, window_s: float = 300.0, dt: float = 1.0) -> np.ndarray:
    """Centred least-squares slope over ``window_s`` (C/min); edges use the nearest full window."""
    half = max(1, int(round(window_s / dt / 2)))
    k = np.arange(-half, half + 1, dtype=float)
    kernel = k / np.sum(k ** 2) / dt * 60.0
    if len(x) <= 2 * half:
        return np.gradient(x, dt) * 60.0
    core = np.convolve(x, kernel[::-1], mode="valid")
    out = np.empty(len(x))
    out[half:len(x) - half] = core
    out[:half] = core[0]
    out[len(x) - half:] = core[-1]
    return out


def moving_average(x: np.ndarray, window_s: float, dt: float = 1.0) -> np.ndarray:
    n = max(1, int(round(window_s / dt)))
    pad = np.concatenate([np.full(n // 2, x[0]), x, np.full(n - 1 - n // 2, x[-1])])
    return np.convolve(pad, np.ones(n) / n, mode="valid")


def duhem(temp: np.ndarray, width_c: float) -> np.ndarray:
    """Gradual (Duhem-like) hysteresis memory in [-1, 1]: while the temperature moves by dT the state
    relaxes towards sign(dT) with a 'width' of ``width_c`` C of travel; it holds while T is still."""
    d = np.diff(temp, prepend=temp[0])
    decay = np.exp(-np.abs(d) / width_c)
    target = np.sign(d)
    h = np.empty(len(temp))
    state = 0.0
    for i in range(len(temp)):
        state = state * decay[i] + target[i] * (1.0 - decay[i])
        h[i] = state
    return h


# ---------------------------------------------------------------------------------------- chamber

def setpoint_program(segments: list[tuple], start_c: float, dt: float = 1.0) -> np.ndarray:
    """segments: ("hold", seconds) or ("ramp", target_c, c_per_min); returns the set point per sample."""
    out = [np.array([start_c])]
    t = start_c
    for seg in segments:
        if seg[0] == "hold":
            out.append(np.full(int(seg[1] / dt), t))
        else:
            target, rate = float(seg[1]), abs(float(seg[2]))
            n = max(1, int(np.ceil(abs(target - t) / (rate / 60.0 * dt))))
            out.append(np.linspace(t, target, n + 1)[1:])
            t = target
    return np.concatenate(out)


def random_segments(rng: np.random.Generator, duration_s: float, tmin: float, tmax: float,
                    rate_range: tuple[float, float], soak_range_s: tuple[float, float] = (1200, 4800),
                    start_c: float = 25.0, first_soak_s: float = 1800.0) -> list[tuple]:
    """A heat/cool test like the seed papers': soak, then ramps between random levels that alternate
    towards the hot and cold ends (reaching both extremes), each followed by a soak."""
    segs: list[tuple] = [("hold", first_soak_s)]
    t, used = start_c, first_soak_s
    ends = [tmax, tmin] if rng.random() < 0.5 else [tmin, tmax]
    i = 0
    while used < duration_s:
        if i < 2:
            target = ends[i]
        else:
            hot = t < (tmin + tmax) / 2
            lo, hi = ((tmin + tmax) / 2, tmax) if hot else (tmin, (tmin + tmax) / 2)
            target = float(rng.uniform(lo, hi))
        rate = float(rng.uniform(*rate_range))
        segs.append(("ramp", target, rate))
        used += abs(target - t) / rate * 60.0
        soak = float(rng.uniform(*soak_range_s))
        segs.append(("hold", soak))
        used += soak
        t = target
        i += 1
    return segs


def chamber_air(setpoint: np.ndarray, rng: np.random.Generator, dt: float = 1.0) -> np.ndarray:
    """Air temperature: the set point through the chamber's lag (60-150 s) plus control ripple."""
    air = lag(setpoint, float(rng.uniform(60, 150)), dt)
    ripple = lag(rng.normal(0.0, 1.0, len(setpoint)), 120.0, dt)
    ripple *= float(rng.uniform(0.01, 0.05)) / max(np.std(ripple), 1e-12)
    return air + ripple


# ---------------------------------------------------------------------------------------- network

def random_network(rng: np.random.Generator) -> dict[str, float]:
    """Conductance/capacity rates (1/s) of the network, randomised; the three coils get time constants
    from separate bands (so each probe has its own dynamics), in random order."""
    bands = [(150.0, 350.0), (500.0, 1000.0), (1300.0, 2500.0)]
    order = rng.permutation(3)
    p = {
        "case_air": 1.0 / rng.uniform(400, 1000),
        "base_air": 1.0 / rng.uniform(900, 2400),
        "case_base": 1.0 / rng.uniform(600, 1800),
        "coil_base": 1.0 / rng.uniform(3000, 8000),
        "board_case": 1.0 / rng.uniform(600, 1500),
        # the table shaft through the chamber wall: the base plate also leaks to the room
        "base_room": 1.0 / rng.uniform(1500, 5000),
        "room_c": rng.uniform(20.0, 26.0),
    }
    for ch, k in zip("xyz", order):
        p[f"coil_{ch}_case"] = 1.0 / rng.uniform(*bands[k])
    return p


def network_temperatures(air: np.ndarray, net: dict[str, float], heat_board: np.ndarray | None = None,
                         dt: float = 1.0) -> dict[str, np.ndarray]:
    """Node temperatures (C) of the network driven by the air (and a board heat input in C/s),
    started in equilibrium with the first air sample."""
    idx = {name: i for i, name in enumerate(NODES)}
    n = len(NODES)
    A = np.zeros((n, n))
    B = np.zeros(n)

    def link(a: str, b: str, g: float) -> None:
        i, j = idx[a], idx[b]
        A[i, i] -= g
        A[j, j] -= g
        A[i, j] += g
        A[j, i] += g

    A[idx["case"], idx["case"]] -= net["case_air"]
    B[idx["case"]] += net["case_air"]
    A[idx["base"], idx["base"]] -= net["base_air"] + net.get("base_room", 0.0)
    B[idx["base"]] += net["base_air"]
    room = np.zeros(n)
    room[idx["base"]] = net.get("base_room", 0.0)
    link("case", "base", net["case_base"])
    link("board", "case", net["board_case"])
    for ch in "xyz":
        link(f"coil_{ch}", "case", net[f"coil_{ch}_case"])
        link(f"coil_{ch}", "base", net["coil_base"])
    # dT/dt = A T + B air + e_board q ; A symmetric -> real modes
    lam, V = np.linalg.eigh(A)
    heat = np.zeros(len(air)) if heat_board is None else heat_board
    U = np.column_stack([air, heat, np.full(len(air), net.get("room_c", 25.0))])    # inputs
    Bfull = np.column_stack([B, np.eye(n)[idx["board"]], room])                     # (n, 3)
    # equilibrium for the first input: T0 = -A^-1 B u0
    T0 = -np.linalg.solve(A, Bfull @ U[0])
    Z0 = V.T @ T0
    drive = (V.T @ Bfull) @ U.T                               # (n, len)
    out = np.empty((n, len(air)))
    for m in range(n):
        a = np.exp(lam[m] * dt)
        gain = (a - 1.0) / lam[m]                             # ZOH input gain
        # z[k+1] = a z[k] + gain d[k], z[0] = Z0 (lfilter: y[0] = zi)
        z, _ = lfilter([0.0, gain], [1.0, -a], drive[m], zi=[Z0[m]])
        out[m] = z
    T = V @ out
    return {name: T[i] for name, i in idx.items()}


def read_probe(true_c: np.ndarray, glue_s: float, offset_c: float, noise_c: float, rng: np.random.Generator,
               dt: float = 1.0) -> np.ndarray:
    """A DS18B20 glued on a node: glue lag, constant offset, read noise, 0.0625 C steps."""
    x = lag(true_c, glue_s, dt) + offset_c + rng.normal(0.0, noise_c, len(true_c))
    return np.round(x / QUANTUM_C) * QUANTUM_C


# ---------------------------------------------------------------------------------------- gyro noise

def gyro_noise(n: int, rng: np.random.Generator, arw_dph_rthz: float, bias_instability_dph: float,
               rrw_dph_rth: float, dt: float = 1.0, filter_s: float = 0.0) -> np.ndarray:
    """Rate noise (deg/h): ARW N (deg/sqrt(h)), flicker with Allan floor 0.664 B, RRW K (deg/h/sqrt(h));
    with ``filter_s`` > 0 the sensor's output filter (first order, that time constant in s, unit gain)
    applied to the sum, so that samples closer than it are correlated."""
    white = rng.normal(0.0, arw_dph_rthz * 60.0 / np.sqrt(dt), n)
    flicker = np.zeros(n)
    if bias_instability_dph > 0:
        w = np.fft.rfft(rng.normal(0.0, 1.0, n))
        f = np.fft.rfftfreq(n, dt)
        shape = np.zeros_like(f)
        shape[1:] = 1.0 / np.sqrt(f[1:])
        flicker = np.fft.irfft(w * shape, n)
        # unit white noise has one-sided PSD 2 dt; shaped: h_-1 = 2 dt -> Allan variance 2 ln2 h_-1
        flicker *= 0.664 * bias_instability_dph / np.sqrt(2.0 * np.log(2.0) * 2.0 * dt)
    walk = np.cumsum(rng.normal(0.0, rrw_dph_rth / 60.0 * np.sqrt(dt), n)) if rrw_dph_rth > 0 else 0.0
    total = white + flicker + walk
    if filter_s > 0:
        a = np.exp(-dt / filter_s)
        total = lfilter([1.0 - a], [1.0, -a], total, zi=[a * total[0]])[0]
    return total


# ---------------------------------------------------------------------------------------- Earth rate

def body_axes(code: str) -> np.ndarray:
    """(3, 3): row i = direction of body axis i (x, y, z) in East-North-Up."""
    return np.array([_DIRECTIONS[c] for c in code])


def earth_rate_body(orientation: np.ndarray, latitude_deg: float) -> np.ndarray:
    """(n, 3): Earth rate seen along body x, y, z (deg/h) for each sample's orientation code."""
    lat = np.radians(latitude_deg)
    omega_enu = EARTH_RATE_DPH * np.array([0.0, np.cos(lat), np.sin(lat)])
    codes, inverse = _orientation_codes(orientation)
    table = np.array([body_axes(str(c)) @ omega_enu for c in codes])
    return table[inverse]


def gravity_up_body(orientation: np.ndarray) -> np.ndarray:
    """(n, 3): the up component of each body axis (the gravity direction in the body frame)."""
    codes, inverse = _orientation_codes(orientation)
    table = np.array([body_axes(str(c))[:, 2] for c in codes])
    return table[inverse]


def _orientation_codes(orientation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct orientation codes and each sample's index among them (as text: numpy sorts an
    array of str ten times faster than one of Python objects, measured on 80,000 samples)."""
    return np.unique(np.asarray(orientation, dtype=object).astype(str), return_inverse=True)
