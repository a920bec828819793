"""Held-out close-the-loop cases: a unit, a TRAIN and a VALIDATE run as measured-data CSV v1 text, the
declared model, and the truth (hidden effects with kind and probe, the honest verdicts, the oracle).

A case is fully determined by its class name and seed.  The hidden physics acts on one channel (the
target); the other channels follow the declared model exactly.  Each hidden effect is scaled on TRAIN
so that what the declared model cannot absorb of it has a std of 100-s means of 4-8x the channel's
noise there; a draw the declared model absorbs almost entirely is drawn again.

Truth vocabulary (kinds; probes are recorded probe names):
  thermal_lag (probe), gradient (probe pair), rate (probe), hysteresis (relay, probe),
  gradual_hysteresis (Duhem, probe), warmup (no probe); not in any library: sinusoid, bias_step.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from tests.heldout import physics as ph

CHANNELS = ("x", "y", "z")
PROBES = ("t1", "t2", "t3", "t4")
DECLARED = "tc + tc^2 + tc^3"          # a cubic in each channel's own probe
EARTH_DPH = 15.041
LATITUDE = 48.0

# verdicts (the words)
EXPLAINED = "explained"
PARTLY = "partly_explained"
NONE_MISSING = "no_effect_missing"
UNEXPLAINED = "unexplained_structure_remains"

PRE_HISTORY_C, PRE_HISTORY_N = 15.0, 400
LIBRARY_KINDS = ("thermal_lag", "gradient", "rate", "hysteresis", "gradual_hysteresis", "warmup")
FOREIGN_KINDS = ("sinusoid", "bias_step")

#: class -> (validation program kind, hidden effects on the target channel, flicker scale)
CLASSES: dict[str, tuple[str, tuple[str, ...], float]] = {
    "complete_inside": ("inside", (), 1.0),
    "complete_colder": ("colder", (), 1.0),
    "complete_hotter": ("hotter", (), 1.0),
    "complete_steeper": ("steeper", (), 1.0),
    "complete_short": ("short", (), 1.0),
    "complete_strong_flicker": ("inside", (), 3.0),
    "lag_any_probe": ("inside", ("thermal_lag",), 1.0),
    "gradient": ("inside", ("gradient",), 1.0),
    "rate": ("inside", ("rate",), 1.0),
    "relay_hysteresis": ("inside", ("hysteresis",), 1.0),
    "gradual_hysteresis": ("inside", ("gradual_hysteresis",), 1.0),
    "warmup": ("inside", ("warmup",), 1.0),
    "two_effects": ("inside", ("pair",), 1.0),
    "effect_validation_colder": ("colder", ("any",), 1.0),
    "unexplained_sinusoid": ("inside", ("sinusoid",), 1.0),
    "unexplained_step": ("inside", ("bias_step",), 1.0),
}


@dataclass
class Effect:
    kind: str
    probes: tuple[str, ...] = ()
    params: dict[str, float] = field(default_factory=dict)
    gain: float = 0.0
    rows: dict[str, np.ndarray] = field(default_factory=dict, repr=False)   # regressor on kept rows

    def label(self) -> str:
        p = "-".join(self.probes)
        return f"{self.kind}({p})" if p else self.kind


@dataclass
class RunData:
    t: np.ndarray                      # s since power-on, kept rows only
    sp: np.ndarray
    air: np.ndarray
    truth: dict[str, np.ndarray]       # probe -> true temperature at the probe
    readings: dict[str, np.ndarray]    # probe -> DS18B20 reading (NaN where a read failed)
    gyro: dict[str, np.ndarray]
    noise: dict[str, np.ndarray]
    dt: float


@dataclass
class Case:
    cls: str
    seed: int
    channel: str
    channel_probes: dict[str, str]
    effects: list[Effect]
    train: RunData
    validate: RunData
    train_csv: str
    validate_csv: str
    declared: str = DECLARED

    @property
    def name(self) -> str:
        return f"{self.cls}/seed{self.seed}"

    @property
    def library_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.kind in LIBRARY_KINDS]

    @property
    def foreign_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.kind in FOREIGN_KINDS]

    def honest_verdicts(self) -> set[str]:
        """The issue's rules: nothing hidden -> no_effect_missing; only library effects -> explained;
        structure no candidate can explain -> unexplained_structure_remains, or partly_explained when a
        library effect was also there to add."""
        if self.foreign_effects:
            return {UNEXPLAINED, PARTLY} if self.library_effects else {UNEXPLAINED}
        return {EXPLAINED} if self.library_effects else {NONE_MISSING}


# ----------------------------------------------------------------------------------------- programs

def _random_program(rng, start, lo, hi, rates, soaks, duration_s, dt, first_extreme=None):
    """Soaks and ramps between ``lo`` and ``hi`` until ``duration_s``; the first two ramps reach the
    extremes exactly, later ones turn within 10 C of them."""
    segs = [("soak", rng.uniform(*soaks))]
    going_down = rng.random() < 0.5 if first_extreme is None else first_extreme == "lo"
    cur, total, k = start, segs[0][1], 0
    while total < duration_s:
        if k < 2:
            target = lo if going_down else hi
        else:
            target = rng.uniform(lo, lo + 10) if going_down else rng.uniform(hi - 10, hi)
        rate = rng.uniform(*rates)
        segs.append(("ramp", target, rate))
        total += abs(target - cur) / rate * 60.0
        soak = rng.uniform(*soaks)
        segs.append(("soak", soak))
        total += soak
        cur, going_down, k = target, not going_down, k + 1
    sp = ph.program(segs, start, dt)
    return sp[: int(duration_s / dt)]


def _programs(rng, kind: str, dt: float):
    lo, hi = rng.uniform(-25, -10), rng.uniform(40, 55)
    train = _random_program(rng, rng.uniform(15, 30), lo, hi, (0.5, 1.5), (1200, 3000), 10 * 3600, dt)
    vlo, vhi = rng.uniform(lo + 3, lo + 10), rng.uniform(hi - 10, hi - 3)
    rates, dur, soaks = (0.3, 2.0), rng.uniform(6, 8) * 3600, (900, 2400)
    first = None
    if kind == "colder":
        vlo, first = lo - rng.uniform(6, 12), "lo"
    elif kind == "hotter":
        vhi, first = hi + rng.uniform(5, 10), "hi"
    elif kind == "steeper":
        rates = (2.0, 3.5)
    elif kind == "short":
        dur, rates, soaks = rng.uniform(1.5, 2.5) * 3600, (1.0, 2.0), (300, 900)
    start = rng.uniform(vlo + 5, vhi - 5)
    val = _random_program(rng, start, vlo, vhi, rates, soaks, dur, dt, first)
    return train, val


# ------------------------------------------------------------------------------------------- runs

def _make_run(rng, unit: ph.Unit, sp: np.ndarray, dt: float, probe_gaps: bool):
    n = len(sp)
    t = np.arange(n) * dt
    air, nodes = ph.node_temperatures(unit, sp, dt)
    truth = ph.probe_truth(unit, nodes)
    readings = ph.probe_readings(unit, truth, t, rng)
    noise = {ch: ph.gyro_noise(unit, ch, n, dt, rng) for ch in CHANNELS}
    # rows that never arrived: a few gaps of 20-600 s and 0.1 % single dropped frames
    keep = np.ones(n, bool)
    for _ in range(int(rng.integers(1, 5))):
        a = int(rng.integers(0, n - 1))
        keep[a: a + int(rng.uniform(20, 600) / dt)] = False
    keep &= rng.random(n) > 0.001
    keep[0] = keep[-1] = True
    if probe_gaps:                       # a failed conversion (CRC error): an empty cell
        for p in readings:
            r = readings[p].copy()
            r[rng.random(n) < 0.0005] = np.nan
            readings[p] = r
    return t, sp, air, truth, readings, noise, keep


def _subset(run: RunData, keep: np.ndarray) -> RunData:
    return RunData(run.t[keep], run.sp[keep], run.air[keep], {k: v[keep] for k, v in run.truth.items()},
                   {k: v[keep] for k, v in run.readings.items()}, {k: v[keep] for k, v in run.gyro.items()},
                   {k: v[keep] for k, v in run.noise.items()}, run.dt)


# ---------------------------------------------------------------------------------------- effects

def regressor(e: Effect, t: np.ndarray, truth: dict[str, np.ndarray], dt: float, rng_phase: float = 0.0,
              step_at: float | None = None) -> np.ndarray:
    """The hidden effect's shape on one run (per row of the uninterrupted run)."""
    if e.kind == "thermal_lag":
        return ph.first_order(truth[e.probes[0]], dt, e.params["tau_s"])
    if e.kind == "gradient":
        return truth[e.probes[0]] - truth[e.probes[1]]
    if e.kind == "rate":
        return ph.derivative_per_min(truth[e.probes[0]], dt)
    if e.kind in ("hysteresis", "gradual_hysteresis"):
        # the memory's state at power-on comes from the unit's history: the lab brings it to the start
        # temperature from the side opposite to the run's first ramp (a heat/cool balanced
        # pre-conditioning, 3 widths and at least 15 C away), so the state at the start is the one the
        # first ramp reverses, which the data themselves tell
        x = truth[e.probes[0]]
        w = e.params["width_c"]
        moved = np.flatnonzero(np.abs(x - x[0]) >= w)
        first = np.sign(x[moved[0]] - x[0]) if moved.size else 1.0
        pre = np.linspace(x[0] + first * max(PRE_HISTORY_C, 3 * w), x[0], PRE_HISTORY_N)
        memory = ph.relay if e.kind == "hysteresis" else ph.duhem
        return memory(np.concatenate([pre, x]), e.params["width_c"])[PRE_HISTORY_N:]
    if e.kind == "warmup":
        return np.exp(-t / e.params["tau_s"])
    if e.kind == "sinusoid":
        return np.sin(2 * np.pi * t / e.params["period_s"] + rng_phase)
    if e.kind == "bias_step":
        return (t >= step_at).astype(float)
    raise ValueError(f"unknown effect kind {e.kind!r}")


