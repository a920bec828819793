"""Score ``bench close-loop`` on the third referee's cases, through the CLI and its JSON only.

    python -m tests.referee3.score --seeds 5 [--first-seed 1] [--classes A,B] [--json out.json] [--verbose]

Per channel a case passes when
* kinds: every missing effect is named by an added effect of the same kind on the same probe(s)
  (a gradient's pair in either order) and nothing else is added; nothing added when nothing is
  missing; for a driver no column records, anything may be added but the verdict must say so;
* verdict: nothing missing -> ``no_effect_missing``; library effect -> ``explained`` (``partly_explained``
  also accepted when even the oracle stays above 1.2 of the product's noise floor); unrecorded driver ->
  ``unexplained_structure_remains``;
* error: ``after`` validation std of 100-s means <= 1.15 x the oracle's (declared terms + the true
  effects in their true form, least squares on TRAIN, in-range VALIDATE) for library effects and
  complete channels, and never above ``before``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from tests.referee3.cases import CLASSES, Case, Run, _poly_design, block_std, build_case, format_csv
from tests.referee3.effects import Effect, column, rate_c_per_min

RATIO_MAX = 1.15
# the referee's kinds -> the kind names close-the-loop uses for them in effects_added[].kind
PRODUCT_KINDS = {
    "lag": {"thermal_lag"},
    "gradient": {"gradient"},
    "rate": {"rate"},
    "rate_squared": {"rate_squared"},
    "temp_rate": {"temp_rate_cross"},
    "relay": {"hysteresis"},    # params.form "reversal"
    "play": {"hysteresis"},     # params.form "gradual"
    "warmup": {"warmup"},
    "time_drift": {"time_drift"},
}


@dataclass
class ChannelScore:
    channel: str
    truth: list[str]
    added: list[str]
    verdict: str
    before: float
    after: float
    oracle: float
    my_before: float
    floor: float
    ratio: float
    failures: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    added_raw: list[dict] = field(default_factory=list)    # effects_added[]: kind, params, terms

    @property
    def passed(self) -> bool:
        return not self.failures


@dataclass
class CaseScore:
    cls: str
    seed: int
    channels: list[ChannelScore]
    seconds: float
    error: str | None = None

    @property
    def passed(self) -> bool:
        return self.error is None and all(c.passed for c in self.channels)


def run_close_loop(case: Case, workdir: str) -> dict:
    tr, va, out = (os.path.join(workdir, n) for n in ("train.csv", "validate.csv", "cl.json"))
    with open(tr, "w") as f:
        f.write(format_csv(case.train))
    with open(va, "w") as f:
        f.write(format_csv(case.validate))
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    proc = subprocess.run([sys.executable, "-m", "bench.cli", "close-loop", tr, va, "--model", case.model,
                           "--json", out], capture_output=True, text=True, timeout=900, env=env, cwd=workdir)
    if proc.returncode != 0:
        raise RuntimeError(f"close-loop exited {proc.returncode}: {proc.stderr.strip()[-400:]}")
    with open(out) as f:
        return json.load(f)


# ------------------------------------------------------------------------------ oracle

def _recorded_temps(run: Run) -> dict[str, np.ndarray]:
    return {k[5:]: v for k, v in run.columns.items() if k.startswith("temp_")}


def _design(run: Run, own: str, terms: list[Effect]) -> np.ndarray:
    temps = _recorded_temps(run)
    cols = [_poly_design(temps[own])]
    cols += [column(e, temps, run.columns["time_s"], run.columns["power"], run.hidden, run.period_s)[:, None]
             for e in terms]
    return np.hstack(cols)


def in_range_mask(case: Case, ch: str) -> np.ndarray:
    """VALIDATE samples whose declared inputs (tc, and dtc when declared) lie in their TRAIN range."""
    own = case.truth[ch].probe
    tr_t, va_t = _recorded_temps(case.train)[own], _recorded_temps(case.validate)[own]
    ok = (va_t >= tr_t.min()) & (va_t <= tr_t.max())
    if case.truth[ch].declared_extra:
        r_tr, r_va = rate_c_per_min(tr_t, case.train.period_s), rate_c_per_min(va_t, case.validate.period_s)
        ok &= (r_va >= r_tr.min()) & (r_va <= r_tr.max())
    return ok


def validation_std100(case: Case, ch: str, terms: list[Effect]) -> float:
    """Declared terms + ``terms`` fitted by least squares on TRAIN, std of 100-s means on in-range VALIDATE."""
    truth = case.truth[ch]
    terms = truth.declared_extra + terms
    y_tr, y_va = case.train.columns[f"gyro_{ch}"], case.validate.columns[f"gyro_{ch}"]
    x_tr, x_va = _design(case.train, truth.probe, terms), _design(case.validate, truth.probe, terms)
    m = np.isfinite(y_tr)
    beta = np.linalg.lstsq(x_tr[m], y_tr[m], rcond=None)[0]
    return block_std(y_va - x_va @ beta, case.validate.columns["time_s"], in_range_mask(case, ch))


# ------------------------------------------------------------------------------ judging

def _probes_of(params: dict) -> set[str]:
    out: set[str] = set()
    for v in params.values():
        vals = v if isinstance(v, (list, tuple)) else [v]
        for x in vals:
            if isinstance(x, str):
                for part in x.replace("-", ",").replace("(", ",").replace(")", ",").split(","):
                    if part.strip().startswith("t") and part.strip()[1:].isdigit():
                        out.add(part.strip())
    return out


HYSTERESIS_FORMS = {"relay": "reversal", "play": "gradual"}


def _matches(e: Effect, added: dict) -> bool:
    if added.get("kind") not in PRODUCT_KINDS.get(e.kind, set()):
        return False
    if e.kind in HYSTERESIS_FORMS and (added.get("params") or {}).get("form") != HYSTERESIS_FORMS[e.kind]:
        return False
    return _probes_of(added.get("params") or {}) == set(e.probes)


def product_effect_columns(a: dict, run: Run) -> list[np.ndarray] | None:
    """The referee's reading of an added effect (kind + params of effects_added) as regressor columns
    on ``run``'s recorded data, or None for a kind it cannot read.  Used only to accept a look-alike."""
    kind, p = a.get("kind"), a.get("params") or {}
    temps, t, dt = _recorded_temps(run), run.columns["time_s"], run.period_s
    power = run.columns["power"]
    probe = p.get("probe")
    try:
        if kind == "thermal_lag":
            lag = column(Effect("lag", (probe,), {"tau_s": float(p["tau_s"])}), temps, t, power, {}, dt)
            if p.get("form") == "polynomial":
                return [(lag - 25) ** k for k in (1, 2, 3)]
            if p.get("form") == "absolute":
                return [lag]
            return [lag - temps[probe]]
        if kind == "gradient":
            a_, b_ = str(p["probes"]).split("-")
            return [temps[a_] - temps[b_]]
        if kind in ("rate", "rate_squared", "temp_rate_cross"):
            r = rate_c_per_min(temps[probe], dt, float(p.get("window_s", 120.0)))
            return [r if kind == "rate" else r ** 2 if kind == "rate_squared" else (temps[probe] - 20) * r]
        if kind == "hysteresis":
            k = "play" if p.get("form") == "gradual" else "relay"
            return [column(Effect(k, (probe,), {"width_c": float(p["width_c"])}), temps, t, power, {}, dt)]
        if kind == "warmup":
            return [column(Effect("warmup", (), {"tau_s": float(p["tau_s"])}), temps, t, power, {}, dt)]
        if kind == "time_drift":
            return [t / 3600.0]
    except (KeyError, ValueError):
        return None
    return None


