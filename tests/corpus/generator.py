"""Simulate one gyro unit (three channels x, y, z, probes t1..t4 on a coupled thermal network) over a
TRAIN run and a VALIDATE run, with true effects hidden in the bias of the channel(s) under test.

The unit's physics (network, probe offsets, bias polynomials, effect coefficients, noise levels) is
drawn once per case; the physics runs at 1 s and the data logger records it (``Recording``): every
``record_period_s`` one row with the gyro averaged over the period (an integrating rate output) and the
other columns read at the period's middle sample; logger outages drop whole rows; each run has its own chamber program, noise and hidden-variable draws.  An
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
from tests.corpus.effects import Effect, RunState, since_on

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
    record_period_s: float = DT                        # the logger's sample period
    outages: bool = False                              # 2-4 logger outages of 5-40 min (rows missing)
    bias_step: bool = False                            # a bias step at a random time (hidden cause)


@dataclass
class Recording:
    """Which physics samples (1 s) make each recorded row: ``group[i]`` is the row of sample i, -1 when
    the sample is not recorded (an outage, or a ragged end)."""

    group: np.ndarray
    n_rows: int

    @classmethod
    def plan(cls, plan: RunPlan, n: int, rng: np.random.Generator) -> "Recording":
        k = max(1, int(round(plan.record_period_s / DT)))
        group = np.arange(n) // k
        group[group >= n // k] = -1
        if plan.outages:
            lost = np.zeros(n // k, dtype=bool)
            for _ in range(int(rng.integers(2, 5))):
                start = float(rng.uniform(1800.0, max(1801.0, plan.duration_s - 3600.0)))
                length = float(rng.uniform(300.0, 2400.0))
                lost[int(start / DT) // k: int((start + length) / DT) // k + 1] = True
            keep = np.flatnonzero(~lost)
            new = np.full(n // k, -1)
            new[keep] = np.arange(len(keep))
            group = np.where(group >= 0, new[np.maximum(group, 0)], -1)
        return cls(group, int(group.max()) + 1)

    @property
    def identity(self) -> bool:
        return self.n_rows == len(self.group) and bool(np.all(self.group == np.arange(len(self.group))))

    def mean(self, x: np.ndarray) -> np.ndarray:
        """Row means (a row with any missing sample is missing), for 1-D or 2-D (samples first)."""
        x = np.asarray(x, dtype=float)
        if self.identity:
            return x
        used = self.group >= 0
        g = self.group[used]
        flat = x[used].reshape(len(g), -1)
        bad = ~np.isfinite(flat)
        cnt = np.bincount(g, minlength=self.n_rows)
        out = np.empty((self.n_rows, flat.shape[1]))
        for j in range(flat.shape[1]):
            s = np.bincount(g, np.where(bad[:, j], 0.0, flat[:, j]), self.n_rows)
            nb = np.bincount(g, bad[:, j].astype(float), self.n_rows)
            out[:, j] = np.where(nb > 0, np.nan, s / np.maximum(cnt, 1))
        return out.reshape((self.n_rows,) + x.shape[1:])

    def pick(self, x: np.ndarray) -> np.ndarray:
        """The value at each row's middle sample (a point reading)."""
        x = np.asarray(x)
        if self.identity:
            return x
        used = np.flatnonzero(self.group >= 0)
        g = self.group[used]
        first = np.full(self.n_rows, -1)
        last = np.full(self.n_rows, -1)
        first[g[::-1]] = used[::-1]
        last[g] = used
        return x[(first + last) // 2]


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
    noise: dict[str, float]                            # arw, bi, rrw (, filter_s: the output filter)
    bias_coef: dict[str, dict[str, float]]             # channel -> term -> deg/h per unit
    probe_nodes: dict[str, str]                        # probe -> node it is glued on
    channel_probes: dict[str, str]                     # channel -> the probe on its coil
    structure_probe: str                               # the probe on the base plate or the case
    effect_coef: dict[tuple[str, int], float] = field(default_factory=dict)
    # share of each effect's 100-s variation on TRAIN that the declared model cannot absorb
    effect_visibility: dict[tuple[str, int], float] = field(default_factory=dict)
    # the smallest error (in noise floors, 100-s means, TRAIN) left when one other-kind or
    # other-probe library regressor replaces the effect: how well a right answer can be told apart
    effect_distinctness: dict[tuple[str, int], float] = field(default_factory=dict)
    # the (kind, probes) that imitate the effect within LOOKALIKE_FLOORS: equally right answers
    effect_lookalikes: dict[tuple[str, int], list] = field(default_factory=dict)


def formula_text(declared: list[tuple]) -> str:
    parts = []
    for term in declared:
        if term[0] == "pow":
            parts.append(term[1] if term[2] == 1 else f"{term[1]}^{term[2]}")
        else:
            parts.append(f"({term[1]}-{term[2]})")
    return " + ".join(parts)


def declared_columns(declared: list[tuple], temps: Callable[[str], np.ndarray], n: int | None = None) -> np.ndarray:
    """(n, k): the declared terms evaluated on temperatures (no intercept)."""
    cols = []
    for term in declared:
        if term[0] == "pow":
            cols.append(temps(term[1]) ** term[2])
        else:
            cols.append(temps(term[1]) - temps(term[2]))
    return np.column_stack(cols) if cols else np.zeros((n or 0, 0))


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
    seeds = {p: int(rng.integers(2 ** 31)) for p in ("t1", "t2", "t3", "t4")}
    # probe placement: a random probe on each coil, the fourth on the base plate or on the case
    names = [str(p) for p in rng.permutation(["t1", "t2", "t3", "t4"])]
    structure_node = "base" if rng.random() < 0.6 else "case"
    probe_nodes = {names[0]: "coil_x", names[1]: "coil_y", names[2]: "coil_z", names[3]: structure_node}
    channel_probes = {"x": names[0], "y": names[1], "z": names[2]}
    return Unit(ph.random_network(rng), seeds, noise, coef, probe_nodes, channel_probes, names[3])


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
        # the board's rise from its own (unrecorded) load: the network is linear, so it is the
        # difference from the same run without the load
        hidden["board_self_heating_c"] = nodes["board"] - ph.network_temperatures(air, unit.net, None, DT)["board"]
    if plan.humidity:
        # relative humidity: slow random process (correlation 1-3 h) about 30-60 %, 5-15 % swings
        rh = ph.lag(rng.normal(0, 1, n), float(rng.uniform(3600, 10800)), DT)
        rh = float(rng.uniform(30, 60)) + rh / np.std(rh) * float(rng.uniform(5, 15))
        hidden["humidity_pct"] = rh
    if plan.bias_step:
        # a step at a random time, not driven by temperature (a shock, a contact settling): 0 then 1
        hidden["bias_step"] = (t >= float(rng.uniform(0.2, 0.8)) * plan.duration_s).astype(float)
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
    return RunState(t, nodes, power, t_on, orientation, table, latitude_deg, dict(unit.probe_nodes), hidden)


def probe_readings(state: RunState, unit: Unit, run_index: int) -> dict[str, np.ndarray]:
    out = {}
    for p, node in sorted(unit.probe_nodes.items()):
        # offsets and glue lags belong to the unit (same draw on both runs); read noise is per run
        unit_rng = np.random.default_rng(unit.probe_rng_seeds[p])
        glue, offset, sigma = unit_rng.uniform(1.0, 4.0), unit_rng.uniform(-0.15, 0.15), unit_rng.uniform(0.003, 0.015)
        run_rng = np.random.default_rng([unit.probe_rng_seeds[p], run_index])
        out[p] = ph.read_probe(state.nodes[node], glue, offset, sigma, run_rng, DT)
    return out


def thermal_bias(channel: str, declared: list[tuple], unit: Unit, state: RunState) -> np.ndarray:
    """The declared physics: a cubic in the channel's coil temperature (plus a gradient term to the
    base when the declared model has one)."""
    c = unit.bias_coef[channel]
    u = state.nodes[f"coil_{channel}"] - 25.0
    b = c["c0"] + c["c1"] * u + c["c2"] * u ** 2 + c["c3"] * u ** 3
    for term in declared:
        if term[0] == "diff":
            b = b + c["grad"] * (state.temp(term[1]) - state.temp(term[2]))
    return b


PER_BLOCK = int(100 / DT)       # samples in a 100-s block


def whole_blocks(x: np.ndarray) -> np.ndarray:
    """``x`` (samples first) as (blocks, PER_BLOCK, ...): its whole 100-s blocks, a ragged end left out."""
    m = (len(x) // PER_BLOCK) * PER_BLOCK
    return x[:m].reshape(-1, PER_BLOCK, *x.shape[1:])


def block_means100(columns: list[np.ndarray]) -> np.ndarray:
    """(blocks, k): 100-s means of equal-length columns.  The sums run in the same order whatever k:
    numpy sums a strided axis in sequence but a contiguous one pairwise, so a lone column is paired
    with zeros (a design's block means are then those of its columns, bit for bit)."""
    X = np.column_stack(list(columns) + ([np.zeros(len(columns[0]))] if len(columns) == 1 else []))
    return whole_blocks(X).mean(axis=1)[:, :len(columns)]


class VisibleFit:
    """Std of the 100-s means of a signal left after a least-squares fit of the declared terms
    (evaluated on the true node temperatures), an intercept and other signals (given by their
    ``block_means100``), over the blocks where ``ok`` holds throughout.  The declared design's block
    means are computed once per declared model: the look-alike search fits a signal against a few
    hundred alternatives on the same run."""

    def __init__(self, state: RunState, ok: np.ndarray):
        self.state = state
        self.okb = whole_blocks(ok).all(axis=1)
        self._declared: dict[tuple, np.ndarray] = {}

    def _declared_blocks(self, declared: list[tuple]) -> np.ndarray:
        key = tuple(declared)
        if key not in self._declared:
            n = len(self.state.time_s)
            X = declared_columns(declared, lambda p: self.state.temp(p) - 25.0, n)
            self._declared[key] = block_means100([np.ones(n), *X.T])
        return self._declared[key]

    def std(self, signal: np.ndarray, declared: list[tuple], other_blocks: list[np.ndarray] = ()) -> float:
        sb = whole_blocks(signal).mean(axis=1)[self.okb]
        Xb = np.column_stack([self._declared_blocks(declared), *other_blocks])[self.okb]
        beta, *_ = np.linalg.lstsq(Xb, sb, rcond=None)
        return float(np.std(sb - Xb @ beta))


ALTERNATIVE_KINDS = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross")
# a lag's time constant is a continuous parameter an analysis fits: any value from a minute to four
# hours may imitate an effect.  The imitation is sharp in tau (a gradient t1-t2 imitated by a lag of
# t1 within 0.02 floors at 19.5 min, 0.47 at 24.5 min, 0.87 at 12 min), so the grid's neighbours are
# 1.1x apart; three values (10, 30, 90 min) had called that gradient distinct from every lag
ALTERNATIVE_LAGS_S = tuple(float(t) for t in np.geomspace(60.0, 14400.0, 59))
LOOKALIKE_FLOORS = 0.5      # naming it instead leaves under half a noise floor of error: no data tells them apart


def alternatives(eff: Effect, state: RunState) -> list[tuple[str, tuple[str, ...], np.ndarray]]:
    """(kind, probes, signal) of the temperature-driven library effects an analysis could name
    instead of ``eff`` (every kind on every probe or pair, lags of 1 min to 4 h), leaving out ``eff``'s own kind
    on its own probes."""
    if eff.kind not in ALTERNATIVE_KINDS or not eff.explainable:
        return []
    probes = sorted(state.probe_nodes)
    out = []

    def add(kind: str, ps: tuple[str, ...], signal: np.ndarray) -> None:
        if not (kind == eff.kind and set(ps) == set(eff.probes)):
            out.append((kind, ps, signal))

    for p in probes:
        t = state.temp(p)
        r = np.gradient(t) * 60.0
        add("rate", (p,), r)
        add("rate_squared", (p,), r ** 2)
        add("temp_rate_cross", (p,), (t - 25.0) * r)
        for tau in ALTERNATIVE_LAGS_S:
            add("thermal_lag", (p,), ph.lag(t, tau) - t)
    for i, a in enumerate(probes):
        for b in probes[i + 1:]:
            add("gradient", (a, b), state.temp(a) - state.temp(b))
    return out


def block_std100(x: np.ndarray) -> float:
    b = whole_blocks(x)
    b = b[np.all(np.isfinite(b), axis=1)].mean(axis=1)
    return float(np.std(b, ddof=1))


def make_run(plan: RunPlan, unit: Unit, specs: list[ChannelSpec], rng: np.random.Generator,
             latitude_deg: float, run_index: int,
             meta: dict[str, str]) -> tuple[Dataset, RunState, dict[str, Any], Dataset, Recording]:
    """Simulate a run.  On the first run (run_index 0) each effect's coefficient is set from its
    visible size; later runs reuse it.  Returns the recorded dataset, the true state, the noise
    floors, the dataset at the physics' 1-s rate and the recording that turns one into the other."""
    state = simulate_state(plan, unit, rng, latitude_deg)
    n = len(state.time_s)
    cols: dict[str, np.ndarray] = {"time_s": state.time_s.copy()}
    floors = {}
    tested = {s.channel: s for s in specs}
    channels = [s.channel for s in specs] if plan.table_rates_dps else ["x", "y", "z"]
    on = state.power > 0.5
    visible = VisibleFit(state, on)
    for ch in channels:
        noise = ph.gyro_noise(n, rng, unit.noise["arw"], unit.noise["bi"], unit.noise["rrw"], DT,
                              unit.noise.get("filter_s", 0.0))
        floors[ch] = block_std100(noise)
        spec = tested.get(ch)
        declared = spec.declared if spec else [("pow", unit.channel_probes[ch], k) for k in (1, 2, 3)]
        bias = thermal_bias(ch, declared, unit, state)
        signals = [eff.signal(state, ch) for eff, _ in (spec.effects if spec else [])]
        for i, (eff, ratio) in enumerate(spec.effects if spec else []):
            sig = signals[i]
            key = (ch, i)
            if key not in unit.effect_coef:
                size = visible.std(sig, declared)
                sign = 1.0 if rng.random() < 0.5 else -1.0
                unit.effect_coef[key] = sign * ratio * floors[ch] / max(size, 1e-12)
                others = [block_means100([s]) for j, s in enumerate(signals) if j != i]
                own = visible.std(sig, declared, others)
                unit.effect_visibility[key] = own / max(visible.std(sig, []), 1e-12)
                errors: dict[tuple[str, tuple[str, ...]], float] = {}
                for kind, ps, alt in alternatives(eff, state):
                    err = abs(unit.effect_coef[key]) * visible.std(sig, declared, others + [block_means100([alt])])
                    errors[(kind, ps)] = min(errors.get((kind, ps), np.inf), err / floors[ch])
                unit.effect_distinctness[key] = min(errors.values(), default=float("inf"))
                unit.effect_lookalikes[key] = sorted(k for k, e in errors.items() if e < LOOKALIKE_FLOORS)
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
    full = Dataset(cols, {"latitude_deg": repr(float(latitude_deg)), "sample_period_s": repr(DT), **meta})
    rec = Recording.plan(plan, n, rng)
    out: dict[str, np.ndarray] = {}
    for name, v in cols.items():
        out[name] = rec.mean(v) if name.startswith("gyro_") else rec.pick(v)
    if not rec.identity:
        out["time_s"] = rec.mean(cols["time_s"])           # the middle of the averaging period
    md = {"latitude_deg": repr(float(latitude_deg)), "sample_period_s": repr(float(plan.record_period_s)),
          "channel_probes": ",".join(f"{c}={p}" for c, p in sorted(unit.channel_probes.items())), **meta}
    return Dataset(out, md), state, floors, full, rec
