"""Referee 7 scorer: run ``bench close-loop`` on generated cases and judge each channel.

Usage::

    python -m tests.referee7.score --seeds 3 --first-seed 1 [--classes a,b] [--verbose] [--keep DIR]

Rules (per channel):

* complete (the declared model is the truth): nothing added and verdict ``no_effect_missing``;
* library effect(s) missing: every true (kind, probe) named and nothing else; verdict ``explained``
  (``partly_explained`` accepted only when our oracle stays above 1.2x the reported noise floor);
  ``after <= 1.15 * oracle`` and ``after <= before``;
* unrecorded driver: verdict ``unexplained_structure_remains`` and ``after <= before``.

Product kinds: lag->thermal_lag, gradient->gradient (probe pair, either order), rate->rate,
rate_squared->rate_squared, cross->temp_rate_cross, relay/gradual->hysteresis (form reported as a note),
warmup->warmup, drift->time_drift.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .cases import CHANNELS, CLASSES, OWN, UNRECORDED, build_case
from .logger import write_csv
from .oracle import evaluate, tuned

ROOT = Path(__file__).resolve().parents[2]
KIND = {"lag": "thermal_lag", "gradient": "gradient", "rate": "rate", "rate_squared": "rate_squared",
        "cross": "temp_rate_cross", "relay": "hysteresis", "gradual": "hysteresis",
        "warmup": "warmup", "drift": "time_drift"}
NO_PROBE = {"warmup", "time_drift"}
MINE = {v: k for k, v in KIND.items() if k not in ("relay", "gradual")}


def _key(kind: str, params: dict):
    if kind in NO_PROBE:
        return (kind, None)
    if kind == "gradient":
        pr = params.get("probes") or params.get("probe") or ""
        return (kind, frozenset(str(pr).replace(" ", "").split("-")))
    return (kind, params.get("probe"))


def _truth_key(nm, pr):
    kind = KIND[nm]
    if kind in NO_PROBE:
        return (kind, None)
    if kind == "gradient":
        return (kind, frozenset(pr.split("-")))
    return (kind, pr)


def _fmt_key(k):
    kind, pr = k
    if pr is None:
        return kind
    return f"{kind}({'-'.join(sorted(pr)) if isinstance(pr, frozenset) else pr})"


def run_product(case: dict, workdir: Path) -> tuple[dict | None, str, float]:
    paths = {}
    for name in ("train", "validate"):
        rr = case["runs"][name]
        paths[name] = workdir / f"{name}.csv"
        write_csv(paths[name], rr["meta"], rr["cols"])
    out = workdir / "report.json"
    cmd = [sys.executable, "-m", "bench", "close-loop", str(paths["train"]), str(paths["validate"]),
           "--model", case["formula"], "--json", str(out)]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.time()
    p = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    dt = time.time() - t0
    if p.returncode != 0 or not out.exists():
        return None, f"exit {p.returncode}: " + (p.stderr or p.stdout)[-400:], dt
    return json.loads(out.read_text()), "", dt


def judge(case: dict, ch: str, rep: dict) -> dict:
    truth = case["truth"][ch]
    ora = evaluate(case, ch)
    eff = rep.get("effects_added") or []
    got = [_key(e.get("kind"), e.get("params") or {}) for e in eff]
    verdict = rep.get("verdict")
    before = rep["before"]["validation_std100_dph"]
    after = rep["after"]["validation_std100_dph"]
    floor = rep.get("noise_floor_dph")
    names = {nm for nm, _, _ in truth["effects"]}
    role = ("complete" if not names else "unrecorded" if names & UNRECORDED else "effect")
    why, notes = [], []
    if role == "complete":
        if got:
            why.append("added " + ", ".join(map(_fmt_key, got)) + " to a complete channel")
        if verdict != "no_effect_missing":
            why.append(f"verdict {verdict} (want no_effect_missing)")
    elif role == "effect":
        want = [_truth_key(nm, pr) for nm, pr, _ in truth["effects"]]
        for i, w in enumerate(want):
            if w not in got:
                amb = _ambiguous_hit(eff, w)
                why.append(f"missed {_fmt_key(w)}" + (" (product lists it as ambiguous)" if amb else ""))
        for g in got:
            if g not in want:
                why.append(f"extra {_fmt_key(g)}")
        for (nm, pr, par) in truth["effects"]:
            for e in eff:
                if _key(e["kind"], e.get("params") or {}) == _truth_key(nm, pr):
                    p = e.get("params") or {}
                    if nm in ("relay", "gradual") and p.get("form") not in {"relay": ("relay", "reversal"),
                                                                            "gradual": ("gradual",)}[nm]:
                        notes.append(f"hysteresis form {p.get('form')} (true {nm})")
                    if nm == "lag" and p.get("tau_s"):
                        notes.append(f"tau {p['tau_s']:.0f}s (true {par:.0f})")
                    if nm == "warmup":
                        notes.append(f"warmup params {p} (true tau {par:.0f})")
        if why or after > 1.15 * ora["oracle"]:
            named = []
            for e, g in zip(eff, got):
                nm = MINE.get(g[0])
                if g[0] == "hysteresis":
                    nm = "gradual" if (e.get("params") or {}).get("form") == "gradual" else "relay"
                if g[0] == "thermal_lag" and (e.get("params") or {}).get("form") != "absolute" \
                        and g[1] != OWN[ch]:
                    nm = "lag_rel"
                pr = "-".join(sorted(g[1])) if isinstance(g[1], frozenset) else g[1]
                named.append((nm, pr))
            mine = [(nm, pr) for nm, pr, _ in truth["effects"]]
            if any(nm is None for nm, _ in named):
                pass
            elif sorted(map(str, named)) != sorted(map(str, mine)):
                alt = tuned(case, ch, named) / ora["oracle"]
                why.append(f"[product's set in our physics, tuned on TRAIN: {alt:.2f}x oracle "
                           + ("(data ambiguous)]" if alt <= 1.10 else "(distinguishable)]"))
            else:
                alt = tuned(case, ch, mine) / ora["oracle"]
                why.append(f"[right names; true set tuned on TRAIN by us: {alt:.2f}x oracle"
                           + (" (TRAIN cannot pin the parameters)]" if alt > 1.15 else " (product's fit/parameter fault)]"))
        partly_ok = floor is not None and ora["oracle"] > 1.2 * floor
        if verdict != "explained" and not (verdict == "partly_explained" and partly_ok):
            why.append(f"verdict {verdict} (want explained; oracle/floor {ora['oracle'] / floor:.2f})")
        if after > 1.15 * ora["oracle"]:
            why.append(f"after {after:.3f} > 1.15 x oracle {ora['oracle']:.3f}")
    else:
        if verdict != "unexplained_structure_remains":
            why.append(f"verdict {verdict} (want unexplained_structure_remains; added "
                       + (", ".join(map(_fmt_key, got)) or "nothing") + ")")
    if after > before * 1.001:
        why.append(f"after {after:.3f} worse than before {before:.3f}")
    naming = [w for w in why if w.startswith(("missed", "extra", "[product's"))]
    amb = bool(why) and len(naming) == len(why) and any("(data ambiguous)" in w for w in why) \
        and not any("(distinguishable)" in w for w in why)
    return {"role": role, "ok": not why, "amb": amb, "why": "; ".join(why), "notes": "; ".join(notes),
            "verdict": verdict, "got": ", ".join(map(_fmt_key, got)) or "-",
            "want": ", ".join(_fmt_key(_truth_key(nm, pr)) if nm in KIND else nm
                              for nm, pr, _ in truth["effects"]) or "-",
            "before": before, "after": after, "floor": floor, **ora}


def _ambiguous_hit(eff, w):
    for e in eff:
        for a in e.get("ambiguous_with") or []:
            if _key(a.get("kind"), a.get("params") or {}) == w:
                return True
    return False


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--keep", default="")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or list(CLASSES)
    for c in classes:
        if c not in CLASSES:
            ap.error(f"unknown class {c!r}; known: {', '.join(CLASSES)}")
    table, fails, t_start = [], [], time.time()
    for cls in classes:
        res = []
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            case = build_case(cls, seed)
            if a.keep:
                wd = Path(a.keep) / f"{cls}-{seed}"
                wd.mkdir(parents=True, exist_ok=True)
                rep, err, dt = run_product(case, wd)
            else:
                with tempfile.TemporaryDirectory() as td:
                    rep, err, dt = run_product(case, Path(td))
            for ch in CHANNELS:
                if rep is None:
                    j = {"role": "?", "ok": False, "why": f"product failed: {err}", "notes": ""}
                else:
                    j = judge(case, ch, rep["channels"][ch])
                j.update(cls=cls, seed=seed, ch=ch)
                res.append(j)
                if not j["ok"]:
                    fails.append(j)
                if a.verbose and rep is not None:
                    print(f"{cls:16s} s{seed} {ch} {j['role']:10s} {'PASS' if j['ok'] else 'FAIL'} "
                          f"want={j['want']:28s} got={j['got']:28s} {j['verdict']:30s} "
                          f"bef={j['before']:.3f} aft={j['after']:.3f} ora={j['oracle']:.3f} "
                          f"decl={j['declared']:.3f} noise={j['noise']:.3f} floor={j['floor']:.3f} "
                          f"cov={j['coverage']:.2f} [{case['kinds'][0]}->{case['kinds'][1]} {dt:.0f}s]"
                          + (f" | {j['why']}" if j["why"] else "") + (f" | {j['notes']}" if j["notes"] else ""),
                          flush=True)
                elif a.verbose:
                    print(f"{cls:16s} s{seed} {ch} FAIL {j['why']}", flush=True)
        ok = sum(r["ok"] for r in res)
        ratios = [r["after"] / r["oracle"] for r in res if r.get("oracle")]
        amb = sum(bool(r.get("amb")) for r in res)
        table.append((cls, len(res), ok, amb, float(np.median(ratios)) if ratios else float("nan")))
    print(f"\n{'class':18s} {'chan':>4s} {'pass':>4s} {'fail':>4s} {'(ambiguous)':>11s} {'med after/oracle':>17s}")
    for cls, n, ok, amb, med in table:
        print(f"{cls:18s} {n:4d} {ok:4d} {n - ok:4d} {amb:11d} {med:17.2f}")
    tot, tok, tam = (sum(t[i] for t in table) for i in (1, 2, 3))
    print(f"{'TOTAL':18s} {tot:4d} {tok:4d} {tot - tok:4d} {tam:11d}   ({time.time() - t_start:.0f} s)")
    if fails:
        print("\nfailing channels:")
        for f in fails:
            print(f"  {f['cls']} seed {f['seed']} {f['ch']} ({f['role']}{', ambiguous data' if f.get('amb') else ''}): "
                  f"{f['why']}")
    return 0 if not fails else 1


if __name__ == "__main__":
    sys.exit(main())
