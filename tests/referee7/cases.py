"""Referee 7 cases: seeded TRAIN/VALIDATE pairs, one class of lab situation each.

Conventions:

* A case = one gyro unit (channels x, y, z; own probes x=t1, y=t2, z=t3; t4 on the mount) tested twice:
  TRAIN and VALIDATE runs with different chamber profile types and logger settings from the class.
* Per channel, ``truth`` lists the missing effects as ``(name, probe-or-None, param)``:
  ``lag`` (param tau_s), ``gradient`` (probe "ta-tb"), ``rate``, ``rate_squared``, ``cross`` (T*dT/dt),
  ``relay``/``gradual`` (hysteresis, param width C), ``warmup`` (param tau_s), ``drift``; unrecorded
  drivers ``humidity``, ``mode_hop``, ``sag``.  An empty list = complete channel.
* The declared part of the bias is b0 + k1*(T-20) + k2*(T-20)^2 (+ k3*(T-20)^3, + kd*dT/dt,
  + kg*(T-T4) when the formula has them) with T the TRUE own-probe node temperature.
* Each effect's coefficient is set so that its part not explained by the declared terms has a
  100-s-mean std of ``snr`` times the channel's expected noise floor on TRAIN.
* ``columns(run, name, probe, param)`` gives the true 1-s regressor; the oracle uses the same columns.
"""
from __future__ import annotations

import numpy as np

from . import physics as ph
from .logger import LogSpec, Rows, gyro_readings, probe_readings, timestamps

CHANNELS = ("x", "y", "z")
OWN = {"x": "t1", "y": "t2", "z": "t3"}
PROFILES = ("stair", "ramp", "sine", "random")

# class -> (model formula, {channel: [effects]}, train LogSpec, validate LogSpec, options)
L1 = LogSpec(period=1.0)
CLASSES = {
    "complete_plain": ("tc + tc^2", {}, L1, LogSpec(period=1.0, jitter_s=0.02), {}),
    "complete_logger": ("tc + tc^2 + tc^3", {},
                        LogSpec(period=0.5, epoch=True, jitter_s=0.02, gaps=1, p_missing=1e-3),
                        LogSpec(period=0.5, epoch=True, jitter_s=0.02, gaps=1, p_missing=1e-3),
                        {"power_col": True}),
    "complete_avg10": ("tc + tc^2 + dtc", {}, LogSpec(period=10, average=True, epoch=True),
                       LogSpec(period=10, average=True, epoch=True), {"val_range": "wider"}),
    "lag": ("tc + tc^2", {"x": [("lag", "t1", None)], "y": [("lag", "t4", None)]},
            LogSpec(period=1.0, epoch=True, jitter_s=0.02), LogSpec(period=2.0, epoch=True), {}),
    "gradient": ("tc + tc^2", {"x": [("gradient", "t1-t4", None)], "y": [("gradient", "t3-t4", None)]},
                 LogSpec(period=2.0), LogSpec(period=2.0, gaps=1), {}),
    "rate": ("tc + tc^2", {"x": [("rate", "t1", None)], "y": [("rate", "t4", None)]},
             LogSpec(period=1.0, jitter_s=0.03, p_missing=5e-4), LogSpec(period=1.0), {}),
    "rate_squared": ("tc + tc^2", {"x": [("rate_squared", "t1", None)],
                                   "y": [("rate_squared", "t3", None)]},
                     L1, LogSpec(period=1.0, epoch=True), {"steep": True}),
    "cross": ("tc + tc^2", {"x": [("cross", "t1", None)], "y": [("cross", "t4", None)]},
              LogSpec(period=2.0, epoch=True), LogSpec(period=1.0, epoch=True), {}),
    "hyst_relay": ("tc + tc^2", {"x": [("relay", "t1", None)], "y": [("relay", "t4", None)]},
                   L1, LogSpec(period=1.0, gaps=1), {}),
    "hyst_gradual": ("tc + tc^2", {"x": [("gradual", "t1", None)], "y": [("gradual", "t3", None)]},
                     L1, L1, {}),
    "warmup": ("tc + tc^2", {"x": [("warmup", None, None)], "z": [("warmup", None, None)]},
               LogSpec(period=1.0, epoch=True), LogSpec(period=1.0, epoch=True), {"power": True}),
    "drift": ("tc + tc^2", {"x": [("drift", None, None)], "z": [("drift", None, None)]},
              LogSpec(period=10, average=True), LogSpec(period=10, average=True), {}),
    "two_effects": ("tc + tc^2", {"x": [("lag", "t1", None), ("gradient", "t1-t4", None)],
                                  "y": [("rate", "t2", None), ("drift", None, None)],
                                  "z": [("relay", "t3", None), ("drift", None, None)]},
                    LogSpec(period=1.0, epoch=True, jitter_s=0.02), LogSpec(period=2.0), {}),
    "weak": ("tc + tc^2", {"x": [("lag", "t1", None)], "y": [("gradient", "t2-t4", None)]},
             L1, L1, {"snr": (2.0, 3.0)}),
    "humidity": ("tc + tc^2", {"x": [("humidity", None, None)], "z": [("humidity", None, None)]},
                 L1, LogSpec(period=1.0, epoch=True), {}),
    "mode_hop": ("tc + tc^2", {"x": [("mode_hop", "t1", None)], "z": [("mode_hop", "t4", None)]},
                 L1, L1, {}),
    "supply_sag": ("tc + tc^2", {"x": [("sag", None, None)], "y": [("sag", None, None)]},
                   LogSpec(period=2.0, epoch=True), LogSpec(period=2.0, epoch=True), {}),
}
UNRECORDED = {"humidity", "mode_hop", "sag"}


