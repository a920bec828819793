"""Referee 9 case generator: one unit per case, three channels (x, y, z) with their own probes plus
structure probes, a TRAIN and a VALIDATE run, a declared model (named or formula) and the truth.

build(cls, seed) is deterministic (numpy default_rng seeded from the class name and the seed).  What
each class does: the README's "Ninth close-the-loop referee" section.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from . import physics as P

CHANNELS = ("x", "y", "z")

CLASSES = [
    "static_lag_cold",
    "dynamic_complete_flicker",
    "hrg_freq_gradient",
    "multipos_gsens",
    "irregular_logging",
    "warmup_power_drift",
    "short_validation",
    "unrecorded_supply",
]


# my kind names -> product kind names (filled from the product's JSON vocabulary)
PRODUCT_KIND = {
    "lag": "thermal_lag",
    "gradient": "gradient",
    "rate": "rate",
    "rate2": "rate_squared",
    "trate": "temp_rate_cross",
    "warmup": "warmup",
    "drift": "time_drift",
    "gsens": "g_sensitivity",
}


@dataclass
class Run:
    t: np.ndarray
    gyro: dict
    temps: dict
    period: float
    freq: dict = field(default_factory=dict)
    orientation: np.ndarray | None = None
    power: np.ndarray | None = None
    chamber_pv: np.ndarray | None = None
    chamber_sp: np.ndarray | None = None
    hidden: dict = field(default_factory=dict)   # truth-only signals (supply voltage, noise)
    noise: dict = field(default_factory=dict)


@dataclass
class Case:
    cls: str
    seed: int
    model: str            # CLI --model string
    declared: str         # static | dynamic | cubic | cubic_rate
    probes: dict          # channel -> own probe
    partner: dict         # dynamic's gradient partner per channel (or {})
    latitude: float
    gyro_type: str
    train: Run
    validate: Run
    truth: dict           # ch -> dict(effects=[...], unrecorded=bool, verdicts=[...])
    coef: dict


def _rng(cls, seed):
    return np.random.default_rng([zlib.crc32(cls.encode()), seed, 9])


# ---------------------------------------------------------------------------------------------
# declared model columns (from the recorded data only)

def declared_cols(case, run, ch):
    tc = P.fill_nan(run.t, run.temps[case.probes[ch]])
    if case.declared in ("static",):
        d = tc - 25.0
        return [d, d ** 2, d ** 3]
    if case.declared == "cubic":
        return [tc, tc ** 2, tc ** 3]
    if case.declared == "cubic_rate":
        return [tc, tc ** 2, tc ** 3, P.centred_slope(run.t, run.temps[case.probes[ch]], 120.0)]
    if case.declared == "dynamic":
        tp = P.fill_nan(run.t, run.temps[case.partner[ch]])
        return [tc - 25.0, tc - tp, P.centred_slope(run.t, run.temps[case.probes[ch]], 120.0)]
    raise ValueError(case.declared)


def declared_inputs(case, run, ch):
    tc = run.temps[case.probes[ch]]
    out = [tc]
    if case.declared in ("cubic_rate", "dynamic"):
        out.append(P.centred_slope(run.t, tc, 120.0))
    if case.declared == "dynamic":
        out.append(run.temps[case.partner[ch]])
    return out


def in_range_blocks(case, ch):
    """VALIDATE 100-s blocks whose declared inputs lie inside their TRAIN ranges (every sample)."""
    tr, va = case.train, case.validate
    ids = P.block_ids(va.t)
    nb = ids.max() + 1
    ok = np.ones(nb, bool)
    for xtr, xva in zip(declared_inputs(case, tr, ch), declared_inputs(case, va, ch)):
        lo, hi = np.nanmin(xtr), np.nanmax(xtr)
        bad = np.isfinite(xva) & ((xva < lo) | (xva > hi))
        ok &= np.bincount(ids[bad], minlength=nb) == 0
    return ok


def _per_sample(run, of_code):
    """(n, 3) array of ``of_code(orientation code)`` per sample (``NUE`` throughout without an
    orientation column), computed once per distinct code."""
    if run.orientation is None:
        return np.tile(of_code("NUE"), (len(run.t), 1))
    codes, inv = np.unique(run.orientation, return_inverse=True)
    return np.array([of_code(c) for c in codes])[inv]


def earth(case, run):
    """Earth rate per channel (deg/h), per sample."""
    tab = _per_sample(run, lambda code: P.earth_rate_body(code, case.latitude))
    return {c: tab[:, i] for i, c in enumerate(CHANNELS)}


def gravity(run):
    """Specific force (g) along body x, y, z, per sample."""
    return _per_sample(run, P.gravity_body)


def time_on(run):
    """Seconds since the last power-on (NaN while off)."""
    if run.power is None:
        return run.t - run.t[0]
    on = run.power > 0.5
    out = np.full(len(run.t), np.nan)
    start = None
    for i in range(len(run.t)):
        if on[i]:
            if start is None:
                start = run.t[i]
            out[i] = run.t[i] - start
        else:
            start = None
    return out


def effect_col(case, run, eff, window_s=120.0):
    """The true effect's regressor in its true form, from the recorded columns."""
    k, pr = eff["kind"], eff["params"]
    if k == "lag":
        return P.lag_irregular(run.t, run.temps[eff["probes"][0]], pr["tau_s"])
    if k == "gradient":
        a, b = eff["probes"]
        return P.fill_nan(run.t, run.temps[a]) - P.fill_nan(run.t, run.temps[b])
    if k in ("rate", "rate2", "trate"):
        p = eff["probes"][0]
        r = P.centred_slope(run.t, run.temps[p], window_s)
        if k == "rate":
            return r
        if k == "rate2":
            return r * r
        return (P.fill_nan(run.t, run.temps[p]) - pr["t0_c"]) * r
    if k == "warmup":
        return np.exp(-time_on(run) / pr["tau_s"])
    if k == "drift":
        return (run.t - run.t[0]) / 3600.0
    if k == "gsens":
        return gravity(run)[:, pr["axis"]]
    if k == "supply":
        return run.hidden["supply_v"]
    raise ValueError(k)


