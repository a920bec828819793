"""The case classes of the referee corpus: ``make_case(class_name, seed) -> Case``.

Every case is a unit (three channels, probes t1..t4 on a coupled thermal network, DS18B20 probes),
a TRAIN run and a VALIDATE run, and a truth record per channel under test: the declared model (a
formula in the product's formula language), the true missing effects (kind, probes), the verdicts
an honest analysis may give, and the oracle regressors (see ``tests.corpus.effects``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import zlib

import numpy as np

from bench.fit.base import Dataset
from tests.corpus import effects as fx
from tests.corpus.generator import (ChannelSpec, Recording, RunPlan, declared_probes, formula_text, make_run,
                                    Unit, random_unit)

EXPLAINED = frozenset({"explained"})
COMPLETE = frozenset({"no_effect_missing"})
UNEXPLAINED = frozenset({"unexplained_structure_remains", "partly_explained"})
TRAIN_S = 10 * 3600.0
VALIDATE_S = 8 * 3600.0
MIN_VISIBILITY = 0.3
MAX_DRAWS = 20
POSITIONS = ("NUE", "ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")


@dataclass
class ChannelTruth:
    channel: str
    formula: str
    declared: list[tuple]
    effects: list[fx.Effect]
    verdicts: frozenset[str]
    coefficients: list[float]                # deg/h per unit of each effect's signal (physical size)
    visibility: list[float]                  # share of each effect the declared model and the other
                                             # effects cannot absorb (std of 100-s means, TRAIN)
    distinctness: list[float]                # error left (noise floors) when the best other library
                                             # regressor replaces the effect
    lookalikes: list[list]                   # per effect: (kind, probes) that imitate it within half
                                             # a noise floor; the referee accepts them as the effect

    @property
    def declared_probes(self) -> list[str]:
        return declared_probes(self.declared)

    def describe(self) -> dict:
        return {"channel": self.channel, "declared_model": self.formula,
                "effects": [{**e.describe(), "coefficient": c, "visibility": v, "distinctness": d,
                             "lookalikes": [[k, list(p)] for k, p in look]}
                            for e, c, v, d, look in zip(self.effects, self.coefficients, self.visibility,
                                                        self.distinctness, self.lookalikes)],
                "verdicts": sorted(self.verdicts)}


@dataclass
class Case:
    case_class: str
    seed: int
    train: Dataset
    validate: Dataset
    truth: dict[str, ChannelTruth]
    hidden_train: dict[str, np.ndarray]
    hidden_validate: dict[str, np.ndarray]
    floors: dict[str, float]
    probe_nodes: dict[str, str]              # where each probe is glued (coil_x/y/z, base or case)
    full: dict[str, tuple[Dataset, Recording]]   # per run: the 1-s data and how the logger recorded it
    # the TRAIN and VALIDATE runs as the logger delivered them to the product, when that differs from
    # what it recorded (readings it wrote without checking them); the referee judges on the recorded runs
    delivered: tuple[Dataset, Dataset] | None = None

    @property
    def product_runs(self) -> tuple[Dataset, Dataset]:
        """The TRAIN and VALIDATE runs the product is given."""
        return self.delivered if self.delivered is not None else (self.train, self.validate)

    def oracle_columns(self, channel: str, which: str) -> np.ndarray:
        """The true effects of ``channel`` as regressor columns on the TRAIN or VALIDATE data, from what
        the logger recorded: its probe readings interpolated onto the physics' 1-s grid (straight
        through an outage: what happened there is not recorded) and its power readings held, the
        effect computed there and recorded
        as the gyro is (averaged over each logger period, outages left out)."""
        hidden = self.hidden_train if which == "train" else self.hidden_validate
        full, rec = self.full[which]
        recorded = self.train if which == "train" else self.validate
        ds = full
        if not rec.identity:
            cols = {p: np.interp(full.time, recorded.time, np.asarray(recorded[p], dtype=float))
                    for p in full.columns if p.startswith("temp_")}
            # the power switch as recorded: each reading holds until the next one
            last = np.clip(np.searchsorted(recorded.time, full.time, side="right") - 1, 0, len(recorded) - 1)
            cols["power"] = np.asarray(recorded["power"], dtype=float)[last]
            ds = full.with_columns(**cols)
        cols = [e.oracle(ds, hidden, channel) for e in self.truth[channel].effects]
        if not cols:
            return np.zeros((rec.n_rows, 0))
        return rec.mean(np.column_stack(cols))


# ------------------------------------------------------------------------------------------ plans

def _train_plan(rng, **kw) -> RunPlan:
    base = dict(duration_s=TRAIN_S, tmin_c=float(rng.uniform(-25, -10)), tmax_c=float(rng.uniform(40, 55)),
                rate_range=(0.5, 2.0))
    base.update(kw)
    return RunPlan(**base)


def _validate_plan(train: RunPlan, rng, **kw) -> RunPlan:
    base = dict(duration_s=VALIDATE_S, tmin_c=train.tmin_c + float(rng.uniform(0, 5)),
                tmax_c=train.tmax_c - float(rng.uniform(0, 5)), rate_range=(0.5, 2.0),
                power_cycles=train.power_cycles, positions=train.positions,
                table_rates_dps=train.table_rates_dps, humidity=train.humidity, board_load=train.board_load,
                record_period_s=train.record_period_s, outages=train.outages, bias_step=train.bias_step)
    base.update(kw)
    return RunPlan(**base)


def _cubic(probe: str) -> list[tuple]:
    return [("pow", probe, k) for k in (1, 2, 3)]


def _declared(rng, unit: Unit, channel: str) -> list[tuple]:
    """The channel's own probe, cubic; half the time with a declared gradient to the structure probe."""
    own = unit.channel_probes[channel]
    d = _cubic(own)
    if rng.random() < 0.5:
        d.append(("diff", own, unit.structure_probe))
    return d