def _draw_effect(rng, kind: str, own: str) -> Effect:
    if kind == "thermal_lag":
        return Effect(kind, (str(rng.choice(PROBES)),), {"tau_s": float(rng.uniform(300, 1800))})
    if kind == "gradient":
        pair = rng.choice(PROBES, 2, replace=False)
        return Effect(kind, (str(pair[0]), str(pair[1])))
    if kind == "rate":
        return Effect(kind, (str(rng.choice(PROBES)),))
    if kind == "hysteresis":
        return Effect(kind, (str(rng.choice(PROBES)),), {"width_c": float(rng.uniform(2, 8))})
    if kind == "gradual_hysteresis":
        return Effect(kind, (str(rng.choice(PROBES)),), {"width_c": float(rng.uniform(3, 10))})
    if kind == "warmup":
        return Effect(kind, (), {"tau_s": float(rng.uniform(300, 1200))})
    if kind == "sinusoid":
        return Effect(kind, (), {"period_s": float(rng.uniform(1500, 4000))})
    if kind == "bias_step":
        return Effect(kind, ())
    raise ValueError(kind)


def block_means(t: np.ndarray, x: np.ndarray, ok: np.ndarray | None = None, block_s: float = 100.0,
                dt: float = 1.0) -> np.ndarray:
    """Means of ``x`` over 100-s blocks of ``t`` that hold at least half their samples, all ``ok``."""
    ok = np.ones(len(t), bool) if ok is None else ok
    ok = ok & np.isfinite(x)
    b = np.floor((t - t[0]) / block_s).astype(int)
    nb = b[-1] + 1
    count = np.bincount(b, minlength=nb)
    good = np.bincount(b, weights=ok.astype(float), minlength=nb)
    s = np.bincount(b, weights=np.where(ok, x, 0.0), minlength=nb)
    use = (good == count) & (count >= 0.5 * block_s / dt)
    return s[use] / count[use]


