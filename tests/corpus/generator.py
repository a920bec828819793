"""Simulate one gyro unit (three channels x, y, z, probes t1..t4 on a coupled thermal network) over a
TRAIN run and a VALIDATE run, with true effects hidden in the bias of the channel(s) under test.

The unit's physics (network, probe offsets, bias polynomials, effect coefficients, noise levels) is
drawn once per case; each run has its own chamber program, noise and hidden-variable draws.  An
effect's coefficient is set from its visible size on TRAIN: the std of its signal after removing what
the declared model can absorb, as a multiple (``ratio``) of the TRAIN noise floor (std of 100-s means
of the gyro noise).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from bench.fit.base import Dataset
from tests.corpus import physics as ph
from tests.corpus.effects import Effect, RunState, node_of, since_on

DT = 1.0


@dataclass
class RunPlan:
    """One run's conditions."""

    duration_s: float
    tmin_c: float
    tmax_c: float
    rate_range: tuple[float, float]                    # C/min
    soak_range_s: tuple[float, float] = (1800.0, 4800.0)
    power_cycles: bool = False                         # power off 15-40 min every 1.5-3 h
    positions: tuple[str, ...] = ()                    # orientation codes visited in turn
    table_rates_dps: tuple[float, ...] = ()            # table rates visited in turn
    humidity: bool = False
    board_load: bool = False


@dataclass
class ChannelSpec:
    channel: str
    declared: list[tuple]                              # ("pow", probe, k) | ("diff", a, b)
    effects: list[tuple[Effect, float]]                # (effect, ratio to the noise floor)
    verdicts: frozenset[str]


@dataclass
class Unit:
    net: dict[str, float]
    probe_rng_seeds: dict[str, int]
    noise: dict[str, float]                            # arw, bi, rrw
    bias_coef: dict[str, dict[str, float]]             # channel -> term -> deg/h per unit
    effect_coef: dict[tuple[str, int], float] = field(default_factory=dict)


def formula_text(declared: list[tuple]) -> str:
    parts = []
    for term in declared:
        if term[0] == "pow":
            parts.append(term[1] if term[2] == 1 else f"{term[1]}^{term[2]}")
        else:
            parts.append(f"({term[1]}-{term[2]})")
    return " + ".join(parts)


def declared_columns(declared: list[tuple], temps: Callable[[str], np.ndarray]) -> np.ndarray:
    """(n, k): the declared terms evaluated on temperatures (no intercept)."""
    cols = []
    for term in declared:
        if term[0] == "pow":
            cols.append(temps(term[1]) ** term[2])
        else:
            cols.append(temps(term[1]) - temps(term[2]))
    return np.column_stack(cols)


def declared_probes(declared: list[tuple]) -> list[str]:
    out: list[str] = []
    for term in declared:
        for p in (term[1:] if term[0] == "diff" else term[1:2]):
            if p not in out:
                out.append(p)
    return out


def random_unit(rng: np.random.Generator, noise_scale: dict[str, tuple[float, float]] | None = None) -> Unit:
    ns = {"arw": (0.002, 0.006), "bi": (0.002, 0.006), "rrw": (0.0003, 0.0015)}
    ns.update(noise_scale or {})
    noise = {k: float(rng.uniform(*v)) for k, v in ns.items()}
    coef = {}
    for ch in "xyz":
        coef[ch] = {"c0": float(rng.uniform(-2, 2)),
                    "c1": float(rng.choice([-1, 1]) * rng.uniform(0.01, 0.04)),
                    "c2": float(rng.choice([-1, 1]) * rng.uniform(1e-4, 5e-4)),
                    "c3": float(rng.choice([-1, 1]) * rng.uniform(1e-6, 6e-6)),
                    "grad": float(rng.choice([-1, 1]) * rng.uniform(0.02, 0.08))}
    seeds = {p: int(rng.integers(2 ** 31)) for p in ph.PROBE_NODES}
    return Unit(ph.random_network(rng), seeds, noise, coef)