def _others(unit: Unit, channel: str) -> list[str]:
    return [p for p in ("t1", "t2", "t3", "t4") if p != unit.channel_probes[channel]]


# ------------------------------------------------------------------------------------------ effects

def _library_effect(kind: str, rng, unit: Unit, channel: str) -> fx.Effect:
    """One library effect on a probe other than the channel's own (where the kind has a probe)."""
    others = _others(unit, channel)
    p = str(rng.choice(others))
    if kind == "thermal_lag":
        # at least ~20 min: a shorter lag is a rate (lag - T = -tau dT/dt) to any analysis
        return fx.ThermalLag(p, float(np.exp(rng.uniform(np.log(1200), np.log(5400)))))
    if kind == "gradient":
        a, b = rng.choice(others, 2, replace=False)
        return fx.Gradient(str(a), str(b))
    if kind == "rate":
        return fx.Rate(p)
    if kind == "rate_squared":
        return fx.RateSquared(p)
    if kind == "temp_rate_cross":
        return fx.TempRateCross(p)
    if kind == "hysteresis":
        return fx.Hysteresis(p, float(rng.uniform(0.3, 1.0)))
    if kind == "warmup":
        return fx.Warmup(float(rng.uniform(300, 1800)))
    if kind == "g_sensitivity":
        return fx.GSensitivity(rng.uniform(-1, 1, 3))
    if kind == "scale_factor_temperature":
        return fx.ScaleFactorTemperature(unit.channel_probes[channel])   # the coil's own temperature
    if kind == "time_drift":
        return fx.TimeDrift()
    raise ValueError(f"unknown effect kind {kind!r}")


def _plan_needs(kinds: list[str]) -> dict:
    kw: dict = {}
    if "warmup" in kinds:
        kw["power_cycles"] = True
    if "g_sensitivity" in kinds:
        kw["positions"] = POSITIONS[1:]
    if "scale_factor_temperature" in kinds:
        kw["table_rates_dps"] = (-10.0, -5.0, -2.0, 0.0, 2.0, 5.0, 10.0)
    return kw


# ------------------------------------------------------------------------------------------ builder

