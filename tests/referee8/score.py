"""Referee 8 scorer: python -m tests.referee8.score --seeds 3 --first-seed 1 [--classes a,b] [--keep DIR] [--verbose]"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from . import cases as C
from . import oracle as O

BENCH = os.path.join(os.path.dirname(sys.executable), "bench")


def run_product(case, d):
    tr, va, js = (os.path.join(d, f) for f in ("train.csv", "validate.csv", "report.json"))
    C.write_run(case, case.train, tr, "train")
    C.write_run(case, case.validate, va, "validate")
    t0 = time.time()
    p = subprocess.run([BENCH, "close-loop", tr, va, "--model", case.formula, "--latitude",
                        f"{case.latitude:.4f}", "--json", js], capture_output=True, text=True,
                       env=dict(os.environ, BENCH_DATABASE_URL=f"sqlite:///{d}/bench.sqlite"))
    el = time.time() - t0
    if p.returncode != 0:
        return None, el, p.stderr[-800:]
    with open(js) as fh:
        return json.load(fh), el, ""


def _eff_probes(e):
    pr = e.get("params", {})
    if "probes" in pr:
        v = pr["probes"]
        return tuple(sorted(v.split("-") if isinstance(v, str) else v))
    if "pair" in pr:
        return tuple(sorted(pr["pair"]))
    if "probe" in pr:
        return (pr["probe"],)
    return ()


def judge_channel(case, ch, rep):
    tru = case.truth[ch]
    o = O.oracle(case, ch)
    after = rep["after"]["validation_std100_dph"]
    before = rep["before"]["validation_std100_dph"]
    floor = rep.get("noise_floor_dph")
    verdict = rep["verdict"]
    added = rep.get("effects_added", [])
    named = sorted((e["kind"], _eff_probes(e)) for e in added)
    want = sorted((e["kind"], tuple(e["probes"])) for e in tru["effects"] if e["kind"] != "unrecorded_supply")
    reasons = []
    if tru["unrecorded"]:
        if verdict != "unexplained_structure_remains":
            reasons.append(f"verdict {verdict} (want unexplained_structure_remains)")
    else:
        if named != want:
            ok, exc, fl = O.lookalike(case, ch, added) if (added and want) else (False, float("nan"), 0.0)
            if not ok:
                reasons.append(f"named {named} truth {want} (look-alike excess {exc:.4f} vs 0.5 floor {0.5 * fl:.4f})")
        allowed = set(tru["verdicts"])
        if want and floor and o["oracle"] > 1.2 * floor:
            allowed.add("partly_explained")
        if verdict not in allowed:
            reasons.append(f"verdict {verdict} (want {'/'.join(sorted(allowed))})")
        if after is None:
            if o["coverage"] > 0.3:
                reasons.append(f"no in-range validation number (oracle coverage {o['coverage']:.2f})")
        elif after > 1.15 * o["oracle"]:
            reasons.append(f"after {after:.4f} > 1.15x oracle {o['oracle']:.4f}")
    if after is not None and before is not None and after > before * 1.0001:
        reasons.append(f"after {after:.4f} above before {before:.4f}")
    after = float("nan") if after is None else after
    before = float("nan") if before is None else before
    floor = float("nan") if floor is None else floor
    return dict(ch=ch, ok=not reasons, reasons=reasons, named=named, want=want, verdict=verdict,
                after=after, before=before, oracle=o["oracle"], floor=floor, noise=o["noise"],
                ratio=(after / o["oracle"]) if after else float("nan"))


def score_case(cls, seed, keep=None, verbose=False):
    case = C.build(cls, seed)
    d = os.path.join(keep, f"{cls}-{seed}") if keep else tempfile.mkdtemp(prefix="r8-")
    os.makedirs(d, exist_ok=True)
    rep, el, err = run_product(case, d)
    if rep is None:
        return dict(cls=cls, seed=seed, ok=False, error=err, chans=[], elapsed=el)
    chans = [judge_channel(case, ch, rep["channels"][ch]) for ch in C.CHANNELS]
    if not keep:
        for f in os.listdir(d):
            os.remove(os.path.join(d, f))
        os.rmdir(d)
    return dict(cls=cls, seed=seed, ok=all(c["ok"] for c in chans), chans=chans, elapsed=el)


def fmt(r, verbose=False):
    if "error" in r:
        return f"{r['cls']:<22} {r['seed']:>3}  ERROR {r['error'].strip().splitlines()[-1] if r['error'].strip() else ''}"
    parts = []
    for c in r["chans"]:
        s = (f"{c['ch']}:{'PASS' if c['ok'] else 'FAIL'} [{c['verdict']}; "
             f"{c['after']:.4f}/{c['oracle']:.4f}/{c['before']:.4f}/{c['floor']:.4f}]")
        if not c["ok"]:
            s += " (" + "; ".join(c["reasons"]) + ")"
        elif verbose and c["named"]:
            s += f" named {c['named']}"
        parts.append(s)
    return f"{r['cls']:<22} {r['seed']:>3} {r['elapsed']:5.1f}s  " + "  ".join(parts)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="")
    ap.add_argument("--keep", default=None)
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or C.CLASSES
    print("columns per channel: [verdict; after/oracle/before/product floor] (deg/h, VALIDATE in range)")
    nc = mc = nch = mch = 0
    for cls in classes:
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            r = score_case(cls, seed, a.keep, a.verbose)
            print(fmt(r, a.verbose), flush=True)
            mc += 1
            nc += r["ok"]
            mch += 3
            nch += sum(c["ok"] for c in r["chans"])
    print(f"SUMMARY {nc}/{mc} cases, {nch}/{mch} channels")


if __name__ == "__main__":
    main()