def simulate_state(plan: RunPlan, unit: Unit, rng: np.random.Generator, latitude_deg: float) -> RunState:
    segs = ph.random_segments(rng, plan.duration_s, plan.tmin_c, plan.tmax_c, plan.rate_range, plan.soak_range_s)
    sp = ph.setpoint_program(segs, 25.0, DT)
    n = int(plan.duration_s / DT)
    if len(sp) < n:
        sp = np.concatenate([sp, np.full(n - len(sp), sp[-1])])
    sp = sp[:n]
    air = ph.chamber_air(sp, rng, DT)
    t = np.arange(n) * DT
    hidden: dict[str, np.ndarray] = {}
    heat = None
    if plan.board_load:
        # unrecorded electronics load: piecewise-constant levels, each 20-90 min, 0-5 C rise at steady state
        levels = np.zeros(n)
        i = 0
        while i < n:
            j = min(n, i + int(rng.uniform(1200, 5400) / DT))
            levels[i:j] = rng.uniform(0.0, 5.0)
            i = j
        heat = levels * unit.net["board_case"]
    nodes = ph.network_temperatures(air, unit.net, heat, DT)
    nodes["air"] = air
    if plan.board_load:
        hidden["board_minus_case_c"] = nodes["board"] - nodes["case"]
    if plan.humidity:
        # relative humidity: slow random process (correlation 1-3 h) about 30-60 %, 5-15 % swings
        rh = ph.lag(rng.normal(0, 1, n), float(rng.uniform(3600, 10800)), DT)
        rh = float(rng.uniform(30, 60)) + rh / np.std(rh) * float(rng.uniform(5, 15))
        hidden["humidity_pct"] = rh
    power = np.ones(n)
    if plan.power_cycles:
        i = int(rng.uniform(3600, 7200) / DT)
        while i < n:
            off = int(rng.uniform(900, 2400) / DT)
            power[i:i + off] = 0.0
            i += off + int(rng.uniform(5400, 10800) / DT)
    t_on = since_on(t, power > 0.5)
    orientation = np.full(n, "NUE", dtype=object)
    if plan.positions:
        dwell = int(rng.uniform(1800, 3600) / DT)
        k = (np.arange(n) // dwell) % len(plan.positions)
        orientation = np.asarray(plan.positions, dtype=object)[k]
    table = np.zeros(n)
    if plan.table_rates_dps:
        dwell = int(rng.uniform(1200, 2400) / DT)
        order = rng.permutation(len(plan.table_rates_dps))
        k = (np.arange(n) // dwell) % len(order)
        table = np.asarray(plan.table_rates_dps, dtype=float)[order][k]
    return RunState(t, nodes, power, t_on, orientation, table, latitude_deg, hidden)


def probe_readings(state: RunState, unit: Unit, run_index: int) -> dict[str, np.ndarray]:
    out = {}
    for p, node in ph.PROBE_NODES.items():
        # offsets and glue lags belong to the unit (same draw on both runs); read noise is per run
        unit_rng = np.random.default_rng(unit.probe_rng_seeds[p])
        glue, offset, sigma = unit_rng.uniform(1.0, 4.0), unit_rng.uniform(-0.15, 0.15), unit_rng.uniform(0.003, 0.015)
        run_rng = np.random.default_rng([unit.probe_rng_seeds[p], run_index])
        x = ph.lag(state.nodes[node], glue, DT) + offset + run_rng.normal(0, sigma, len(state.time_s))
        out[p] = np.round(x / ph.QUANTUM_C) * ph.QUANTUM_C
    return out


def thermal_bias(channel: str, declared: list[tuple], unit: Unit, state: RunState) -> np.ndarray:
    """The declared physics: a cubic in the channel's coil temperature (plus a gradient term to the
    base when the declared model has one)."""
    c = unit.bias_coef[channel]
    u = state.nodes[f"coil_{channel}"] - 25.0
    b = c["c0"] + c["c1"] * u + c["c2"] * u ** 2 + c["c3"] * u ** 3
    for term in declared:
        if term[0] == "diff":
            b = b + c["grad"] * (state.nodes[node_of(term[1])] - state.nodes[node_of(term[2])])
    return b


def _visible_std(signal: np.ndarray, declared: list[tuple], state: RunState, ok: np.ndarray) -> float:
    """Std of the 100-s means of ``signal`` left after a least-squares fit of the declared terms
    (evaluated on the true node temperatures) plus an intercept."""
    X = np.column_stack([np.ones(len(signal)), declared_columns(declared, lambda p: state.nodes[node_of(p)] - 25.0)])
    per = int(100 / DT)
    m = (len(signal) // per) * per
    okb = ok[:m].reshape(-1, per).all(axis=1)
    sb = signal[:m].reshape(-1, per).mean(axis=1)[okb]
    Xb = X[:m].reshape(-1, per, X.shape[1]).mean(axis=1)[okb]
    beta, *_ = np.linalg.lstsq(Xb, sb, rcond=None)
    return float(np.std(sb - Xb @ beta))


def block_std100(x: np.ndarray) -> float:
    per = int(100 / DT)
    m = (len(x) // per) * per
    b = x[:m].reshape(-1, per)
    b = b[np.all(np.isfinite(b), axis=1)].mean(axis=1)
    return float(np.std(b, ddof=1))


def make_run(plan: RunPlan, unit: Unit, specs: list[ChannelSpec], rng: np.random.Generator,
             latitude_deg: float, run_index: int, meta: dict[str, str]) -> tuple[Dataset, RunState, dict[str, Any]]:
    """Simulate a run.  On the first run (run_index 0) each effect's coefficient is set from its
    visible size; later runs reuse it.  Returns the dataset, the true state and the noise floors."""
    state = simulate_state(plan, unit, rng, latitude_deg)
    n = len(state.time_s)
    cols: dict[str, np.ndarray] = {"time_s": state.time_s.copy()}
    floors = {}
    tested = {s.channel: s for s in specs}
    channels = [s.channel for s in specs] if plan.table_rates_dps else ["x", "y", "z"]
    on = state.power > 0.5
    for ch in channels:
        noise = ph.gyro_noise(n, rng, unit.noise["arw"], unit.noise["bi"], unit.noise["rrw"], DT)
        floors[ch] = block_std100(noise)
        spec = tested.get(ch)
        declared = spec.declared if spec else [("pow", ph.CHANNEL_PROBES[ch], k) for k in (1, 2, 3)]
        bias = thermal_bias(ch, declared, unit, state)
        for i, (eff, ratio) in enumerate(spec.effects if spec else []):
            sig = eff.signal(state, ch)
            key = (ch, i)
            if key not in unit.effect_coef:
                size = _visible_std(sig, declared, state, on)
                sign = 1.0 if rng.random() < 0.5 else -1.0
                unit.effect_coef[key] = sign * ratio * floors[ch] / max(size, 1e-12)
            bias = bias + unit.effect_coef[key] * sig
            if not eff.explainable:
                state.hidden[eff.kind] = sig        # what the referee may use; no column records it
        i_ch = "xyz".index(ch)
        w_in = ph.earth_rate_body(state.orientation, latitude_deg)[:, i_ch] + state.table_rate_dps * 3600.0
        y = w_in + bias + noise
        y[~on] = np.nan
        cols[f"gyro_{ch}"] = y
    for p, x in probe_readings(state, unit, run_index).items():
        cols[f"temp_{p}"] = x
    cols["power"] = state.power.copy()
    if plan.positions:
        cols["orientation"] = state.orientation.copy()
    if plan.table_rates_dps:
        cols["table_rate_dps"] = state.table_rate_dps.copy()
    md = {"latitude_deg": repr(float(latitude_deg)), "sample_period_s": repr(DT),
          "channel_probes": ",".join(f"{c}={p}" for c, p in ph.CHANNEL_PROBES.items()), **meta}
    return Dataset(cols, md), state, floors