def _draw_params(name, rng):
    if name == "lag":
        return float(np.exp(rng.uniform(np.log(300), np.log(3000))))
    if name == "relay":
        return float(rng.uniform(0.5, 1.5))
    if name == "gradual":
        return float(rng.uniform(1.5, 4.0))
    if name == "warmup":
        return float(rng.uniform(400, 1500))
    return None


def _draw_lag(run, formula, ch, probe, rng, tries=8):
    """A lag tau in 300-3000 s that no other probe's lag or gradient mimics (noise-free correlation of
    the parts left by the declared terms < 0.99 on TRAIN); the last draw if none qualifies."""
    sl = slice(None, None, 10)
    D = np.column_stack([np.ones(run["n"])] + declared_columns(formula, run, OWN[ch]))[sl]
    res = lambda c: (lambda r: r / np.linalg.norm(r))(c[sl] - D @ np.linalg.lstsq(D, c[sl], rcond=None)[0])
    alts = [res(run["T"][a] - run["T"][b]) for a in ph.PROBES for b in ph.PROBES if a < b]
    for p in ph.PROBES:
        if p != probe:
            alts += [res(ph.first_order_lag(run["T"][p], tau)) for tau in np.geomspace(150, 8000, 12)]
    for _ in range(tries):
        tau = float(np.exp(rng.uniform(np.log(300), np.log(3000))))
        r = res(ph.first_order_lag(run["T"][probe], tau))
        if max(abs(float(a @ r)) for a in alts) < 0.99:
            break
    return tau


def column(run: dict, name: str, probe, param, rng=None) -> np.ndarray:
    """True 1-s regressor of one effect on one run."""
    T = run["T"]
    if name == "lag":
        return ph.first_order_lag(T[probe], param)
    if name == "lag_rel":                  # the lagged minus the present temperature of one probe
        return ph.first_order_lag(T[probe], param) - T[probe]
    if name == "gradient":
        a, b = probe.split("-")
        return T[a] - T[b]
    if name == "rate":
        return run["rate"][probe]
    if name == "rate_squared":
        return run["rate"][probe] ** 2
    if name == "cross":
        return T[probe] * run["rate"][probe]
    if name == "relay":
        return ph.relay_state(T[probe], param)
    if name == "gradual":
        return ph.gradual_state(T[probe], param)
    if name == "warmup":
        return np.exp(-run["since_on"] / param)
    if name == "drift":
        return np.arange(run["n"]) / 3600.0
    if name == "humidity":
        return run["rh"]
    if name == "mode_hop":
        return run["mode"][probe]
    if name == "sag":
        return run["sag"]
    raise ValueError(name)