def std100(t, x, ok=None, dt=1.0) -> float:
    m = block_means(t, x, ok, dt=dt)
    return float(np.std(m, ddof=1)) if len(m) > 2 else float("nan")


def declared_design(temp: np.ndarray) -> np.ndarray:
    d = temp - 25.0
    return np.column_stack([np.ones_like(d), d, d ** 2, d ** 3])


def _fill(x: np.ndarray) -> np.ndarray:
    """Probe readings with the failed conversions held from the previous read (for our own fits)."""
    x = x.copy()
    bad = np.isnan(x)
    if bad.any():
        idx = np.where(~bad, np.arange(len(x)), 0)
        np.maximum.accumulate(idx, out=idx)
        x = x[idx]
    return x


# ------------------------------------------------------------------------------------------- build

def make_case(cls: str, seed: int) -> Case:
    if cls not in CLASSES:
        raise ValueError(f"unknown case class {cls!r} (known: {', '.join(CLASSES)})")
    vkind, hidden, flicker = CLASSES[cls]
    rng = np.random.default_rng([zlib.crc32(cls.encode()), seed])
    unit = ph.draw_unit(rng, CHANNELS, flicker)
    cp = {c: str(p) for c, p in ph.channel_probe_map(unit).items()}
    dt = 2.0 if rng.random() < 0.25 else 1.0
    probe_gaps = rng.random() < 0.5
    target = str(rng.choice(CHANNELS))
    own = cp[target]
    sp_tr, sp_va = _programs(rng, vkind, dt)
    raw = {}
    for name, sp in (("train", sp_tr), ("validate", sp_va)):
        t, sp_, air, truth, readings, noise, keep = _make_run(rng, unit, sp, dt, probe_gaps)
        raw[name] = (RunData(t, sp_, air, truth, readings, {}, noise, dt), keep)

    # the declared physics: a cubic in each channel's own probe temperature
    coefs = {ch: rng.normal(0, 1, 4) * np.array([1.0, 0.03, 4e-4, 5e-6]) for ch in CHANNELS}
    for name in raw:
        run = raw[name][0]
        for ch in CHANNELS:
            earth = EARTH_DPH * (np.cos(np.radians(LATITUDE)) if ch == "x" else
                                 np.sin(np.radians(LATITUDE)) if ch == "y" else 0.0)
            run.gyro[ch] = declared_design(run.truth[cp[ch]]) @ coefs[ch] + earth + run.noise[ch]

    wanted: list[str] = []
    for h in hidden:
        if h == "pair":
            a, b = rng.choice(["thermal_lag", "rate", "hysteresis", "warmup", "gradient"], 2, replace=False)
            wanted += [str(a), str(b)]
        elif h == "any":
            wanted.append(str(rng.choice(["thermal_lag", "rate", "hysteresis", "warmup", "gradient"])))
        else:
            wanted.append(h)

    effects: list[Effect] = []
    tr, ktr = raw["train"]
    va, kva = raw["validate"]
    x_tr = declared_design(_fill(tr.readings[own]))[ktr]
    pinv = np.linalg.pinv(x_tr)
    floor = std100(tr.t[ktr], tr.noise[target][ktr], dt=dt)
    for kind in wanted:
        for _attempt in range(40):
            e = _draw_effect(rng, kind, own)
            if any(o.label() == e.label() or (o.kind == e.kind and kind == "warmup") for o in effects):
                continue
            phase_tr, phase_va = rng.uniform(0, 2 * np.pi, 2)
            step_tr = rng.uniform(0.2, 0.8) * tr.t[-1]
            step_va = rng.uniform(0.2, 0.8) * va.t[-1]
            r_tr = regressor(e, tr.t, tr.truth, dt, phase_tr, step_tr)
            r_va = regressor(e, va.t, va.truth, dt, phase_va, step_va)
            left = r_tr[ktr] - x_tr @ (pinv @ r_tr[ktr])
            s_left, s_raw = std100(tr.t[ktr], left, dt=dt), std100(tr.t[ktr], r_tr[ktr], dt=dt)
            if not (s_left > 0.1 * s_raw) or not np.isfinite(s_left):
                continue                     # the declared cubic would absorb it: draw again
            e.gain = float(rng.uniform(4, 8) * floor / s_left * rng.choice([-1.0, 1.0]))
            tr.gyro[target] = tr.gyro[target] + e.gain * r_tr
            va.gyro[target] = va.gyro[target] + e.gain * r_va
            if kind == "sinusoid":
                e.params.update({"phase_train": phase_tr, "phase_validate": phase_va})
            if kind == "bias_step":
                e.params.update({"step_train_s": step_tr, "step_validate_s": step_va})
            e.rows = {"train": r_tr[ktr], "validate": r_va[kva]}
            effects.append(e)
            break
        else:
            raise RuntimeError(f"{cls} seed {seed}: no drawable {kind} effect")

    train, validate = _subset(tr, ktr), _subset(va, kva)
    meta = {"gyro_id": f"HELDOUT-{zlib.crc32(cls.encode()) % 1000:03d}-{seed}", "gyro_type": "rlg",
            "sample_period_s": repr(dt), "channel_probes": cp}
    return Case(cls, seed, target, cp, effects, train, validate,
                to_csv(train, meta, "TRAIN"), to_csv(validate, meta, "VALIDATE"))