# ---------------------------------------------------------------------------------------------
# programs

def slow_train(rng, hours_max=9.0):
    """0.5 C/min ramps with long soaks (seed papers' style), heat and cool."""
    lo = rng.uniform(-10, 0)
    hi = rng.uniform(42, 55)
    mid = rng.uniform(15, 28)
    r = 0.5
    seg = [(lo, r, rng.uniform(55, 75) * 60), (mid, r, rng.uniform(30, 45) * 60), (hi, r, rng.uniform(55, 75) * 60),
           (rng.uniform(20, 30), r, rng.uniform(40, 60) * 60)]
    return rng.uniform(22, 28), seg, (lo, hi)


def fast_validate(rng, lo, hi, cold=0.0, hours=6.0, slow=False):
    r = rng.uniform(0.35, 0.48) if slow else rng.uniform(1.0, 1.5)
    a = lo + rng.uniform(2, 5) if not cold else lo - cold
    b = hi - rng.uniform(2, 6)
    soak_a = rng.uniform(25, 40) * 60 if not cold else rng.uniform(60, 75) * 60
    seg = [(b, r, rng.uniform(25, 40) * 60), (a, r, soak_a),
           (rng.uniform(lo + 8, hi - 8), r, rng.uniform(20, 30) * 60),
           (b - rng.uniform(0, 5), r, rng.uniform(20, 30) * 60), (rng.uniform(20, 30), r, 40 * 60)]
    return rng.uniform(20, 30), seg


def trim(sp, hours):
    n = int(hours * 3600)
    if len(sp) >= n:
        return sp[:n]
    return np.r_[sp, np.full(n - len(sp), sp[-1])]


# ---------------------------------------------------------------------------------------------
# unit, runs

def unit_params(rng):
    return dict(air=rng.uniform(90, 200), base=rng.uniform(1800, 3600), case=rng.uniform(700, 1400),
                mount=rng.uniform(1200, 2400), elem=list(rng.uniform(150, 500, 3)),
                elem_off=list(rng.uniform(-0.3, 0.3, 3)), ripple=rng.uniform(0.02, 0.08),
                ripple_p=rng.uniform(240, 420))


def noise_params(rng, flick_strong=False):
    white = rng.uniform(0.04, 0.12)
    fl = rng.uniform(0.015, 0.03) if flick_strong else rng.uniform(0.002, 0.006)
    return dict(white=white, flick=fl, rrw=rng.uniform(0.0005, 0.002))