def declared_columns(formula: str, run: dict, own: str) -> list[np.ndarray]:
    """True 1-s columns of the declared terms (constant excluded)."""
    T, cols = run["T"][own] - 20.0, []
    for term in [s.strip() for s in formula.split("+")]:
        if term == "tc":
            cols.append(T)
        elif term.startswith("tc^"):
            cols.append(T ** int(term[3:]))
        elif term == "dtc":
            cols.append(run["rate"][own])
        elif term == "(tc-t4)":
            cols.append(run["T"][own] - run["T"]["t4"])
        else:
            raise ValueError(term)
    return cols


def _ranges(rng, opts):
    lo, hi = rng.uniform(-15, 0), rng.uniform(35, 55)
    mode = opts.get("val_range") or rng.choice(["same", "inside", "wider"])
    if mode == "wider":
        vlo, vhi = lo - rng.uniform(3, 8), hi + rng.uniform(3, 8)
    elif mode == "inside":
        vlo, vhi = lo + rng.uniform(2, 8), hi - rng.uniform(2, 8)
    else:
        vlo, vhi = lo + rng.uniform(-2, 2), hi + rng.uniform(-2, 2)
    return (lo, hi), (vlo, vhi)


def _simulate_run(unit, kind, n, trange, rng, power_cycles: int | None) -> dict:
    sp = ph.setpoint_profile(kind, n, trange[0], trange[1], rng)
    air = ph.chamber_air(sp, rng)
    power, since_on = None, np.arange(n, dtype=float)
    if power_cycles is not None:
        power = np.ones(n)
        for _ in range(power_cycles):
            s = int(rng.uniform(0.2, 0.8) * n)
            power[s:s + int(rng.uniform(1800, 3600))] = 0.0
        since_on = np.zeros(n)
        for k in range(1, n):
            since_on[k] = since_on[k - 1] + 1 if (power[k] and power[k - 1]) else 0.0
    net = ph.simulate_network(air, unit["g"], power)
    T = {p: net["T"][ph.NODE_OF_PROBE[p]] for p in ph.PROBES}
    rate = {p: net["dT"][ph.NODE_OF_PROBE[p]] * 60.0 for p in ph.PROBES}
    run = {"n": n, "kind": kind, "T": T, "rate": rate, "air": air, "power": power,
           "since_on": since_on, "rh": ph.humidity(air, rng), "sag": ph.supply_sag(n, rng),
           "mode": {p: ph.schmitt_mode(T[p], *unit["hop"][p], rng) for p in ("t1", "t4")}}
    return run


