"""Referee 8 case generator: deterministic from (class name, seed).

A case is one three-channel FOG unit, a TRAIN and a VALIDATE run, a declared formula and the truth:
per channel the effects the declared model lacks (kind + probes, product's kind names) with their
true columns on both runs, and the verdicts an honest analysis may give.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from . import physics as ph

CHANNELS = ("x", "y", "z")
SITES = {"x": "mount_x", "y": "mount_y", "z": "mount_z"}
T_REF = 25.0


# ----------------------------------------------------------------------------- chamber programs
def _knots_to_sp(knots, t):
    kt = np.array([k[0] for k in knots], float)
    kv = np.array([k[1] for k in knots], float)
    return np.interp(t, kt, kv)


def program(kind, rng, dur_s, lo, hi, start=None):
    """Chamber set-point knots [(t, T)] covering [-pre, dur_s]. Own mix of programs."""
    T0 = lo if start is None else start
    kn = [(0.0, T0)]
    t = 0.0
    cur = T0
    if kind == "ramp_dwell":              # staircase of ramps (0.3-0.8 C/min) and 30-70 min dwells
        levels = list(np.linspace(lo, hi, rng.integers(3, 5)))
        seq = levels[1:] + levels[-2::-1]
        i = 0
        while t < dur_s:
            tgt = seq[i % len(seq)]
            i += 1
            r = rng.uniform(0.3, 0.8) / 60.0
            t += abs(tgt - cur) / r
            kn.append((t, tgt))
            cur = tgt
            t += rng.uniform(30, 70) * 60
            kn.append((t, cur))
    elif kind == "triangle":              # continuous triangle, period 3-5 h
        per = rng.uniform(3, 5) * 3600
        up = True
        while t < dur_s:
            tgt = hi if up else lo
            t += per / 2 * abs(tgt - cur) / (hi - lo)
            kn.append((t, tgt))
            cur, up = tgt, not up
    elif kind == "shock":                 # fast transfers (3-5 C/min) between levels, 60-100 min dwells
        levels = [lo, hi, 0.5 * (lo + hi), hi, lo]
        i = 0
        while t < dur_s:
            tgt = levels[i % len(levels)] + rng.uniform(-1.5, 1.5)
            tgt = min(max(tgt, lo), hi)
            i += 1
            t += abs(tgt - cur) / (rng.uniform(3, 5) / 60.0) + 1.0
            kn.append((t, tgt))
            cur = tgt
            t += rng.uniform(60, 100) * 60
            kn.append((t, cur))
    elif kind == "sine_walk":             # smooth random walk of the set-point (sum of slow sines)
        tt = np.arange(0.0, dur_s + 600, 300.0)
        y = np.zeros_like(tt)
        for _ in range(3):
            P = rng.uniform(2, 7) * 3600
            y += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * tt / P + rng.uniform(0, 6.28))
        y = (y - y.min()) / (y.max() - y.min())
        y = lo + (hi - lo) * y
        kn = [(0.0, y[0])] + [(a, b) for a, b in zip(tt[1:], y[1:])]
    else:
        raise ValueError(kind)
    return kn


# ----------------------------------------------------------------------------- case container
@dataclass
class Run:
    t: np.ndarray
    sp: np.ndarray
    air: np.ndarray
    power: np.ndarray
    temps: dict            # probe name -> recorded readings
    clean: dict            # probe name -> noiseless readings (die + offset)
    gyro: dict             # channel -> deg/h (NaN when off)
    noise: dict            # channel -> the noise part alone
    effects: dict          # channel -> list of true effect columns (scaled, deg/h)
    declared_true: dict    # channel -> declared part (deg/h)
    nodes: dict
    has_power: bool


@dataclass
class Case:
    cls: str
    seed: int
    dt: float
    formula: str
    probes: list
    channel_probes: dict
    latitude: float
    train: Run = None
    validate: Run = None
    truth: dict = field(default_factory=dict)     # channel -> dict(effects=[{kind, probes, ...}], verdicts=set, unrecorded=bool)
    notes: str = ""


def _seed_of(cls, seed):
    h = hashlib.sha256(f"referee8/{cls}/{seed}".encode()).digest()
    return int.from_bytes(h[:8], "little")


# ----------------------------------------------------------------------------- class designs
# Each design: profile kinds, durations, the declared formula and the per-channel truth specs.
# A truth spec is a list of effects: dict(kind, probe-role, params); roles: 'own', 'base', 'air',
# 'other' (another channel's probe).

def _design(cls, rng):
    d = dict(dt=1.0, train_prog="ramp_dwell", val_prog="triangle", train_h=rng.uniform(8.5, 11),
             val_h=rng.uniform(6, 7.5), lo=rng.uniform(-10, 5), hi=rng.uniform(40, 55),
             val_shrink=(0.12, 0.12), formula="tc + tc^2 + tc^3", flicker=1.0, power_cycles=(0, 0),
             pre="soak", air_probe=rng.random() < 0.5, specs={}, unrecorded=None, factor=rng.uniform(4.5, 7.5))
    ch = list(CHANNELS)
    rng.shuffle(ch)
    a, b = ch[0], ch[1]
    if cls == "complete_colder_val":
        d.update(val_prog="shock", val_shrink=(0.0, 0.35), train_prog="triangle")
    elif cls == "complete_flicker":
        d.update(flicker=4.0, train_prog="sine_walk", val_prog="ramp_dwell")
    elif cls == "lag_own":
        d["specs"] = {a: [dict(kind="lag", role="own", tau=rng.uniform(700, 2500))]}
    elif cls == "lag_base":
        d["specs"] = {a: [dict(kind="lag", role="base", tau=rng.uniform(400, 1800))]}
    elif cls == "gradient_base":
        d["specs"] = {a: [dict(kind="gradient", role="base")]}
        d.update(train_prog="shock", val_prog="ramp_dwell")
    elif cls == "rate_own":
        d["specs"] = {a: [dict(kind="rate", role="own")]}
    elif cls == "rate_sq":
        d["specs"] = {a: [dict(kind="rate_squared", role="own")]}
        d.update(train_prog="shock", val_prog="shock")
    elif cls == "cross":
        d["specs"] = {a: [dict(kind="temp_rate_cross", role="own")]}
        d.update(train_prog="triangle", val_prog="ramp_dwell")
    elif cls == "play_hyst":
        d["specs"] = {a: [dict(kind="hysteresis", role="own", width=rng.uniform(3.0, 6.0))]}
        d.update(train_prog="triangle", val_prog="ramp_dwell")
    elif cls == "warmup_cycles":
        d["specs"] = {a: [dict(kind="warmup", role=None, tau=rng.uniform(400, 1500))],
                      b: [dict(kind="warmup", role=None, tau=rng.uniform(400, 1500))]}
        d.update(power_cycles=(2, 1))
    elif cls == "time_drift":
        d["specs"] = {a: [dict(kind="time_drift", role=None)]}
    elif cls == "two_effects":
        d["specs"] = {a: [dict(kind="lag", role="base", tau=rng.uniform(500, 1500)),
                          dict(kind="rate", role="own")]}
        d.update(train_prog="shock", val_prog="triangle")
    elif cls == "long_tau":
        d["specs"] = {a: [dict(kind="lag", role="own", tau=rng.uniform(0.5, 0.9) * d["train_h"] * 3600)]}
        d.update(train_prog="sine_walk", val_prog="triangle")
    elif cls == "unrecorded_supply":
        d["unrecorded"] = {a: "supply"}
    elif cls == "short_validate":
        d["specs"] = {a: [dict(kind="gradient", role="air" if d["air_probe"] else "base")]}
        d.update(val_h=rng.uniform(1.8, 3.0), val_prog="shock")
    elif cls == "nonequilibrium_start":
        d["specs"] = {a: [dict(kind="lag", role="own", tau=rng.uniform(900, 2200))]}
        d.update(pre="ramp")
    elif cls == "half_second":
        d["specs"] = {a: [dict(kind="temp_rate_cross", role="own")]}
        d.update(dt=0.5, train_h=rng.uniform(7.5, 9), val_h=rng.uniform(5.5, 6.5))
    else:
        raise KeyError(cls)
    return d


CLASSES = ["complete_colder_val", "complete_flicker", "lag_own", "lag_base", "gradient_base", "rate_own",
           "rate_sq", "cross", "play_hyst", "warmup_cycles", "time_drift", "two_effects", "long_tau",
           "unrecorded_supply", "short_validate", "nonequilibrium_start", "half_second"]

# product effect kind names (from the report's effects_added[].kind)
KIND = {"lag": "thermal_lag", "gradient": "gradient", "rate": "rate", "rate_squared": "rate_squared",
        "temp_rate_cross": "temp_rate_cross", "hysteresis": "hysteresis", "warmup": "warmup",
        "time_drift": "time_drift"}


def _power_schedule(t, n_cycles, rng):
    p = np.ones_like(t)
    if n_cycles <= 0:
        return p
    span = t[-1]
    for k in range(n_cycles):
        start = span * (k + 1) / (n_cycles + 1) + rng.uniform(-0.08, 0.08) * span
        p[(t >= start) & (t < start + rng.uniform(12, 30) * 60)] = 0.0
    return p


def _simulate_run(d, rng, net, layout, hours, prog, lo, hi, pre, cycles):
    dt = d["dt"]
    dur = hours * 3600.0
    t = np.arange(0.0, dur, dt)
    start = lo + rng.uniform(0, 0.3) * (hi - lo) if pre == "soak" else None
    kn = program(prog, rng, dur + 3600, lo, hi, start=start)
    sp = _knots_to_sp(kn, t)
    pre_s = rng.uniform(2, 4) * 3600
    if pre == "ramp":       # logging begins while the unit is still catching up a fast ramp
        T_from = hi + 5.0
        sp_pre = lambda tt: np.interp(tt, [-pre_s, -1800.0, 0.0], [T_from, T_from, sp[0]])
    else:
        sp_pre = lambda tt: np.full_like(np.asarray(tt, float), sp[0])
    power = _power_schedule(t, cycles, rng)
    out = ph.simulate_network(net, layout["sites"], layout["glue"], t, sp, power, pre_s=pre_s, sp_pre=sp_pre)
    return t, sp, power, out


def build(cls, seed):
    rng = np.random.default_rng(_seed_of(cls, seed))
    d = _design(cls, rng)
    net = ph.default_network_params(rng)
    # probe layout: physical probes at mount_x/y/z and base (+ air), names assigned in a shuffled order
    phys = ["mount_x", "mount_y", "mount_z", "base"] + (["air"] if d["air_probe"] else [])
    names = [f"t{i + 1}" for i in range(len(phys))]
    order = list(rng.permutation(len(phys)))
    site_of = {names[order[i]]: phys[i] for i in range(len(phys))}
    probes = names
    layout = {"sites": [site_of[n] for n in probes], "glue": list(rng.uniform(15, 45, len(probes)))}
    layout["glue"] = [g if s != "air" else 8.0 for g, s in zip(layout["glue"], layout["sites"])]
    probe_at = {v: k for k, v in site_of.items()}
    chp = {c: probe_at[SITES[c]] for c in CHANNELS}
    offsets = rng.uniform(-0.25, 0.25, len(probes))
    rnoise = rng.uniform(0.01, 0.03, len(probes))
    lat = float(rng.uniform(30, 60))

    case = Case(cls=cls, seed=seed, dt=d["dt"], formula=d["formula"], probes=probes, channel_probes=chp,
                latitude=lat)
    lo, hi = d["lo"], d["hi"]
    span = hi - lo
    vlo, vhi = lo + d["val_shrink"][0] * span, hi - d["val_shrink"][1] * span
    if cls == "complete_colder_val":
        vlo, vhi = lo - 3.0, lo + 0.55 * span     # colder than TRAIN: part of it out of range
    runs = {}
    for rn, hours, prog, rlo, rhi, cyc, pre in (
            ("train", d["train_h"], d["train_prog"], lo, hi, d["power_cycles"][0], d["pre"]),
            ("validate", d["val_h"], d["val_prog"], vlo, vhi, d["power_cycles"][1], "soak")):
        t, sp, power, out = _simulate_run(d, rng, net, layout, hours, prog, rlo, rhi, pre, cyc)
        clean = {p: out["die"][i] + offsets[i] for i, p in enumerate(probes)}
        temps = {p: ph.probe_readings(out["die"][i:i + 1], offsets[i:i + 1], rnoise[i:i + 1], rng)[0]
                 for i, p in enumerate(probes)}
        pre_clean = {p: out["pre_die"][i] + offsets[i] for i, p in enumerate(probes)}
        runs[rn] = dict(t=t, sp=sp, power=power, out=out, clean=clean, temps=temps, pre_clean=pre_clean)

    # noise parameters per channel (tactical FOG)
    nz = {}
    for c in CHANNELS:
        nz[c] = dict(arw=rng.uniform(0.004, 0.012), bi=rng.uniform(0.004, 0.012) * d["flicker"],
                     rrw=rng.uniform(0.001, 0.004), lp=rng.choice([0.0, 0.0, 1.5]))
    for rn, r in runs.items():
        r["noise"] = {c: ph.gyro_noise(len(r["t"]), d["dt"], rng, nz[c]["arw"], nz[c]["bi"], nz[c]["rrw"],
                                       nz[c]["lp"]) for c in CHANNELS}

    # declared (true) part: cubic in the own probe's noiseless reading
    poly = {c: (rng.uniform(-0.08, 0.08), rng.uniform(-8e-4, 8e-4), rng.uniform(-1.5e-5, 1.5e-5),
                rng.uniform(-3, 3)) for c in CHANNELS}
    earth = {"x": EARTH * np.cos(np.radians(lat)), "y": EARTH * np.sin(np.radians(lat)), "z": 0.0}

    truth = {}
    role_probe = lambda c, role: {"own": chp[c], "base": probe_at["base"],
                                  "air": probe_at.get("air", probe_at["base"])}.get(role)
    for c in CHANNELS:
        specs = d["specs"].get(c, [])
        effs = []
        for s in specs:
            p = role_probe(c, s["role"]) if s["role"] else None
            cols = {rn: _effect_column(s, r, chp[c], p, d["dt"]) for rn, r in runs.items()}
            effs.append(dict(kind=KIND[s["kind"]], spec=s, probes=_truth_probes(s, chp[c], p), cols=cols))
        unrec = (d["unrecorded"] or {}).get(c)
        if unrec:
            cols = {rn: _supply_column(r, rng) for rn, r in runs.items()}
            effs.append(dict(kind="unrecorded_supply", spec={"kind": "supply"}, probes=(), cols=cols))
        # scale each effect so its part the declared model cannot absorb is factor x noise floor
        for e in effs:
            tr = runs["train"]
            floor = ph.std100(tr["t"], tr["noise"][c], valid=tr["power"] > 0.5)
            decl = _declared_cols(tr["clean"][chp[c]])
            un = _unabsorbed_std(tr["t"], e["cols"]["train"], decl, tr["power"] > 0.5)
            e["scale"] = float(d["factor"] * floor / un) * rng.choice([-1, 1])
            e["unabsorbed_frac"] = float(un / (np.nanstd(e["cols"]["train"]) + 1e-12))
            e["floor_train"] = float(floor)
        verdicts = ({"no_effect_missing"} if not effs else
                    {"unexplained_structure_remains"} if unrec else {"explained"})
        truth[c] = dict(effects=effs, verdicts=verdicts, unrecorded=bool(unrec), noise=nz[c])

    for rn, r in runs.items():
        gy, dec, effcols = {}, {}, {}
        for c in CHANNELS:
            T = r["clean"][chp[c]] - T_REF
            a1, a2, a3, b0 = poly[c]
            dec[c] = a1 * T + a2 * T ** 2 + a3 * T ** 3
            effcols[c] = [e["scale"] * e["cols"][rn] for e in truth[c]["effects"]]
            g = b0 + earth[c] + dec[c] + sum(effcols[c], np.zeros_like(T)) + r["noise"][c]
            g = np.where(r["power"] > 0.5, g, np.nan)
            gy[c] = g
        run = Run(t=r["t"], sp=r["sp"], air=r["out"]["air"], power=r["power"], temps=r["temps"], clean=r["clean"],
                  gyro=gy, noise=r["noise"], effects=effcols, declared_true=dec, nodes=r["out"],
                  has_power=bool((r["power"] < 0.5).any()) or d["power_cycles"][0] > 0)
        setattr(case, rn, run)
    case.truth = truth
    return case


EARTH = ph.EARTH_RATE_DPH


def _truth_probes(s, own, p):
    k = s["kind"]
    if k in ("warmup", "time_drift"):
        return ()
    if k == "gradient":
        return tuple(sorted((own, p)))
    return (p,)


def _declared_cols(T):
    x = T - T_REF
    return np.column_stack([x, x ** 2, x ** 3])


def _unabsorbed_std(t, col, decl, valid):
    m = [ph.block_means(t, col, valid=valid)[0]]
    for j in range(decl.shape[1]):
        m.append(ph.block_means(t, decl[:, j], valid=valid)[0])
    M = np.column_stack(m)
    M = M[np.all(np.isfinite(M), axis=1)]
    y = M[:, 0]
    X = np.column_stack([np.ones(len(M)), M[:, 1:]])
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(np.std(y - X @ beta, ddof=1))


def _effect_column(s, r, own, p, dt):
    """Unscaled true effect column on a run (before the scale)."""
    k = s["kind"]
    t = r["t"]
    if k == "lag":
        # a hidden element that follows the probe's node with time constant tau: column = lag(T) - T
        # (state at the first row: what the element held after the run's pre-history, computed below)
        T = r["clean"][p]
        y0 = _lag_start(r, p, s["tau"])
        return ph.first_order_lag(T, dt, s["tau"], y0=y0) - T
    if k == "gradient":
        return r["clean"][own] - r["clean"][p]
    if k == "rate":
        return ph.smooth_rate(r["clean"][p], dt, 20.0) * 60.0          # per C/min
    if k == "rate_squared":
        return (ph.smooth_rate(r["clean"][p], dt, 20.0) * 60.0) ** 2
    if k == "temp_rate_cross":
        T = r["clean"][p]
        return (T - 15.0) * ph.smooth_rate(T, dt, 20.0) * 60.0 / 10.0
    if k == "hysteresis":
        T = r["clean"][p]
        r0 = s["width"] / 2
        Tp = r["pre_clean"][p]          # the memory's state at the first row: its pre-history
        y0 = ph.play_operator(Tp, r0, y0=Tp[0] + r0 * 0.5)[-1] if len(Tp) else T[0]
        return ph.play_operator(T, r0, y0=y0) - T
    if k == "warmup":
        on = r["power"] > 0.5
        tsince = np.zeros_like(t)
        last = 0.0
        for i in range(len(t)):
            if i > 0 and on[i] and not on[i - 1]:
                last = t[i]
            tsince[i] = t[i] - last
        return np.where(on, np.exp(-tsince / s["tau"]), 0.0)
    if k == "time_drift":
        return t / 3600.0
    raise KeyError(k)


def _lag_start(r, p, tau):
    # the element's state at the first row: the lag run over the probe's simulated pre-history (the
    # unit starts that history in equilibrium at the pre-history's first set-point)
    Tp = r["pre_clean"][p]
    if not len(Tp):
        return r["clean"][p][0]
    dt = float(r["t"][1] - r["t"][0])
    Tp = np.append(Tp, r["clean"][p][0])
    return float(ph.first_order_lag(Tp, dt, tau)[-1])


def _supply_column(r, rng):
    """Supply voltage drift (no column records it): slow wander plus one mode hop."""
    t = r["t"]
    v = np.zeros_like(t)
    for _ in range(3):
        P = rng.uniform(1.0, 4.0) * 3600
        v += rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * t / P + rng.uniform(0, 6.28))
    hop = rng.uniform(0.3, 0.7) * t[-1]
    v += rng.uniform(0.8, 1.5) * (t > hop)
    return v - v.mean()


# ----------------------------------------------------------------------------- CSV (measured-data v1)
def _fmt(v, nd):
    return "" if not np.isfinite(v) else repr(round(float(v), nd))


def write_run(case, run, path, name):
    lines = [f"# gyro_id: R8-{case.cls}-{case.seed}", "# gyro_type: FOG",
             f"# latitude_deg: {case.latitude:.4f}", f"# sample_period_s: {case.dt}",
             "# channel_probes: " + ",".join(f"{c}={case.channel_probes[c]}" for c in CHANNELS),
             f"# notes: referee8 {case.cls} seed {case.seed} {name}"]
    cols = ["time_s"] + [f"gyro_{c}" for c in CHANNELS] + [f"temp_{p}" for p in case.probes] + ["chamber_sp"]
    if run.has_power:
        cols.append("power")
    lines.append(",".join(cols))
    n = len(run.t)
    data = [[_fmt(v, 3) for v in run.t]]
    data += [[_fmt(v, 5) for v in run.gyro[c]] for c in CHANNELS]
    data += [[repr(float(v)) for v in run.temps[p]] for p in case.probes]
    data.append([_fmt(v, 2) for v in run.sp])
    if run.has_power:
        data.append([str(int(v)) for v in run.power])
    rows = zip(*data)
    lines.extend(",".join(r) for r in rows)
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
