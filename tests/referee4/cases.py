"""The case classes of the fourth referee and the builder of one case (train + validate + truth).

Every class states the declared model, which physical effects act on which channels (drawn per
seed) and how strong they are: the strength is the std of the effect's 100-s means on the training
run *after* the declared model has absorbed what it can (least squares on the block means), in
units of the noise's own std of 100-s means.  So "3x" means barely detectable whatever the form.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from tests.referee4.effects import T_REF_C, Signals, regressor
from tests.referee4.generator import (CHANNEL_PROBES, CHANNELS, PROBES, Logger, draw_hardware,
                                      draw_outages, format_csv, gyro_output, heater_node, log_run,
                                      simulate, smooth_random)
from tests.referee4.physics import NoiseSpec, flicker_noise
from tests.referee4.programs import draw_train, draw_validate_style, validate_program

POLY3 = "tc + tc^2 + tc^3"
DYNAMIC = "tc + tc^2 + tc^3 + dtc"
CROSS = "tc + tc^2 + dtc + tc*dtc"
GRADIENT = "tc + tc^2 + tc^3 + (tc-t4) + dtc"

# declared form -> the signals it reads (for the in-range rule) and its regressors
DECLARED_INPUTS = {POLY3: ("tc",), DYNAMIC: ("tc", "dtc"), CROSS: ("tc", "dtc"),
                   GRADIENT: ("tc", "t4", "dtc")}


def declared_regressors(form: str, sig: Signals, probe: str) -> np.ndarray:
    """Columns (no intercept) spanning the declared formula, centred at 25 C for conditioning."""
    d = sig.temp(probe) - T_REF_C
    r = sig.rate(probe)
    cols = {POLY3: [d, d ** 2, d ** 3], DYNAMIC: [d, d ** 2, d ** 3, r],
            CROSS: [d, d ** 2, r, d * r], GRADIENT: [d, d ** 2, d ** 3, sig.temp(probe) - sig.temp("t4"), r]}[form]
    return np.column_stack(cols)


def declared_inputs(form: str, sig: Signals, probe: str) -> dict[str, np.ndarray]:
    src = {"tc": sig.temp(probe), "dtc": sig.rate(probe), "t4": sig.temp("t4")}
    return {k: src[k] for k in DECLARED_INPUTS[form]}


# ------------------------------------------------------------------------------------------------
# effect drawers: (rng, own probe, declared form) -> (kind, params)

def _other(rng, own):
    return str(rng.choice([p for p in PROBES if p != own]))


def lag_other(rng, own, form):
    return "lag", {"probe": _other(rng, own), "tau_s": float(rng.uniform(600, 2400))}


def lag_own(rng, own, form):
    return "lag", {"probe": own, "tau_s": float(rng.uniform(1200, 3600))}


def gradient(rng, own, form):
    pairs = [pq for pq in itertools.combinations(PROBES, 2)
             if not (form == GRADIENT and set(pq) == {own, "t4"})]
    a, b = pairs[int(rng.integers(len(pairs)))]
    return "gradient", {"pair": [a, b]}


def rate(rng, own, form):
    probe = own if (form == POLY3 and rng.random() < 0.5) else _other(rng, own)
    return "rate", {"probe": probe}


def temp_rate(rng, own, form):
    return "temp_rate", {"probe": str(rng.choice(PROBES))}


def relay(rng, own, form):
    return "hysteresis_relay", {"probe": own, "threshold_c_per_min": float(rng.uniform(0.05, 0.3))}


def play(rng, own, form):
    return "hysteresis_play", {"probe": str(rng.choice([own, own, _other(rng, own)])),
                               "width_c": float(rng.uniform(1.5, 8.0))}


def reversal(rng, own, form):
    return "hysteresis_reversal", {"probe": own, "band_c": float(rng.uniform(0.5, 3.0))}


def warm(rng, own, form):
    return "warmup", {"tau_s": float(rng.uniform(300, 1800))}


def drift(rng, own, form):
    return "drift", {}


TWO_EFFECT_POOL = (lag_other, gradient, rate, temp_rate, play, warm, drift)


@dataclass
class CaseClass:
    name: str
    model: str
    effects: tuple[Callable, ...] = ()        # drawers; one per affected channel (two_effects: 2)
    n_effects: int = 1                        # effects per affected channel
    unrecorded: str | None = None
    magnitude: tuple[float, float] = (5.0, 20.0)
    power_cycle: bool | None = None           # None: drawn
    validate: str | None = None               # None: drawn
    flicker_scale: float = 1.0
    channels: tuple[int, int] = (1, 2)        # how many channels carry the effect (min, max)


CLASSES: dict[str, CaseClass] = {c.name: c for c in [
    CaseClass("complete_poly3", POLY3),
    CaseClass("complete_dynamic", DYNAMIC),
    CaseClass("complete_cross", CROSS, validate="steeper"),
    CaseClass("complete_gradient_flicker", GRADIENT, flicker_scale=2.5),
    CaseClass("lag_other_probe", DYNAMIC, effects=(lag_other,)),
    CaseClass("lag_own_probe", DYNAMIC, effects=(lag_own,)),
    CaseClass("gradient_pair", DYNAMIC, effects=(gradient,)),
    CaseClass("gradient_with_declared_gradient", GRADIENT, effects=(gradient,)),
    CaseClass("rate_probe", POLY3, effects=(rate,)),
    CaseClass("temp_rate_cross", DYNAMIC, effects=(temp_rate,)),
    CaseClass("hysteresis_relay_rate", DYNAMIC, effects=(relay,)),
    CaseClass("hysteresis_play", DYNAMIC, effects=(play,)),
    CaseClass("hysteresis_reversal", POLY3, effects=(reversal,)),
    CaseClass("warmup", DYNAMIC, effects=(warm,), power_cycle=True, channels=(3, 3)),
    CaseClass("time_drift", DYNAMIC, effects=(drift,)),
    CaseClass("weak_effect", DYNAMIC, effects=(lag_other, gradient, rate, temp_rate), magnitude=(3.0, 4.0)),
    CaseClass("two_effects", DYNAMIC, effects=TWO_EFFECT_POOL, n_effects=2, power_cycle=True,
              magnitude=(6.0, 20.0), channels=(1, 1)),
    CaseClass("unrecorded_humidity", DYNAMIC, unrecorded="humidity", channels=(2, 3)),
    CaseClass("unrecorded_heater", DYNAMIC, unrecorded="heater", channels=(1, 2)),
    CaseClass("unrecorded_bias_step", DYNAMIC, unrecorded="bias_step", channels=(1, 1)),
    CaseClass("unrecorded_hvac", POLY3, unrecorded="hvac", channels=(1, 3)),
]}


# ------------------------------------------------------------------------------------------------

def block_index(t: np.ndarray, t0: float, block_s: float = 100.0) -> np.ndarray:
    return np.floor((t - t0) / block_s).astype(np.int64)


def block_means(idx: np.ndarray, values: np.ndarray, min_count: int = 1):
    """Means per block of the rows where every column of ``values`` is finite: (blocks, means)."""
    v = values if values.ndim == 2 else values[:, None]
    ok = np.all(np.isfinite(v), axis=1)
    idx, v = idx[ok], v[ok]
    blocks, inv, counts = np.unique(idx, return_inverse=True, return_counts=True)
    sums = np.zeros((blocks.size, v.shape[1]))
    np.add.at(sums, inv, v)
    keep = counts >= min_count
    return blocks[keep], (sums / counts[:, None])[keep]


def residual_std100(t, y, design, powered, min_count) -> float:
    """Std of the 100-s means of y after least squares on [1, design] at the block-mean level."""
    idx = block_index(t[powered], t[0])
    _, m = block_means(idx, np.column_stack([y[powered], design[powered]]), min_count)
    x = np.column_stack([np.ones(len(m)), m[:, 1:]])
    coef, *_ = np.linalg.lstsq(x, m[:, 0], rcond=None)
    return float(np.std(m[:, 0] - x @ coef))


def noise_std100(spec: NoiseSpec, n: int, dt: float, rng) -> float:
    """Expected std of 100-s means of the white + flicker noise over a record of n samples."""
    m = int(round(100.0 / dt))
    k = n // m
    vals = []
    for _ in range(3):
        x = rng.normal(0.0, spec.white_sigma_dph(dt), k * m) + flicker_noise(k * m, dt, spec.bias_inst_dph, rng)
        vals.append(np.std(x.reshape(k, m).mean(axis=1)))
    return float(np.mean(vals))


@dataclass
class Case:
    cls: str
    seed: int
    model: str
    logger: str
    styles: dict[str, str]
    texts: dict[str, str]                       # "train"/"validate" -> CSV text
    columns: dict[str, dict[str, np.ndarray]]   # the logged columns (what the CSV holds)
    truth: dict[str, dict] = field(default_factory=dict)
    noise_std100_dph: float = 0.0


def case_rng(cls: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([4, sorted(CLASSES).index(cls), int(seed)])


def build_case(cls_name: str, seed: int) -> Case:
    spec = CLASSES[cls_name]
    rng = case_rng(cls_name, seed)
    hw = draw_hardware(rng, flicker_scale=spec.flicker_scale)
    power_cycle = spec.power_cycle if spec.power_cycle is not None else bool(rng.random() < 0.3)
    tstyle, tprog = draw_train(rng, power_cycle=power_cycle)
    vstyle = spec.validate or draw_validate_style(rng)
    vprog = validate_program(rng, vstyle, tprog)
    mode = str(rng.choice(["1s", "1s", "1s", "0.5s", "10s_avg", "10s_avg"]))
    loggers = {"train": Logger(mode, draw_outages(rng, tprog.end)),
               "validate": Logger(mode, draw_outages(rng, vprog.end))}
    runs = {k: simulate(hw, p, loggers[k].physics_dt, rng) for k, p in (("train", tprog), ("validate", vprog))}
    train = runs["train"]
    min_count = int(50 / train.dt)
    sigma100 = noise_std100(hw.noise, train.t.size, train.dt, rng)

    # which channels carry what
    n_ch = int(rng.integers(spec.channels[0], spec.channels[1] + 1))
    affected = set(rng.choice(CHANNELS, size=n_ch, replace=False).tolist()) if (spec.effects or spec.unrecorded) else set()
    truth: dict[str, dict] = {}
    signals = {k: {} for k in runs}
    for ch in CHANNELS:
        own = CHANNEL_PROBES[ch]
        d_train = declared_regressors(spec.model, train.sig, own)
        coefs = _declared_coefficients(rng, spec.model)
        for k, run in runs.items():
            decl = declared_regressors(spec.model, run.sig, own)
            signals[k][ch] = float(coefs[0]) + decl @ coefs[1:]
        entry = {"probe": own, "declared": spec.model, "effects": [], "unrecorded": None}
        if ch in affected and spec.effects:
            drawers = list(spec.effects)
            picks = rng.choice(len(drawers), size=spec.n_effects, replace=False)
            kinds_seen = set()
            for i in picks:
                kind, params = drawers[int(i)](rng, own, spec.model)
                if kind in kinds_seen:
                    continue
                kinds_seen.add(kind)
                mag = float(np.exp(rng.uniform(*np.log(spec.magnitude))))
                e_train = regressor(kind, params, train.sig)
                s_e = residual_std100(train.t, e_train, d_train, train.powered, min_count)
                coef = float(rng.choice([-1, 1])) * mag * sigma100 / s_e
                for k, run in runs.items():
                    e = e_train if k == "train" else regressor(kind, params, run.sig)
                    signals[k][ch] = signals[k][ch] + coef * e
                entry["effects"].append({"kind": kind, "params": params, "coef": coef, "magnitude": mag})
        if ch in affected and spec.unrecorded:
            mag = float(np.exp(rng.uniform(*np.log(spec.magnitude))))
            series = _unrecorded_series(spec.unrecorded, runs, rng)
            s_e = residual_std100(train.t, series["train"], d_train, train.powered, min_count)
            coef = float(rng.choice([-1, 1])) * mag * sigma100 / s_e
            for k in runs:
                signals[k][ch] = signals[k][ch] + coef * series[k]
            entry["unrecorded"] = {"kind": spec.unrecorded, "coef": coef, "magnitude": mag}
        truth[ch] = entry

    texts, columns = {}, {}
    for k, run in runs.items():
        gyro = {ch: gyro_output(run, signals[k][ch], hw.noise, rng) for ch in CHANNELS}
        cols = log_run(run, hw, gyro, loggers[k], rng)
        meta = {"gyro_id": f"REF4-{cls_name}-{seed}", "gyro_type": "RLG",
                "sample_period_s": f"{loggers[k].period_s:g}",
                "channel_probes": ",".join(f"{c}={p}" for c, p in CHANNEL_PROBES.items())}
        texts[k] = format_csv(cols, meta)
        columns[k] = cols
    return Case(cls=cls_name, seed=seed, model=spec.model, logger=mode,
                styles={"train": tstyle, "validate": vstyle}, texts=texts, columns=columns,
                truth=truth, noise_std100_dph=sigma100)


def _declared_coefficients(rng, form: str) -> np.ndarray:
    """Intercept and declared-term coefficients of an RLG/FOG-grade channel (deg/h per unit)."""
    b0 = rng.uniform(-2, 2)
    a1 = rng.uniform(-0.05, 0.05)
    a2 = rng.uniform(-5e-4, 5e-4)
    a3 = rng.uniform(-1e-5, 1e-5)
    q = rng.choice([-1, 1]) * rng.uniform(0.02, 0.1)         # per C/min
    r = rng.uniform(-2e-3, 2e-3)
    g = rng.choice([-1, 1]) * rng.uniform(0.02, 0.1)
    return np.array({POLY3: [b0, a1, a2, a3], DYNAMIC: [b0, a1, a2, a3, q], CROSS: [b0, a1, a2, q, r],
                     GRADIENT: [b0, a1, a2, a3, g, q]}[form])


def _unrecorded_series(kind: str, runs, rng) -> dict[str, np.ndarray]:
    """Unit-scale series of a driver that no column records, per run (same physics, new draw)."""
    out = {}
    period = rng.uniform(2400, 5400)
    tau = rng.uniform(1800, 5400)
    heater_scale = rng.uniform(0.7, 1.5)
    for k, run in runs.items():
        t = run.t
        if kind == "humidity":
            out[k] = smooth_random(t.size, run.dt, tau, rng)
        elif kind == "heater":
            out[k] = heater_node(run, rng, period_scale=heater_scale)
        elif kind == "bias_step":
            on = run.t[run.powered]
            ts = on[0] + rng.uniform(0.25, 0.75) * (on[-1] - on[0])
            out[k] = (t >= ts).astype(float) * (1.0 if k == "train" else rng.choice([-1, 1]) * rng.uniform(0.6, 1.4))
        elif kind == "hvac":
            out[k] = np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
        else:
            raise ValueError(kind)
    return out