def simulate(rng, sp, par, noise, probes, struct, *, orient=None, power=None, hidden=None):
    """Return (Run on the 1-s grid, true node temperatures dict by probe name, noise per channel)."""
    n = len(sp)
    t = np.arange(n, dtype=float)
    net = P.network(sp, rng, par)
    true = {}
    for i, c in enumerate(CHANNELS):
        true[probes[c]] = net["e"][i]
    true[struct[0]] = net["base"]
    if len(struct) > 1:
        true[struct[1]] = net["mount"]
    temps = {}
    for name, x in true.items():
        temps[name] = P.fine_probe(rng, x) if name in probes.values() else P.ds18b20(x + rng.normal(0, 0.02, n))
    nz = {c: P.gyro_noise(rng, n, 1.0, noise["white"], noise["flick"], noise["rrw"]) for c in CHANNELS}
    run = Run(t=t, gyro={}, temps=temps, period=1.0, orientation=orient, power=power,
              chamber_pv=np.round(net["air"] + rng.normal(0, 0.02, n), 3), chamber_sp=np.round(sp, 3),
              hidden=dict(hidden or {}), noise=nz)
    return run, true


def true_rate(x):
    return np.gradient(x) * 60.0


def true_effect(eff, true, run, case_t0=0.0):
    k, pr = eff["kind"], eff["params"]
    if k == "lag":
        return P.lag(true[eff["probes"][0]], pr["tau_s"])
    if k == "gradient":
        a, b = eff["probes"]
        return true[a] - true[b]
    if k == "rate":
        return true_rate(true[eff["probes"][0]])
    if k == "rate2":
        return true_rate(true[eff["probes"][0]]) ** 2
    if k == "trate":
        p = eff["probes"][0]
        return (true[p] - pr["t0_c"]) * true_rate(true[p])
    if k == "warmup":
        return np.nan_to_num(np.exp(-time_on(run) / pr["tau_s"]))
    if k == "drift":
        return (run.t + case_t0) / 3600.0
    if k == "gsens":
        return gravity(run)[:, pr["axis"]]
    if k == "supply":
        return run.hidden["supply_v"] - 28.0
    raise ValueError(k)


def supply_voltage(rng, n):
    """A drifting bench supply: slow wander (random sines, 40 min - 4 h) plus a linear drift."""
    t = np.arange(n, dtype=float)
    v = 28.0 + rng.uniform(-0.3, 0.3) * t / n
    for _ in range(4):
        per = rng.uniform(2400, 14400)
        v = v + rng.uniform(0.05, 0.2) * np.sin(2 * np.pi * t / per + rng.uniform(0, 2 * np.pi))
    return v + rng.normal(0, 0.002, n)