def _build(case_class: str, seed: int, rng, unit: Unit, specs: list[ChannelSpec], train_plan: RunPlan,
           validate_plan: RunPlan) -> Case:
    lat = float(rng.uniform(-60, 60))
    meta = {"gyro_id": f"CORPUS-{case_class}-{seed}", "gyro_type": "FOG"}
    train, st_tr, floors, full_tr, rec_tr = make_run(train_plan, unit, specs, rng, lat, 0, meta)
    validate, st_va, _, full_va, rec_va = make_run(validate_plan, unit, specs, rng, lat, 1, meta)
    truth = {s.channel: ChannelTruth(s.channel, formula_text(s.declared), s.declared,
                                     [e for e, _ in s.effects], s.verdicts,
                                     [unit.effect_coef[(s.channel, i)] for i in range(len(s.effects))],
                                     [unit.effect_visibility[(s.channel, i)] for i in range(len(s.effects))],
                                     [unit.effect_distinctness[(s.channel, i)] for i in range(len(s.effects))],
                                     [unit.effect_lookalikes[(s.channel, i)] for i in range(len(s.effects))])
             for s in specs}
    return Case(case_class, seed, train, validate, truth, st_tr.hidden, st_va.hidden,
                {s.channel: floors[s.channel] for s in specs}, dict(unit.probe_nodes),
                {"train": (full_tr, rec_tr), "validate": (full_va, rec_va)})


def _single(case_class: str, seed: int, kinds: list[str] | Callable, *, channel: str | None = None,
            ratio=(5.0, 10.0), train_kw=None, validate_kw=None, verdicts=EXPLAINED,
            effect_factory: Callable | None = None, unit_noise=None,
            min_visibility: float = MIN_VISIBILITY) -> Case:
    """A case with one channel under test.  Effects the declared model and the other true effects
    would mostly absorb (visibility < MIN_VISIBILITY) cannot be named by anyone: such a draw is
    replaced by the next one of the same seed (``kinds`` may be drawn too: a callable of the rng)."""
    rng = np.random.default_rng([zlib.crc32(case_class.encode()), seed])
    for _ in range(MAX_DRAWS):
        unit = random_unit(rng, unit_noise)
        ch = channel or str(rng.choice(["x", "y", "z"]))
        if effect_factory is not None:
            effs = effect_factory(rng, unit, ch)
        else:
            effs = []
            used_probes: set[str] = set()
            for k in (kinds(rng) if callable(kinds) else kinds):
                for _ in range(20):
                    e = _library_effect(k, rng, unit, ch)
                    if not (set(e.probes) & used_probes) or not e.probes:
                        break
                used_probes |= set(e.probes)
                effs.append(e)
        needs = _plan_needs([e.kind for e in effs])
        tp = _train_plan(rng, **{**needs, **(train_kw or {})})
        vp = _validate_plan(tp, rng, **(validate_kw or {}))
        spec = ChannelSpec(ch, _declared(rng, unit, ch), [(e, float(rng.uniform(*ratio))) for e in effs], verdicts)
        case = _build(case_class, seed, rng, unit, [spec], tp, vp)
        t = case.truth[ch]
        if all(v >= min_visibility for v in t.visibility):
            return case
    raise RuntimeError(f"{case_class} seed {seed}: no draw with visible effects in {MAX_DRAWS} tries")


def _with_glitches(case: Case) -> Case:
    """The case as a logger that does not check its readings delivers it: in every gyro column of both
    runs a few frames corrupted past their checksum (30-300x the column's sample-to-sample noise; one of
    them three frames long), in every probe column one to three readings of a DS18B20's power-on
    85.0 C, its 127.94 C bus error or a -127 C disconnect."""
    rng = np.random.default_rng([zlib.crc32(b"glitches"), case.seed])

    def deliver(ds: Dataset) -> Dataset:
        cols = {}
        for name in ds.columns:
            x = np.array(ds[name], dtype=float)
            ok = np.flatnonzero(np.isfinite(x))[30:-30]
            if name.startswith("gyro_"):
                noise = float(np.nanstd(np.diff(x))) / np.sqrt(2.0)
                at = np.sort(rng.choice(ok, 4, replace=False))
                at = np.concatenate([at, at[-1] + np.arange(1, 3)])     # the last one three frames long
                x[at] += rng.choice([-1.0, 1.0], len(at)) * rng.uniform(30.0, 300.0, len(at)) * noise
            elif name.startswith("temp_"):
                at = rng.choice(ok, int(rng.integers(1, 4)), replace=False)
                x[at] = rng.choice([85.0, 127.94, -127.0], len(at))
            else:
                continue
            cols[name] = x
        return ds.with_columns(**cols)

    return replace(case, delivered=(deliver(case.train), deliver(case.validate)))