def look_alike(case: Case, ch: str, e: Effect, kept: list[Effect], added: list[dict], floor: float) -> bool:
    """True when the added effects (the referee's reading of them) together with the declared terms and
    the other true effects reproduce the true effect ``e`` within half a noise floor (std of 100-s
    means, TRAIN and in-range VALIDATE, coefficients from TRAIN): a look-alike the data cannot tell apart."""
    truth = case.truth[ch]
    cols = {}
    for name, run in (("train", case.train), ("validate", case.validate)):
        extra = [product_effect_columns(a, run) for a in added]
        if any(x is None for x in extra) or not extra:
            return False
        x = np.hstack([_design(run, truth.probe, truth.declared_extra + kept)]
                      + [np.column_stack(c) for c in extra])
        u = e.coef * column(e, _recorded_temps(run), run.columns["time_s"], run.columns["power"], run.hidden,
                            run.period_s)
        cols[name] = (x, u)
    (x_tr, u_tr), (x_va, u_va) = cols["train"], cols["validate"]
    m = np.isfinite(case.train.columns[f"gyro_{ch}"])
    beta = np.linalg.lstsq(x_tr[m], u_tr[m], rcond=None)[0]
    r_tr = block_std(u_tr - x_tr @ beta, case.train.columns["time_s"], m)
    r_va = block_std(u_va - x_va @ beta, case.validate.columns["time_s"], in_range_mask(case, ch))
    return bool(max(r_tr, r_va) < 0.5 * floor)