def _std100_of(x: np.ndarray) -> float:
    m = x[: len(x) // 100 * 100].reshape(-1, 100).mean(axis=1)
    return float(np.std(m, ddof=1))


def build_case(cls: str, seed: int) -> dict:
    formula, effects, spec_tr, spec_va, opts = CLASSES[cls]
    rng = np.random.default_rng([seed, sum(map(ord, cls)) * 7919 + len(cls)])
    unit = {"g": ph.draw_unit_thermal(rng), "noise": {ch: ph.draw_noise(rng) for ch in CHANNELS},
            "offset": {p: rng.normal(0, 0.15) for p in ph.PROBES}}
    (tlo, thi), (vlo, vhi) = _ranges(rng, opts)
    mid = 0.5 * (tlo + thi)
    unit["hop"] = {p: (mid + rng.uniform(3, 8), mid - rng.uniform(1, 5)) for p in ("t1", "t4")}
    kinds = rng.choice(PROFILES, 2, replace=False)
    if opts.get("steep"):
        kinds = np.array(["ramp", "random"])
    n_tr = int(rng.uniform(8, 12) * 3600)
    n_va = int(rng.uniform(5, 8) * 3600)
    pc = (2, 1) if opts.get("power") else (None, None)
    runs = {"train": _simulate_run(unit, kinds[0], n_tr, (tlo, thi), rng, pc[0]),
            "validate": _simulate_run(unit, kinds[1], n_va, (vlo, vhi), rng, pc[1])}
    snr_lo, snr_hi = opts.get("snr", (4.0, 7.0))

    # truth per channel: declared coefficients + effects with params and scaled coefficients
    truth = {}
    for ch in CHANNELS:
        n_decl = len(declared_columns(formula, runs["train"], OWN[ch]))
        k = [rng.uniform(-1.5, 1.5), rng.uniform(-0.02, 0.02), rng.uniform(-3e-4, 3e-4)][:n_decl]
        if "dtc" in formula:
            k[-1] = rng.uniform(-2, 2)
        eff = [(nm, pr, _draw_lag(runs["train"], formula, ch, pr, rng) if nm == "lag"
                else _draw_params(nm, rng)) for nm, pr, _ in effects.get(ch, [])]
        truth[ch] = {"b0": rng.uniform(-20, 20), "k": k, "effects": eff, "coef": []}
        noise = unit["noise"][ch]
        floor = np.hypot(6 * noise["arw"], 1.2 * noise["bias_inst"])
        run = runs["train"]
        D = np.column_stack([np.ones(run["n"])] + declared_columns(formula, run, OWN[ch]))
        ok = run["power"] == 1 if run["power"] is not None else np.ones(run["n"], bool)
        for nm, pr, par in eff:
            c = column(run, nm, pr, par)
            beta = np.linalg.lstsq(D[ok], c[ok], rcond=None)[0]
            r = np.where(ok, c - D @ beta, 0.0)
            s = _std100_of(r)
            truth[ch]["coef"].append(rng.choice([-1, 1]) * rng.uniform(snr_lo, snr_hi) * floor / s)
        truth[ch]["floor_guess"] = floor

    # logging
    case = {"class": cls, "seed": seed, "formula": formula, "truth": truth, "runs": {},
            "kinds": list(map(str, kinds)), "ranges": ((tlo, thi), (vlo, vhi))}
    for name, spec in (("train", spec_tr), ("validate", spec_va)):
        run = runs[name]
        rows = Rows(run["n"], spec, rng)
        cols = {"time_s": timestamps(rows, spec, rng)}
        gyro_truth, noise_rows = {}, {}
        for ch in CHANNELS:
            b = bias_1s(case, run, ch)
            nz = unit["noise"][ch]
            slow = ph.gyro_noise(run["n"], dict(nz, arw=0.0), rng)
            g = gyro_readings(b, slow, nz["arw"], nz["count"], rows, rng)
            pw = rows.at(run["power"]) if run["power"] is not None else None
            if pw is not None:
                g[pw < 0.999] = np.nan
            cols[f"gyro_{ch}"] = g
            gyro_truth[ch] = rows.at(b)
        for p in ph.PROBES:
            cols[f"temp_{p}"] = probe_readings(run["T"][p], unit["offset"][p], rows, spec, rng)
        if run["power"] is not None:
            cols["power"] = (rows.at(run["power"]) > 0.999).astype(float)
        elif opts.get("power_col"):
            cols["power"] = np.ones(len(rows.t))
        meta = {"gyro_id": f"R7-{cls}-{seed}", "channel_probes": "x=t1,y=t2,z=t3",
                "sample_period_s": f"{spec.period:g}"}
        case["runs"][name] = {"run": run, "rows": rows, "cols": cols, "meta": meta,
                              "gyro_truth": gyro_truth}
    return case


def bias_1s(case: dict, run: dict, ch: str) -> np.ndarray:
    tr = case["truth"][ch]
    b = np.full(run["n"], tr["b0"])
    for k, c in zip(tr["k"], declared_columns(case["formula"], run, OWN[ch])):
        b = b + k * c
    for (nm, pr, par), coef in zip(tr["effects"], tr["coef"]):
        b = b + coef * column(run, nm, pr, par)
    return b