LIBRARY_KINDS = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "hysteresis", "warmup",
                 "g_sensitivity", "scale_factor_temperature", "time_drift")
PAIRABLE = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "hysteresis", "warmup",
            "time_drift")


PROBE_KINDS = ("thermal_lag", "gradient", "rate", "rate_squared", "temp_rate_cross", "hysteresis")


def _one_of(kinds: tuple[str, ...], salt: int) -> Callable:
    """A class's effect kind drawn per seed (the same seed, the same kind)."""
    return lambda s: [str(np.random.default_rng([salt, s]).choice(kinds))]


def _mode_hop(rng, unit, ch):
    probe = unit.channel_probes[ch]
    return [fx.ModeHop(probe, float(rng.uniform(0, 30)), float(rng.uniform(0.5, 2.0)))]


CLASSES: dict[str, Callable[[int], Case]] = {
    # complete declared model; validation leaves the training range -> nothing is missing
    "complete_validation_colder": lambda s: _single(
        "complete_validation_colder", s, [], verdicts=COMPLETE,
        train_kw=dict(tmin_c=-15.0 - 10 * (s % 3) / 2), validate_kw=dict(tmin_c=-38.0)),
    "complete_validation_hotter": lambda s: _single(
        "complete_validation_hotter", s, [], verdicts=COMPLETE,
        train_kw=dict(tmax_c=40.0 + 2 * (s % 3)), validate_kw=dict(tmax_c=60.0)),
    "complete_validation_steeper": lambda s: _single(
        "complete_validation_steeper", s, [], verdicts=COMPLETE,
        train_kw=dict(rate_range=(0.5, 1.0)), validate_kw=dict(rate_range=(2.5, 3.0), soak_range_s=(1200, 2400))),
    # complete models under coloured noise and short validation runs: nothing may be added
    "complete_strong_flicker": lambda s: _single(
        "complete_strong_flicker", s, [], verdicts=COMPLETE,
        unit_noise={"arw": (0.002, 0.004), "bi": (0.02, 0.04), "rrw": (0.001, 0.003)}),
    "complete_short_validation": lambda s: _single(
        "complete_short_validation", s, [], verdicts=COMPLETE,
        validate_kw=dict(duration_s=float(np.random.default_rng(s).uniform(5400, 9000)),
                         soak_range_s=(900, 1800))),
    # one library effect on a probe other than the channel's own (t1 for x)
    **{f"effect_off_own_probe_{k}": (lambda k: lambda s: _single(f"effect_off_own_probe_{k}", s, [k]))(k)
       for k in LIBRARY_KINDS},
    # a real effect while the validation run leaves the training range (diagnosis on the in-range part)
    "effect_validation_colder": lambda s: _single(
        "effect_validation_colder", s, [str(np.random.default_rng([5, s]).choice(PAIRABLE))],
        train_kw=dict(tmin_c=-15.0), validate_kw=dict(tmin_c=-38.0)),
    # bias instability / 1/f noise with a real effect
    "effect_with_flicker": lambda s: _single(
        "effect_with_flicker", s, [str(np.random.default_rng(s).choice(PAIRABLE))],
        unit_noise={"arw": (0.002, 0.004), "bi": (0.01, 0.025)}),
    # a sensor whose output filter is slower than its 1-s samples (correlated samples): a complete model
    # and two effects
    "complete_band_limited": lambda s: _single(
        "complete_band_limited", s, [], verdicts=COMPLETE, unit_noise={"filter_s": (2.0, 8.0)}),
    "band_limited_two_effects": lambda s: _single(
        "band_limited_two_effects", s, lambda rng: [str(k) for k in rng.choice(PAIRABLE, 2, replace=False)],
        ratio=(4.0, 8.0), unit_noise={"filter_s": (2.0, 8.0)}),
    "two_effects": lambda s: _single(
        "two_effects", s, lambda rng: [str(k) for k in rng.choice(PAIRABLE, 2, replace=False)],
        ratio=(4.0, 8.0)),
    "three_effects": lambda s: _single(
        "three_effects", s, lambda rng: [str(k) for k in rng.choice(PAIRABLE, 3, replace=False)],
        ratio=(4.0, 8.0)),
    "gradual_hysteresis": lambda s: _single(
        "gradual_hysteresis", s, [],
        effect_factory=lambda rng, unit, ch: [fx.Hysteresis(str(rng.choice(["t1", "t2", "t3", "t4"])),
                                                      float(rng.uniform(3.0, 12.0)))]),
    "long_time_constant": lambda s: _single(
        "long_time_constant", s, [],
        effect_factory=lambda rng, unit, ch: [fx.ThermalLag(unit.channel_probes[ch],
                                                            float(rng.uniform(0.3, 0.8)) * TRAIN_S)],
        min_visibility=0.15),   # a lag this slow is partly a function of T: less of it is visible
    # effects from variables no column records: must come out unexplained
    "unrecorded_humidity": lambda s: _single(
        "unrecorded_humidity", s, [], verdicts=UNEXPLAINED, train_kw=dict(humidity=True),
        effect_factory=lambda rng, unit, ch: [fx.Humidity()]),
    "unrecorded_internal_node": lambda s: _single(
        "unrecorded_internal_node", s, [], verdicts=UNEXPLAINED, train_kw=dict(board_load=True),
        effect_factory=lambda rng, unit, ch: [fx.InternalNode()]),
    "unrecorded_mode_hop": lambda s: _single(
        "unrecorded_mode_hop", s, [], verdicts=UNEXPLAINED, effect_factory=_mode_hop),
    # the logger at another rate: one row every 10 s, the gyro averaged over it
    "effect_sampled_10s": lambda s: _single(
        "effect_sampled_10s", s, _one_of(PAIRABLE, 11)(s), train_kw=dict(record_period_s=10.0)),
    # logger outages (rows missing, 5-40 min each) in both runs
    "effect_with_logger_gaps": lambda s: _single(
        "effect_with_logger_gaps", s, _one_of(PAIRABLE, 12)(s), train_kw=dict(outages=True)),
    # a validation run far shorter than the training run (1.5-2.5 h against 10 h), with a real effect
    "effect_short_validation": lambda s: _single(
        "effect_short_validation", s, _one_of(PAIRABLE, 13)(s),
        validate_kw=dict(duration_s=float(np.random.default_rng([13, s]).uniform(5400, 9000)),
                         soak_range_s=(900, 1800))),
    # two effects, each through its own probe (neither the channel's own)
    "two_probe_effects": lambda s: _single(
        "two_probe_effects", s, lambda rng: [str(k) for k in rng.choice(PROBE_KINDS, 2, replace=False)],
        ratio=(4.0, 8.0)),
    # a real effect, and a logger that writes corrupted gyro frames and probe failure readings unchecked
    "effect_with_glitches": lambda s: _with_glitches(_single("effect_with_glitches", s, _one_of(PAIRABLE, 14)(s))),
    # a bias step at a random time of each run, not driven by temperature: must come out unexplained
    "unrecorded_bias_step": lambda s: _single(
        "unrecorded_bias_step", s, [], verdicts=UNEXPLAINED, train_kw=dict(bias_step=True),
        effect_factory=lambda rng, unit, ch: [fx.BiasStep()]),
}


def write_case(case: Case, directory) -> dict:
    """Write the case as measured-data CSV v1 files (train.csv, validate.csv) and its truth
    (truth.json) into ``directory``; returns the truth record."""
    import json
    from pathlib import Path

    from bench.fit.csvio import write_csv

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    train, validate = case.product_runs
    write_csv(train, d / "train.csv")
    write_csv(validate, d / "validate.csv")
    record = {"case_class": case.case_class, "seed": case.seed,
              "channels": {ch: t.describe() for ch, t in case.truth.items()}, "probe_nodes": case.probe_nodes,
              "noise_floor_dph": case.floors}
    (d / "truth.json").write_text(json.dumps(record, indent=1), encoding="utf-8")
    return record


def make_case(case_class: str, seed: int) -> Case:
    try:
        factory = CLASSES[case_class]
    except KeyError:
        raise KeyError(f"unknown case class {case_class!r} (have: {', '.join(sorted(CLASSES))})") from None
    return factory(seed)