def to_csv(run: RunData, meta: dict, what: str) -> str:
    """Measured-data CSV v1 text (written here, independently of the product's writer)."""
    lines = [f"# gyro_id: {meta['gyro_id']}", f"# gyro_type: {meta['gyro_type']}",
             f"# sample_period_s: {meta['sample_period_s']}",
             "# channel_probes: " + ",".join(f"{c}={p}" for c, p in meta["channel_probes"].items()),
             f"# notes: held-out {what} run"]
    cols = ["time_s"] + [f"gyro_{c}" for c in CHANNELS] + [f"temp_{p}" for p in PROBES] + \
        ["power", "chamber_pv", "chamber_sp"]
    lines.append(",".join(cols))
    pv = np.round(run.air, 1)
    data = [run.t] + [run.gyro[c] for c in CHANNELS] + [run.readings[p] for p in PROBES] + \
        [np.ones_like(run.t), pv, np.round(run.sp, 2)]
    fmt = [lambda v: f"{v:.1f}"] + [lambda v: f"{v:.6f}"] * 3 + [lambda v: "" if v != v else f"{v:.4f}"] * 4 + \
        [lambda v: f"{v:.0f}", lambda v: f"{v:.1f}", lambda v: f"{v:.2f}"]
    cols_txt = [[f(v) for v in col.tolist()] for f, col in zip(fmt, data)]
    lines += [",".join(row) for row in zip(*cols_txt)]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------- the oracle

