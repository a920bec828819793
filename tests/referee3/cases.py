"""Case classes of the third referee: one gyro unit (two channels), a TRAIN and a VALIDATE run, a
declared model and the truth per channel.

Each run is simulated at 1 s (chamber air -> network -> probes, gyro bias + noise) and logged at
``period_s`` (1 s or 10 s): the gyro averaged over the period, the probes read at the period's end.
Power is off for the first minutes of each run (no gyro rows' values) and once in mid-TRAIN.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tests.referee3 import physics as ph
from tests.referee3.effects import Effect, LIBRARY_KINDS, column

CHANNELS = ("x", "y")
LATITUDE_DEG = 48.1
EARTH_DPH = 15.041067


@dataclass
class Run:
    columns: dict[str, np.ndarray]          # as recorded: time_s, gyro_<ch>, temp_<p>, power
    meta: dict[str, str]
    period_s: float
    truth_temps: dict[str, np.ndarray]       # probe die temperatures on the recorded grid
    hidden: dict[str, np.ndarray]            # unrecorded drivers on the recorded grid
    noise: dict[str, np.ndarray]             # per channel, gyro noise on the recorded grid


@dataclass
class ChannelTruth:
    probe: str                               # the channel's own probe
    effects: list[Effect]                    # missing from the declared model
    declared_extra: list[Effect] = field(default_factory=list)   # true terms the model declares
    poly: tuple[float, ...] = ()

    @property
    def unrecorded(self) -> bool:
        return any(e.kind not in LIBRARY_KINDS for e in self.effects)


@dataclass
class Case:
    cls: str
    seed: int
    model: str
    train: Run
    validate: Run
    truth: dict[str, ChannelTruth]
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"{self.cls}/seed{self.seed}"


# ------------------------------------------------------------------------------ programs

def train_program(rng) -> tuple[list, float]:
    start = rng.uniform(15, 28)
    low, high = rng.uniform(-20, -5), rng.uniform(40, 55)
    r = lambda: rng.uniform(0.4, 1.0)          # noqa: E731 - C/min
    soak = lambda: rng.uniform(35, 60)          # noqa: E731 - minutes
    seg = [("soak", rng.uniform(15, 25), 0), ("ramp", low, r()), ("soak", soak(), 0), ("ramp", high, r()),
           ("soak", soak(), 0), ("ramp", rng.uniform(10, 25), r()), ("soak", soak() * 0.6, 0),
           ("ramp", rng.uniform(30, 38), r()), ("soak", 20, 0)]
    return seg, start


def validate_program(rng, kind: str, train_low: float, train_high: float) -> tuple[list, float]:
    """``kind``: inside, colder, hotter, steeper; ``short`` programs are about 2 h."""
    r = lambda: rng.uniform(1.2, 2.5)           # noqa: E731 - steeper than training
    start = rng.uniform(25, 35)
    lo = train_low + rng.uniform(3, 8)
    hi = train_high - rng.uniform(3, 8)
    if kind == "colder":
        lo = train_low - rng.uniform(5, 12)
    if kind == "hotter":
        hi = train_high + rng.uniform(5, 10)
    if kind == "short":
        return [("soak", 10, 0), ("ramp", hi, r()), ("soak", 15, 0), ("ramp", lo + 15, r()),
                ("soak", 15, 0), ("ramp", start, r())], start
    return [("soak", 10, 0), ("ramp", lo, r()), ("soak", rng.uniform(20, 35), 0), ("ramp", hi, r()),
            ("soak", rng.uniform(20, 35), 0), ("ramp", rng.uniform(5, 15), r()), ("soak", 20, 0),
            ("ramp", start, r()), ("soak", 10, 0)], start


# ------------------------------------------------------------------------------ unit and runs

@dataclass
class Unit:
    net: ph.Network
    probes: list[ph.Probe]
    channel_probes: dict[str, str]
    noise: dict                              # white_dph, b_dph, k_rrw
    board_w: float


def draw_unit(rng, n_probes: int, strong_flicker: bool = False) -> Unit:
    net = ph.draw_network(rng, CHANNELS)
    probes = [ph.Probe(f"t{i + 1}", f"sense_{c}", rng.uniform(8, 40), rng.uniform(-0.3, 0.3), 0.01)
              for i, c in enumerate(CHANNELS)]
    extra_nodes = list(rng.permutation(["case", "base"]))
    for k in range(n_probes - len(CHANNELS)):
        probes.append(ph.Probe(f"t{len(probes) + 1}", str(extra_nodes[k]), rng.uniform(8, 40),
                               rng.uniform(-0.3, 0.3), 0.01))
    noise = dict(white_dph=rng.uniform(0.08, 0.25), b_dph=rng.uniform(0.008, 0.025),
                 k_rrw=rng.uniform(2e-5, 1.2e-4))
    if strong_flicker:
        noise["b_dph"] = rng.uniform(0.03, 0.05)
    return Unit(net, probes, {c: probes[i].name for i, c in enumerate(CHANNELS)}, noise, rng.uniform(0.5, 2.0))


def _load_schedule(rng, n: int, dt: float, varying: bool) -> np.ndarray:
    """Electronics dissipation factor: 1, or random levels every 30-120 min when ``varying``."""
    if not varying:
        return np.ones(n)
    out = np.empty(n)
    k = 0
    while k < n:
        m = int(rng.uniform(1800, 7200) / dt)
        out[k:k + m] = rng.uniform(0.2, 3.0)
        k += m
    return out


def _humidity(rng, n: int, air: np.ndarray) -> np.ndarray:
    """Water taken up by the coil potting: the chamber's absolute humidity (dryer cycles and door
    events, random levels every 40-150 min) through a 20-60 min absorption lag.  Not recorded."""
    ah = np.empty(n)
    k = 0
    while k < n:
        m = int(rng.uniform(2400, 9000))
        ah[k:k + m] = rng.uniform(2, 12)        # g/m^3
        k += m
    ah = ph.lowpass(ah, 600.0)
    return ph.lowpass(ah, rng.uniform(1200, 3600))


def simulate_run(unit: Unit, segments, start_c, rng, *, period_s: float, power_off: list[tuple[float, float]],
                 varying_load: bool, mode_threshold_c: float | None) -> dict:
    """1-s physics of one run; returns 1-s arrays (temps, hidden drivers, power)."""
    sp = ph.setpoint_program(segments, start_c)
    n = sp.size
    n -= n % int(period_s)
    sp = sp[:n]
    t = np.arange(n, dtype=float)
    air = ph.chamber_air(sp, rng)
    power = np.ones(n)
    for a, b in power_off:
        power[(t >= a) & (t < b)] = 0.0
    load = _load_schedule(rng, n, 1.0, varying_load)
    nodes = ph.integrate_network(unit.net, air, unit.board_w * load * power)
    node = {name: nodes[i] for i, name in enumerate(unit.net.names)}
    die = {p.name: ph.probe_physical(node[p.node], p) for p in unit.probes}
    hidden = {"humidity": _humidity(rng, n, air),
              "internal_node": node["board"] - node["case"]}
    if mode_threshold_c is not None:
        hidden["mode_hop"] = (node["board"] > mode_threshold_c).astype(float)
    return dict(t=t, power=power, die=die, hidden=hidden, air=air, node=node)


def log_run(unit: Unit, sim: dict, bias: dict[str, np.ndarray], noise: dict[str, np.ndarray], rng,
            period_s: float) -> Run:
    """The data logger: gyro averaged over each period, probes read at its end, power at its end."""
    p = int(period_s)
    n = sim["t"].size // p
    end = np.arange(n) * p + (p - 1)
    cols: dict[str, np.ndarray] = {"time_s": sim["t"][end] + 1.0}
    on = sim["power"].reshape(n, p).min(axis=1) >= 0.5
    for ch in CHANNELS:
        g = (bias[ch] + noise[ch]).reshape(n, p).mean(axis=1)
        cols[f"gyro_{ch}"] = np.where(on, g, np.nan)
    truth_temps = {}
    for pr in unit.probes:
        reading = ph.probe_reading(sim["die"][pr.name], pr, rng)
        cols[f"temp_{pr.name}"] = reading[end]
        truth_temps[pr.name] = sim["die"][pr.name][end]
    cols["power"] = sim["power"][end]
    meta = {"gyro_id": "R3", "gyro_type": "fog", "latitude_deg": f"{LATITUDE_DEG}",
            "sample_period_s": f"{period_s:g}",
            "channel_probes": ",".join(f"{c}={unit.channel_probes[c]}" for c in CHANNELS)}
    hidden = {k: v[end] for k, v in sim["hidden"].items()}
    nz = {ch: noise[ch].reshape(n, p).mean(axis=1) for ch in CHANNELS}
    return Run(cols, meta, period_s, truth_temps, hidden, nz)


# ------------------------------------------------------------------------------ CSV

def format_csv(run: Run) -> str:
    lines = [f"# {k}: {v}" for k, v in run.meta.items()]
    names = list(run.columns)
    lines.append(",".join(names))
    cols = [run.columns[k] for k in names]
    for i in range(cols[0].size):
        cells = []
        for name, c in zip(names, cols):
            v = c[i]
            if np.isnan(v):
                cells.append("")
            elif name == "power":
                cells.append(str(int(v)))
            elif name == "time_s":
                cells.append(f"{v:.1f}")
            else:
                cells.append(repr(float(v)) if name.startswith("temp_") else f"{v:.6f}")
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ case classes

# class -> (validation program, logger period, strong flicker, missing effects on the target channel,
#           declared model)
CLASSES: dict[str, dict] = {
    "complete_colder": dict(val="colder", effects=[]),
    "complete_hotter": dict(val="hotter", effects=[]),
    "complete_steeper": dict(val="inside", effects=[]),
    "complete_flicker_short": dict(val="short", flicker=True, effects=[]),
    "complete_declared_rate": dict(val="inside", effects=[], declared_rate=True),
    "lag": dict(val="inside", effects=["lag"]),
    "long_lag": dict(val="inside", effects=["long_lag"]),
    "gradient": dict(val="inside", effects=["gradient"]),
    "rate": dict(val="inside", effects=["rate"]),
    "rate_squared": dict(val="inside", effects=["rate_squared"]),
    "temp_rate": dict(val="inside", effects=["temp_rate"]),
    "relay_hysteresis": dict(val="inside", effects=["relay"]),
    "gradual_hysteresis": dict(val="inside", effects=["play"]),
    "warmup": dict(val="inside", effects=["warmup"]),
    "time_drift": dict(val="inside", effects=["time_drift"]),
    "effect_validation_colder": dict(val="colder", effects=["any"]),
    "two_effects": dict(val="inside", effects=["any", "any"]),
    "three_effects": dict(val="inside", effects=["any", "any", "any"]),
    "effect_sampled_10s": dict(val="inside", period=10.0, effects=["any"]),
    "effect_flicker_short": dict(val="short", flicker=True, effects=["any"]),
    "unrecorded_humidity": dict(val="inside", effects=["humidity"]),
    "unrecorded_internal_node": dict(val="inside", effects=["internal_node"], load=True),
    "unrecorded_mode_hop": dict(val="inside", effects=["mode_hop"], load=True),
}
ANY_KINDS = ("lag", "gradient", "rate", "rate_squared", "temp_rate", "relay", "play", "warmup")


def _draw_effect(kind: str, rng, probes: list[str], own: str) -> Effect:
    if kind == "any":
        kind = str(rng.choice(ANY_KINDS))
    pick = lambda: str(rng.choice(probes))     # noqa: E731
    if kind == "lag":
        return Effect("lag", (pick(),), {"tau_s": float(rng.uniform(600, 3000))})
    if kind == "long_lag":
        return Effect("lag", (pick(),), {"tau_s": float(rng.uniform(5400, 14400))})
    if kind == "gradient":
        a, b = rng.choice(probes, 2, replace=False)
        return Effect("gradient", (str(a), str(b)))
    if kind in ("rate", "rate_squared", "temp_rate"):
        return Effect(kind, (pick(),))
    if kind == "relay":
        return Effect("relay", (pick(),), {"width_c": float(rng.uniform(0.5, 3.0))})
    if kind == "play":
        return Effect("play", (pick(),), {"width_c": float(rng.uniform(4.0, 15.0))})
    if kind == "warmup":
        return Effect("warmup", (), {"tau_s": float(rng.uniform(600, 2400))})
    if kind == "time_drift":
        return Effect("time_drift")
    if kind in ("humidity", "internal_node", "mode_hop"):
        return Effect(kind)
    raise ValueError(kind)


def block_std(x: np.ndarray, t_s: np.ndarray, ok: np.ndarray, block_s: float = 100.0) -> float:
    """Std of the means of the 100-s blocks (from the first time) all of whose samples are ``ok``
    (and measured: NaN in ``x`` is not ok)."""
    ok = ok & np.isfinite(x)
    b = np.floor((t_s - t_s[0]) / block_s).astype(int)
    nb = b[-1] + 1
    cnt = np.bincount(b, minlength=nb)
    good_cnt = np.bincount(b, weights=ok.astype(float), minlength=nb)
    sums = np.bincount(b, weights=np.where(ok, x, 0.0), minlength=nb)
    full = (good_cnt == cnt) & (cnt > 0)
    if full.sum() < 3:
        return float("nan")
    return float(np.std(sums[full] / cnt[full], ddof=1))


def _poly_design(temp: np.ndarray) -> np.ndarray:
    d = temp - 20.0
    return np.column_stack([np.ones_like(d), d, d ** 2, d ** 3])


def build_case(cls: str, seed: int) -> Case:
    import zlib

    spec = CLASSES[cls]
    rng = np.random.default_rng([seed, zlib.crc32(cls.encode())])
    period = float(spec.get("period", 1.0))
    n_probes = int(rng.integers(3, 5)) if spec["effects"] else int(rng.integers(2, 5))
    unit = draw_unit(rng, n_probes, strong_flicker=bool(spec.get("flicker")))
    tr_seg, tr_start = train_program(rng)
    tr_low = min(s[1] for s in tr_seg if s[0] == "ramp")
    tr_high = max(s[1] for s in tr_seg if s[0] == "ramp")
    va_seg, va_start = validate_program(rng, spec["val"], tr_low, tr_high)
    load = bool(spec.get("load"))
    n_tr = ph.setpoint_program(tr_seg, tr_start).size
    off_mid = rng.uniform(0.4, 0.6) * n_tr
    sims = {"train": simulate_run(unit, tr_seg, tr_start, rng, period_s=period, varying_load=load,
                                  power_off=[(0, 600), (off_mid, off_mid + 900)], mode_threshold_c=None),
            "validate": simulate_run(unit, va_seg, va_start, rng, period_s=period, varying_load=load,
                                     power_off=[(0, 300)], mode_threshold_c=None)}
    board = sims["train"]["node"]["board"]
    thr = float(np.quantile(board, rng.uniform(0.35, 0.65)))
    for s in sims.values():
        s["hidden"]["mode_hop"] = (s["node"]["board"] > thr).astype(float)

    probes = [p.name for p in unit.probes]
    target = str(rng.choice(CHANNELS))
    earth = {"x": EARTH_DPH * np.cos(np.radians(LATITUDE_DEG)), "y": EARTH_DPH * np.sin(np.radians(LATITUDE_DEG))}
    declared_rate = bool(spec.get("declared_rate"))
    model = "tc + tc^2 + tc^3 + dtc" if declared_rate else "tc + tc^2 + tc^3"
    truth: dict[str, ChannelTruth] = {}
    bias = {"train": {}, "validate": {}}
    noise = {"train": {}, "validate": {}}
    notes = []
    for ch in CHANNELS:
        own = unit.channel_probes[ch]
        for run, s in sims.items():
            noise[run][ch] = ph.gyro_noise(s["t"].size, rng=rng, **unit.noise)
        poly = (rng.normal(0, 2.0), rng.choice([-1, 1]) * rng.uniform(0.01, 0.05),
                rng.choice([-1, 1]) * rng.uniform(1e-4, 5e-4), rng.choice([-1, 1]) * rng.uniform(1e-6, 5e-6))
        ct = ChannelTruth(own, [], poly=tuple(float(p) for p in poly))
        if declared_rate:
            ct.declared_extra.append(Effect("own_rate", (own,), coef=float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.0))))
        kinds = spec["effects"] if ch == target else []
        ct.effects = _draw_effects(kinds, rng, probes, own, sims, noise, ct, ch)
        truth[ch] = ct
        for run, s in sims.items():
            temp = s["die"][own]
            b = _poly_design(temp) @ np.asarray(ct.poly) + earth[ch]
            for e in ct.declared_extra + ct.effects:
                b = b + e.coef * column(e, s["die"], s["t"], s["power"], s["hidden"], 1.0)
            bias[run][ch] = b
    runs = {run: log_run(unit, sims[run], bias[run], noise[run], rng, period) for run in sims}
    notes.append(f"target channel {target}; probes "
                 + ", ".join(f"{p.name}@{p.node}" for p in unit.probes))
    return Case(cls, seed, model, runs["train"], runs["validate"], truth, notes)


def _draw_effects(kinds, rng, probes, own, sims, noise, ct: ChannelTruth, ch: str, tries: int = 40) -> list[Effect]:
    """Draw the missing effects and size each at 4-10 noise floors in what the declared model and the
    other effects cannot absorb (on TRAIN and on the in-range VALIDATE samples); redraw a draw that the
    others would mostly absorb."""
    if not kinds:
        return []
    tr, va = sims["train"], sims["validate"]
    on_va = va["power"] > 0.5
    floor = block_std(noise["validate"][ch], va["t"], on_va)
    tmin, tmax = tr["die"][own].min(), tr["die"][own].max()
    in_range = (va["die"][own] >= tmin) & (va["die"][own] <= tmax) & on_va
    on_tr = tr["power"] > 0.5

    def design(s, extra_cols):
        cols = [_poly_design(s["die"][own])]
        cols += [column(e, s["die"], s["t"], s["power"], s["hidden"], 1.0)[:, None] for e in ct.declared_extra]
        cols += [c[:, None] for c in extra_cols]
        return np.hstack(cols)

    for _ in range(tries):
        effects = [_draw_effect(k, rng, probes, own) for k in kinds]
        if len({(e.kind, e.probes) for e in effects}) < len(effects):
            continue
        cols = {run: [column(e, s["die"], s["t"], s["power"], s["hidden"], 1.0) for e in effects]
                for run, s in (("train", tr), ("validate", va))}
        ok = True
        for i, e in enumerate(effects):
            others_tr = [c for j, c in enumerate(cols["train"]) if j != i]
            others_va = [c for j, c in enumerate(cols["validate"]) if j != i]
            xtr, xva = design(tr, others_tr), design(va, others_va)
            u_tr, u_va = cols["train"][i], cols["validate"][i]
            beta = np.linalg.lstsq(xtr[on_tr], u_tr[on_tr], rcond=None)[0]
            a_tr = block_std(u_tr - xtr @ beta, tr["t"], on_tr)
            a_va = block_std(u_va - xva @ beta, va["t"], in_range)
            raw = block_std(u_tr - u_tr[on_tr].mean(), tr["t"], on_tr)
            vis = min(a_tr, a_va)
            if not np.isfinite(vis) or vis < 0.1 * raw or vis <= 0:
                ok = False
                break
            e.coef = float(rng.choice([-1, 1]) * rng.uniform(4, 10) * floor / vis)
        if ok:
            return effects
    raise RuntimeError(f"no visible draw of {kinds} in {tries} tries")