def judge_channel(case: Case, ch: str, rep: dict) -> ChannelScore:
    truth = case.truth[ch]
    added = rep.get("effects_added") or []
    verdict = rep.get("verdict", "?")
    before = float(rep["before"]["validation_std100_dph"])
    after = float(rep["after"]["validation_std100_dph"])
    floor = float(rep.get("noise_floor_dph") or np.nan)
    oracle = validation_std100(case, ch, truth.effects)
    my_before = validation_std100(case, ch, [])
    ratio = after / oracle if oracle > 0 else float("inf")
    fails: list[str] = []
    notes: list[str] = []
    names = [f"{a.get('kind')}({','.join(sorted(_probes_of(a.get('params') or {})))})" for a in added]
    if not truth.effects:
        if added:
            fails.append(f"kinds: added {names} where nothing is missing")
        if verdict != "no_effect_missing":
            fails.append(f"verdict: {verdict} where nothing is missing")
    elif truth.unrecorded:
        if verdict != "unexplained_structure_remains":
            fails.append(f"verdict: {verdict} for a driver no column records")
    else:
        unmatched = [e for e in truth.effects if not any(_matches(e, a) for a in added)]
        extra = [(a, n) for a, n in zip(added, names) if not any(_matches(e, a) for e in truth.effects)]
        kept = [e for e in truth.effects if e not in unmatched]
        alike = [e for e in unmatched if extra and look_alike(case, ch, e, kept, [a for a, _ in extra], floor)]
        # an extra term on the probe of a matched effect that, with it, reproduces that effect (a
        # temp*rate cross about another reference temperature needs a rate term beside it)
        reexpressed = (not unmatched and extra
                        and all(_probes_of(a.get("params") or {}) <= {p for e in kept for p in e.probes}
                                for a, _ in extra)
                        and all(look_alike(case, ch, e, [k for k in kept if k is not e], added, floor)
                                for e in kept))
        if alike and len(alike) == len(unmatched):
            notes.append(f"look-alike: {[n for _, n in extra]} for {[e.describe() for e in alike]}")
        elif reexpressed:
            notes.append(f"re-expression: {[n for _, n in extra]} beside the matched effects")
        elif unmatched or extra:
            amb = any(_matches(e, c) for e in unmatched for a in added for c in (a.get("ambiguous_with") or []))
            fails.append(f"kinds: missed {[e.describe() for e in unmatched]}, added {[n for _, n in extra]}"
                         + (" (the missed one named in ambiguous_with)" if amb else ""))
        ok = {"explained"} | ({"partly_explained"} if oracle > 1.2 * floor else set())
        if verdict not in ok:
            fails.append(f"verdict: {verdict} (oracle/floor {oracle / floor:.2f})")
    if not truth.unrecorded and ratio > RATIO_MAX:
        fails.append(f"error: after {after:.4g} = {ratio:.2f}x the oracle {oracle:.4g}")
    if after > before * (1 + 1e-9):
        fails.append(f"error: after {after:.4g} worse than before {before:.4g}")
    return ChannelScore(ch, [e.describe() for e in truth.effects], names, verdict, before, after, oracle,
                        my_before, floor, ratio, fails, notes,
                        [{k: a.get(k) for k in ("kind", "params", "terms", "ambiguous_with")} for a in added])