def in_range(case: Case) -> np.ndarray:
    """Validation rows whose declared-model input (the target channel's own probe) lies inside the
    range that probe covered on TRAIN."""
    own = case.channel_probes[case.channel]
    tr, va = _fill(case.train.readings[own]), _fill(case.validate.readings[own])
    return (va >= tr.min()) & (va <= tr.max())


def reference_errors(case: Case) -> dict[str, float]:
    """On the in-range validation blocks: std of 100-s means of the declared model alone ("before"),
    of the declared model plus the true library effects in their true form ("oracle", least squares
    on TRAIN), and of the noise alone ("noise")."""
    own = case.channel_probes[case.channel]
    tr, va, ch, dt = case.train, case.validate, case.channel, case.train.dt
    x_tr, x_va = declared_design(_fill(tr.readings[own])), declared_design(_fill(va.readings[own]))
    ok = in_range(case)
    out = {}
    b, *_ = np.linalg.lstsq(x_tr, tr.gyro[ch], rcond=None)
    out["before"] = std100(va.t, va.gyro[ch] - x_va @ b, ok, dt)
    cols_tr, cols_va = [x_tr], [x_va]
    for e in case.library_effects:
        cols_tr.append(e.rows["train"][:, None])
        cols_va.append(e.rows["validate"][:, None])
    a_tr, a_va = np.hstack(cols_tr), np.hstack(cols_va)
    b, *_ = np.linalg.lstsq(a_tr, tr.gyro[ch], rcond=None)
    out["oracle"] = std100(va.t, va.gyro[ch] - a_va @ b, ok, dt)
    out["noise"] = std100(va.t, va.noise[ch], ok, dt)
    out["coverage"] = float(ok.mean())
    return out