def average_run(run, k, rng, jitter=0.0):
    """k-sample block averages (a logger reporting k-s means), timestamps at the block centres."""
    n = (len(run.t) // k) * k
    f = lambda x: np.nanmean(np.asarray(x[:n], float).reshape(-1, k), axis=1)
    t = f(run.t)
    if jitter:
        t = t + rng.uniform(-jitter, jitter, len(t))
    nr = Run(t=t, gyro={c: f(v) for c, v in run.gyro.items()}, temps={}, period=float(k),
             chamber_pv=np.round(f(run.chamber_pv), 3), chamber_sp=np.round(f(run.chamber_sp), 3),
             hidden={a: f(b) for a, b in run.hidden.items()}, noise={c: f(v) for c, v in run.noise.items()})
    for name, x in run.temps.items():
        nr.temps[name] = np.round(f(x), 4)
    return nr


def blank_cells(rng, run, frac):
    for name, x in run.temps.items():
        m = rng.random(len(x)) < frac
        m[0] = m[-1] = False
        x = x.copy()
        x[m] = np.nan
        run.temps[name] = x


# ---------------------------------------------------------------------------------------------

def build(cls, seed):
    rng = _rng(cls, seed)
    # probe names: own probes t1..t3 assigned to channels at random, structure probes t4 (base) t5 (mount)
    own = [str(p) for p in rng.permutation(["t1", "t2", "t3"])]
    probes = dict(zip(CHANNELS, own))
    struct = ["t4", "t5"]
    par = unit_params(rng)
    lat = float(rng.uniform(30, 62))
    gyro_type = "MEMS"
    noise = noise_params(rng, flick_strong=(cls == "dynamic_complete_flicker"))
    declared, model, partner = "static", "static", {}
    truth = {c: dict(effects=[], unrecorded=False, verdicts=["no_effect_missing"]) for c in CHANNELS}
    chans = [str(c) for c in rng.permutation(CHANNELS)]
    a_ch, b_ch = chans[0], chans[1]
    T0unit = rng.uniform(15, 35)
    orient_tr = orient_va = None
    power_tr = power_va = None
    avg_val = 1
    jitter = 0.0
    blank = 0.0

    t0, seg, (lo, hi) = slow_train(rng)
    sp_tr = trim(P.program(seg, t0), 9.0)
    cold = 0.0
    val_hours = 6.0
    if cls == "static_lag_cold":
        cold = rng.uniform(5, 15)
        truth[a_ch]["effects"] = [dict(kind="lag", probes=["t4"], params=dict(tau_s=float(rng.uniform(300, 3600))))]
    elif cls == "dynamic_complete_flicker":
        declared, model = "dynamic", "dynamic"
    elif cls == "hrg_freq_gradient":
        declared, model, gyro_type = "cubic", "tc + tc^2 + tc^3", "HRG"
        truth[a_ch]["effects"] = [dict(kind="gradient", probes=["t4", "t5"], params={})]
    elif cls == "multipos_gsens":
        truth[a_ch]["effects"] = [dict(kind="gsens", probes=[], params=dict(axis=int(rng.integers(0, 3))))]
        truth[b_ch]["effects"] = [dict(kind="rate", probes=[str(rng.choice(struct))], params={})]
    elif cls == "irregular_logging":
        declared, model = "cubic", "tc + tc^2 + tc^3"
        avg_val, jitter, blank = 5, 0.3, 0.003
        truth[a_ch]["effects"] = [dict(kind="trate", probes=[probes[a_ch]], params=dict(t0_c=float(T0unit)))]
        truth[b_ch]["effects"] = [dict(kind="rate2", probes=[probes[b_ch]], params={})]
    elif cls == "warmup_power_drift":
        declared, model = "cubic_rate", "tc + tc^2 + tc^3 + dtc"
        truth[a_ch]["effects"] = [dict(kind="warmup", probes=[], params=dict(tau_s=float(rng.uniform(600, 2400))))]
        truth[b_ch]["effects"] = [dict(kind="drift", probes=[], params={})]
    elif cls == "short_validation":
        val_hours = 1.5
        truth[a_ch]["effects"] = [dict(kind="lag", probes=["t5"], params=dict(tau_s=float(rng.uniform(300, 1200))))]
        truth[b_ch]["effects"] = [dict(kind="gradient", probes=[probes[b_ch], "t4"], params={})]
    elif cls == "unrecorded_supply":
        truth[a_ch]["effects"] = [dict(kind="supply", probes=[], params={})]
        truth[a_ch]["unrecorded"] = True
        truth[a_ch]["verdicts"] = ["unexplained_structure_remains"]
    else:
        raise ValueError(cls)
    for c in CHANNELS:
        if truth[c]["effects"] and not truth[c]["unrecorded"]:
            truth[c]["verdicts"] = ["explained"]

    if cls == "short_validation":
        r = rng.uniform(1.2, 1.5)
        a = lo + rng.uniform(4, 8)
        b = hi - rng.uniform(4, 8)
        v0 = rng.uniform(20, 30)
        sp_va = trim(P.program([(b, r, 15 * 60), (a, r, 10 * 60), (rng.uniform(15, 30), r, 600)], v0), val_hours)
    elif cls == "multipos_gsens":
        sp_tr, orient_tr = multipos_program(rng, [lo + 3, rng.uniform(12, 22), rng.uniform(32, 40), hi - 3], 9.0)
        sp_va, orient_va = multipos_program(rng, [rng.uniform(lo + 5, 10), rng.uniform(20, 30), hi - 6], 6.0,
                                            ramp=rng.uniform(0.8, 1.2))
    else:
        v0, segv = fast_validate(rng, lo, hi, cold, slow=declared in ("dynamic", "cubic_rate"))
        sp_va = trim(P.program(segv, v0), val_hours)

    if cls == "warmup_power_drift":
        power_tr = power_profile(rng, len(sp_tr))
        power_va = power_profile(rng, len(sp_va))

    hid_tr = hid_va = None
    if cls == "unrecorded_supply":
        hid_tr = dict(supply_v=supply_voltage(rng, len(sp_tr)))
        hid_va = dict(supply_v=supply_voltage(rng, len(sp_va)))
    tr, true_tr = simulate(rng, sp_tr, par, noise, probes, struct, orient=orient_tr, power=power_tr, hidden=hid_tr)
    va, true_va = simulate(rng, sp_va, par, noise, probes, struct, orient=orient_va, power=power_va, hidden=hid_va)

    if declared == "dynamic":
        # the named model's gradient partner, as `bench fit dynamic` reports it for this probe set
        partner = dynamic_partner(probes)

    # declared (true) part of the bias
    coef = {}
    for c in CHANNELS:
        if declared == "dynamic":
            k1, p1, q1 = rng.uniform(0.2, 1.0) * rng.choice([-1, 1]), rng.uniform(0.3, 1.5) * rng.choice([-1, 1]), \
                rng.uniform(2, 8) * rng.choice([-1, 1])
            coef[c] = dict(b0=rng.uniform(-5, 5), k=k1, p=p1, q=q1)
        else:
            coef[c] = dict(b0=rng.uniform(-5, 5), k1=rng.uniform(0.2, 1.2) * rng.choice([-1, 1]),
                           k2=rng.uniform(0.003, 0.012) * rng.choice([-1, 1]),
                           k3=rng.uniform(5e-5, 2.5e-4) * rng.choice([-1, 1]))
            if declared == "cubic_rate":
                coef[c]["q"] = rng.uniform(1, 5) * rng.choice([-1, 1])

    def base_bias(c, true):
        T = true[probes[c]]
        cf = coef[c]
        if declared == "dynamic":
            return cf["b0"] + cf["k"] * (T - 25) + cf["p"] * (T - true[partner[c]]) + cf["q"] * true_rate(T)
        d = T - 25.0
        b = cf["b0"] + cf["k1"] * d + cf["k2"] * d ** 2 + cf["k3"] * d ** 3
        if "q" in cf:
            b = b + cf["q"] * true_rate(T)
        return b

    case = Case(cls=cls, seed=seed, model=model, declared=declared, probes=probes, partner=partner, latitude=lat,
                gyro_type=gyro_type, train=tr, validate=va, truth=truth, coef=coef)
    drift_t0 = len(sp_tr) + rng.uniform(1800, 7200)    # validation starts some time after training
    for run, true in ((tr, true_tr), (va, true_va)):
        for c in CHANNELS:
            run.gyro[c] = base_bias(c, true)
        run._true = true
    # effects: sized against the noise floor in what the declared model cannot absorb
    for c in CHANNELS:
        for eff in truth[c]["effects"]:
            e_tr = true_effect(eff, true_tr, tr, 0.0)
            e_va = true_effect(eff, true_va, va, drift_t0)
            s = size_effect(rng, case, c, e_tr, e_va, eff)
            eff["scale_dph"] = s
            eff["true_tr"], eff["true_va"] = s * e_tr, s * e_va
            tr.gyro[c] = tr.gyro[c] + s * e_tr
            va.gyro[c] = va.gyro[c] + s * e_va
    # Earth rate, noise, power-off gaps, HRG frequencies
    for run, true in ((tr, true_tr), (va, true_va)):
        er = earth(case, run)
        for c in CHANNELS:
            g = run.gyro[c] + er[c] + run.noise[c]
            if run.power is not None:
                g = np.where(run.power > 0.5, g, np.nan)
            run.gyro[c] = g
        if gyro_type == "HRG":
            for i, c in enumerate(CHANNELS):
                f0 = 5000.0 + 700.0 * i + rng.uniform(-50, 50)
                alpha = rng.uniform(-3.5e-5, -2.5e-5)
                run.freq[c] = f0 * (1 + alpha * (true[probes[c]] - 25.0)) + rng.normal(0, 0.002, len(run.t))
        del run._true
    # logging irregularities
    if jitter:
        tr.t = tr.t + rng.uniform(-jitter, jitter, len(tr.t))
        tr.t[0] = 0.0
    if avg_val > 1:
        case.validate = va = average_run(va, avg_val, rng, jitter=0.5)
    if blank:
        blank_cells(rng, tr, blank)
        blank_cells(rng, va, blank)
    return case


def dynamic_partner(probes):
    """The named `dynamic` model's gradient partner per channel, as `bench fit dynamic` reports it:
    t1, or t2 for the channel whose own probe is t1."""
    return {c: "t2" if probes[c] == "t1" else "t1" for c in CHANNELS}


def size_effect(rng, case, c, e_tr, e_va, eff):
    """Scale so that the part the declared model cannot absorb is 4-10x the noise floor (std of 100-s
    means of the noise) on TRAIN and on the in-range part of VALIDATE."""
    tr, va = case.train, case.validate
    target = rng.uniform(5.0, 8.0)
    res = []
    for run, e, blocks in ((tr, e_tr, None), (va, e_va, in_range_blocks(case, c))):
        cols = declared_cols(case, run, c)
        valid = np.isfinite(e) & (np.ones(len(e), bool) if run.power is None else run.power > 0.5)
        beta = P.lstsq_blocks(run.t, e, cols, valid)
        r = np.where(valid, e - P.predict(beta, cols, len(e)), np.nan)
        s_eff = P.std100(run.t, r, blocks)
        s_noise = P.std100(run.t, np.where(valid, run.noise[c], np.nan), blocks)
        res.append((s_eff, s_noise))
    (etr, ntr), (eva, nva) = res
    s = target * ntr / etr
    if eff["kind"] != "supply":      # a library effect: also 4-10x the noise on in-range VALIDATE
        if np.isfinite(eva) and eva * s < 4.0 * nva:
            s = 4.0 * nva / eva
        if etr * s > 12.0 * ntr and np.isfinite(eva) and eva * s > 4.0 * nva:
            s = max(10.0 * ntr / etr, 4.0 * nva / eva)
    return float(s * rng.choice([-1, 1]))


def power_profile(rng, n):
    p = np.ones(n)
    off0 = int(rng.uniform(600, 1200))
    p[:off0] = 0
    a = int(n * rng.uniform(0.4, 0.6))
    p[a:a + int(rng.uniform(1200, 2400))] = 0
    return p


def multipos_program(rng, temps, hours, ramp=0.5):
    """Soaks at the given temperatures; during each soak the unit visits six positions (each body
    axis up and down), 12-15 min each; ramps in the home position."""
    codes = P.right_handed_codes()
    sp, orient = [], []
    cur = rng.uniform(20, 28)
    home = "NUE"
    for T in temps:
        nr = int(abs(T - cur) / (ramp / 60.0))
        sp.extend(np.linspace(cur, T, nr + 1)[1:])
        orient.extend([home] * nr)
        settle = int(rng.uniform(25, 35) * 60)
        sp.extend([T] * settle)
        orient.extend([home] * settle)
        pos = []
        for ax in range(3):
            for s in "UD":
                cand = [k for k in codes if k[ax] == s]
                pos.append(str(rng.choice(cand)))
        rng.shuffle(pos)
        for code in pos:
            m = int(rng.uniform(12, 15) * 60)
            sp.extend([T] * m)
            orient.extend([code] * m)
        cur = T
    sp = np.array(sp)
    orient = np.array(orient, dtype=object)
    n = int(hours * 3600)
    if len(sp) > n:
        sp, orient = sp[:n], orient[:n]
    else:
        sp = np.r_[sp, np.full(n - len(sp), sp[-1])]
        orient = np.r_[orient, np.array([home] * (n - len(orient)), dtype=object)]
    return sp, orient


# ---------------------------------------------------------------------------------------------
# CSV v1 writer (own code)

def _fmt(x, nd):
    return np.where(np.isfinite(x), np.char.mod(f"%.{nd}f", np.nan_to_num(x)), "")


def write_run(case, run, path, which):
    cols, names = [], []
    names.append("time_s")
    cols.append(np.char.mod("%.3f", run.t))
    for c in CHANNELS:
        names.append(f"gyro_{c}")
        cols.append(_fmt(run.gyro[c], 5))
    for c in CHANNELS:
        if c in run.freq:
            names.append(f"freq_{c}")
            cols.append(_fmt(run.freq[c], 5))
    for name in sorted(run.temps):
        names.append(f"temp_{name}")
        cols.append(_fmt(run.temps[name], 4))
    if run.orientation is not None:
        names.append("orientation")
        cols.append(np.asarray(run.orientation, dtype=str))
    if run.power is not None:
        names.append("power")
        cols.append(np.char.mod("%d", run.power.astype(int)))
    if run.chamber_pv is not None:
        names.append("chamber_pv")
        cols.append(_fmt(run.chamber_pv, 3))
        names.append("chamber_sp")
        cols.append(_fmt(run.chamber_sp, 3))
    cp = ",".join(f"{c}={case.probes[c]}" for c in CHANNELS)
    head = [f"# gyro_id: R9-{case.cls}-{case.seed}", f"# gyro_type: {case.gyro_type}",
            f"# latitude_deg: {case.latitude:.4f}", f"# sample_period_s: {run.period:g}",
            f"# channel_probes: {cp}", f"# referee9 {which} run"]
    body = cols[0]
    for col in cols[1:]:
        body = np.char.add(np.char.add(body, ","), col)
    with open(path, "w") as fh:
        fh.write("\n".join(head) + "\n" + ",".join(names) + "\n")
        fh.write("\n".join(body.tolist()) + "\n")