def score_case(cls: str, seed: int) -> CaseScore:
    t0 = time.perf_counter()
    try:
        case = build_case(cls, seed)
        with tempfile.TemporaryDirectory(prefix="referee3-") as d:
            rep = run_close_loop(case, d)
        chans = [judge_channel(case, ch, rep["channels"][ch]) for ch in case.truth]
        return CaseScore(cls, seed, chans, time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - a case that cannot be scored is reported, not hidden
        return CaseScore(cls, seed, [], time.perf_counter() - t0, error=f"{type(exc).__name__}: {exc}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="", help="comma-separated class names (default: all)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or list(CLASSES)
    unknown = [c for c in classes if c not in CLASSES]
    if unknown:
        ap.error(f"unknown classes {unknown}; known: {', '.join(CLASSES)}")
    results: list[CaseScore] = []
    cpu0 = os.times()
    for cls in classes:
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            r = score_case(cls, seed)
            results.append(r)
            status = "pass" if r.passed else "FAIL"
            print(f"{cls:28s} seed {seed:3d} {status} {r.seconds:5.1f}s", file=sys.stderr)
            if a.verbose or not r.passed:
                if r.error:
                    print(f"    error: {r.error}", file=sys.stderr)
                for c in r.channels:
                    print(f"    {c.channel}: truth {c.truth} added {c.added} verdict {c.verdict} "
                          f"before {c.before:.4g} after {c.after:.4g} oracle {c.oracle:.4g} (my before "
                          f"{c.my_before:.4g}) floor {c.floor:.4g} ratio {c.ratio:.2f} {c.failures}{' ' + str(c.notes) if c.notes else ''}", file=sys.stderr)
    cpu1 = os.times()
    print(f"| class | passed | failures |\n|---|---|---|")
    total = 0
    for cls in classes:
        rs = [r for r in results if r.cls == cls]
        p = sum(r.passed for r in rs)
        total += p
        why: dict[str, int] = {}
        for r in rs:
            if r.error:
                why["error"] = why.get("error", 0) + 1
            for c in r.channels:
                for f in {f.split(":")[0] for f in c.failures}:
                    why[f] = why.get(f, 0) + 1
        print(f"| `{cls}` | {p}/{len(rs)} | {', '.join(f'{k} {v}' for k, v in sorted(why.items())) or '—'} |")
    print(f"| **all** | **{total}/{len(results)}** | |")
    cpu = (cpu1.children_user + cpu1.children_system + cpu1.user + cpu1.system
           - cpu0.children_user - cpu0.children_system - cpu0.user - cpu0.system)
    print(f"CPU {cpu:.1f} s for {len(results)} cases; load average {os.getloadavg()[0]:.2f}", file=sys.stderr)
    if a.json:
        with open(a.json, "w") as f:
            json.dump([{**{k: v for k, v in asdict(r).items() if k != "channels"}, "passed": r.passed,
                        "channels": [{**asdict(c), "passed": c.passed} for c in r.channels]} for r in results],
                      f, indent=1)
    return 0 if total == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
