"""Fifth referee: generate cases, run the product's ``bench close-loop`` on them, score each channel.

    python -m tests.referee5.score --seeds 5 --first-seed 1 [--classes a,b] [--verbose]
                                   [--json out.json] [--jobs 2] [--keep DIR] [--diag]

Per channel (the rule the product is judged by):

* kinds   - the product's added effect families (and probes, where the truth names a probe) equal
            the true ones; nothing is added to a complete channel.  Unrecorded-driver channels
            require nothing (anything added is judged through the verdict).
* verdict - complete -> no_effect_missing; library effects -> explained (partly_explained only when
            the referee's oracle itself stays above 1.2x the product's noise_floor_dph); unrecorded
            driver -> unexplained_structure_remains.
* error   - after validation_std100_dph <= before; for library-effect channels also
            after <= 1.15 x the referee's oracle (oracle.py).
A case passes when its three channels pass.  The referee's own "before" is printed next to the
product's and a difference over 5 % is flagged (a note, not a failure).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

from . import cases as cs
from . import oracle as orc

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
PROBE_RE = re.compile(r"\bt\d+\b")


def family_of(kind: str) -> str:
    k = kind.lower()
    if "hyster" in k or "relay" in k:
        return "hysteresis"
    if "lag" in k:
        return "lag"
    if "gradient" in k:
        return "gradient"
    if "warm" in k:
        return "warmup"
    if "drift" in k:
        return "drift"
    if ("temp" in k and "rate" in k) or "cross" in k:
        return "temp_rate"
    if "rate" in k and "squar" in k:
        return "rate_squared"
    if "rate" in k:
        return "rate"
    return k


def _strings(v):
    if isinstance(v, str):
        yield v
    elif isinstance(v, dict):
        for x in v.values():
            yield from _strings(x)
    elif isinstance(v, (list, tuple)):
        for x in v:
            yield from _strings(x)


def product_effects(ch_report: dict) -> list:
    out = []
    for e in ch_report.get("effects_added") or []:
        out.append((family_of(e.get("kind", "")), _probes(e), e.get("kind", "")))
    return out


def _probes(e):
    probes = set()
    for s in _strings(e.get("params") or {}):
        probes |= set(PROBE_RE.findall(s))
    return frozenset(probes)


def ambiguous(ch_report: dict) -> list:
    """'family[probes]' of the candidates the product itself named as not decided by TRAIN."""
    out = []
    for e in ch_report.get("effects_added") or []:
        for a in e.get("ambiguous_with") or []:
            tag = f"{family_of(a.get('kind', ''))}[{','.join(sorted(_probes(a)))}]"
            if tag not in out:
                out.append(tag)
    return out


def run_product(case, workdir: str) -> tuple[dict | None, str, float]:
    tr, va, js = (os.path.join(workdir, n) for n in ("train.csv", "validate.csv", "out.json"))
    case.write_csv(tr, "train")
    case.write_csv(va, "val")
    env = dict(os.environ, PYTHONPATH=REPO, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               MKL_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "bench", "close-loop", tr, va, "--model", case.model, "--json", js,
           "--db", f"sqlite:///{os.path.join(workdir, 'bench.sqlite')}"]
    t0 = time.time()
    try:
        p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        return None, "timeout", time.time() - t0
    wall = time.time() - t0
    if p.returncode != 0 or not os.path.exists(js):
        return None, (p.stderr or p.stdout)[-800:], wall
    with open(js) as f:
        return json.load(f), "", wall


def score_channel(case, ch, rep: dict, mine: dict) -> dict:
    tr = case.truth[ch]
    reasons, notes = [], []
    verdict = rep.get("verdict")
    before = (rep.get("before") or {}).get("validation_std100_dph")
    after = (rep.get("after") or {}).get("validation_std100_dph")
    floor = rep.get("noise_floor_dph")
    added = product_effects(rep)
    fams = sorted({a[0] for a in added})
    # kinds
    if tr.kind == "complete":
        if added:
            reasons.append(f"added {[a[2] for a in added]} to a complete channel")
    elif tr.kind == "library":
        want = tr.families()
        if fams != want:
            reasons.append(f"families {fams} != truth {want}")
        for e in tr.effects:
            if not e.probes:
                continue
            need = set(e.probes)
            got = [a[1] for a in added if a[0] == e.family]
            if got and not any(need <= g if e.family != "gradient" else need == g for g in got):
                reasons.append(f"{e.family} probes {[sorted(g) for g in got]} != truth {sorted(need)}")
    # verdict
    if tr.kind == "complete" and verdict != "no_effect_missing":
        reasons.append(f"verdict {verdict} (want no_effect_missing)")
    elif tr.kind == "unrecorded" and verdict != "unexplained_structure_remains":
        reasons.append(f"verdict {verdict} (want unexplained_structure_remains)")
    elif tr.kind == "library" and verdict != "explained":
        ok_partly = (verdict == "partly_explained" and floor is not None
                     and mine["oracle"] > 1.2 * floor)
        if not ok_partly:
            reasons.append(f"verdict {verdict} (want explained; oracle/floor="
                           f"{mine['oracle'] / floor if floor else float('nan'):.2f})")
    # error
    if before is None and after is None and mine["coverage"] == 0:
        notes.append("no validation block in range: error not judged")
    elif before is None or after is None:
        reasons.append("no before/after numbers")
    else:
        if after > before * (1 + 1e-9):
            reasons.append(f"after {after:.4f} > before {before:.4f}")
        if tr.kind == "library" and after > 1.15 * mine["oracle"]:
            reasons.append(f"after {after:.4f} > 1.15 x oracle {mine['oracle']:.4f}")
        if before and abs(mine["before"] - before) > 0.05 * before:
            notes.append(f"referee before {mine['before']:.4f} vs product {before:.4f} "
                         f"({100 * (mine['before'] / before - 1):+.0f} %)")
        cov = (rep.get("before") or {}).get("validation_coverage")
        if cov is not None and abs(cov - mine["coverage"]) > 0.05:
            notes.append(f"coverage referee {mine['coverage']:.2f} vs product {cov:.2f}")
    return dict(channel=ch, kind=tr.kind, truth=[e.describe() for e in tr.effects],
                truth_families=tr.families(), verdict=verdict, added=[a[2] for a in added],
                added_families=fams, added_probes=[sorted(a[1]) for a in added],
                before=before, after=after, floor=floor, ref_before=mine["before"],
                oracle=mine["oracle"], ref_coverage=mine["coverage"], sigma100=tr.sigma100,
                noise_inrange=mine["noise_inrange"], ambiguous=ambiguous(rep),
                passed=not reasons, reasons=reasons, notes=notes)


def run_case(arg) -> dict:
    cls, seed, keep = arg
    t0 = time.time()
    case = cs.build_case(cls, seed)
    t_gen = time.time() - t0
    mine = {ch: orc.channel_numbers(case, ch) for ch in "xyz"}
    with tempfile.TemporaryDirectory(prefix="referee5-") as tmp:
        workdir = tmp
        if keep:
            workdir = os.path.join(keep, case.name)
            os.makedirs(workdir, exist_ok=True)
        rep, err, wall = run_product(case, workdir)
    res = dict(name=case.name, cls=cls, seed=seed, model=case.model, gen_s=t_gen, product_s=wall,
               setup=case.diag["setup"], channel_probes=case.channel_probes)
    if rep is None:
        res.update(passed=False, error=err, channels=[])
        return res
    chans = []
    for ch in "xyz":
        chrep = (rep.get("channels") or {}).get(ch)
        if chrep is None:
            chans.append(dict(channel=ch, passed=False, reasons=["channel missing in report"],
                              kind=case.truth[ch].kind, notes=[]))
            continue
        sc = score_channel(case, ch, chrep, mine[ch])
        sc["diag"] = case.diag[ch]
        chans.append(sc)
    res.update(passed=all(c["passed"] for c in chans), channels=chans)
    return res


def diagnose(arg) -> str:
    """Generator diagnostics for one case, without the product."""
    cls, seed, _ = arg
    case = cs.build_case(cls, seed)
    st = case.diag["setup"]
    lines = [f"{case.name}: model '{case.model}', logger {st['period']} s, probes {st['probes']}, "
             f"network taus {st['taus']} s, train {st['train_h']:.1f} h {st['train_prog']}, "
             f"validate {st['val_h']:.1f} h {st['val_prog']}"]
    for ch in "xyz":
        m = orc.channel_numbers(case, ch)
        d = case.diag[ch]
        eff = "; ".join(f"{e['effect']} r={e['r_train']:.1f}/{e['r_val']:.1f}" for e in d["effects"])
        lines.append(f"   {ch} {d['kind']:10s} noise(in range) {m['noise_inrange']:.4f} before {m['before']:.4f} "
                     f"oracle {m['oracle']:.4f} (oracle/noise {m['oracle'] / m['noise_inrange']:.2f}) "
                     f"coverage {m['coverage']:.2f} poly-left {d['poly_unabsorbed']:.2f} {eff}")
    return "\n".join(lines)


def _fmt(v):
    return "   -   " if v is None else f"{v:.4f}"


def print_case(res, verbose):
    tag = "pass" if res["passed"] else "FAIL"
    print(f"{tag} {res['name']}  model='{res['model']}'  ({res['product_s']:.1f} s)", flush=True)
    if res.get("error"):
        print(f"   product error: {res['error']}")
        return
    for c in res["channels"]:
        if not verbose and c["passed"] and not c.get("notes"):
            continue
        line = (f"   {c['channel']} {c['kind']:10s} truth={'+'.join(c.get('truth_families') or []) or '-':24s}"
                f" verdict={c.get('verdict')!s:30s} added={','.join(c.get('added') or []) or '-'}")
        print(line)
        if verbose or not c["passed"]:
            print(f"      before {_fmt(c.get('before'))} (ref {_fmt(c.get('ref_before'))}) after "
                  f"{_fmt(c.get('after'))} oracle {_fmt(c.get('oracle'))} floor {_fmt(c.get('floor'))}"
                  f" noise {_fmt(c.get('noise_inrange'))}  truth: {'; '.join(c.get('truth') or [])}"
                  f" probes={c.get('added_probes')}")
            if c.get("ambiguous") and not c["passed"]:
                print(f"      product's ambiguous candidates: {' '.join(c['ambiguous'])}")
        for r in c.get("reasons", []):
            print(f"      FAIL: {r}")
        for n in c.get("notes", []):
            print(f"      note: {n}")


def table(results):
    rows = {}
    for r in results:
        d = rows.setdefault(r["cls"], dict(cases=0, cpass=0, ch=0, chpass=0, kinds=0, verdict=0, error=0))
        d["cases"] += 1
        d["cpass"] += r["passed"]
        for c in r["channels"]:
            d["ch"] += 1
            d["chpass"] += c["passed"]
            for reason in c.get("reasons", []):
                if reason.startswith("verdict"):
                    d["verdict"] += 1
                elif reason.startswith("after") or reason.startswith("no before"):
                    d["error"] += 1
                else:
                    d["kinds"] += 1
    tot = dict(cases=0, cpass=0, ch=0, chpass=0, kinds=0, verdict=0, error=0)
    print()
    print(f"{'class':18s} {'cases':>9s} {'channels':>10s} {'kinds':>6s} {'verdict':>8s} {'error':>6s}")
    for cls in cs.CLASSES:
        if cls not in rows:
            continue
        d = rows[cls]
        for k in tot:
            tot[k] += d[k]
        print(f"{cls:18s} {d['cpass']:>4d}/{d['cases']:<4d} {d['chpass']:>5d}/{d['ch']:<4d} "
              f"{d['kinds']:>6d} {d['verdict']:>8d} {d['error']:>6d}")
    print(f"{'TOTAL':18s} {tot['cpass']:>4d}/{tot['cases']:<4d} {tot['chpass']:>5d}/{tot['ch']:<4d} "
          f"{tot['kinds']:>6d} {tot['verdict']:>8d} {tot['error']:>6d}")
    print("(kinds / verdict / error = channel failures by criterion; a channel may fail several)")
    return rows, tot


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--json", default="")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", default="", help="keep the CSVs and reports in this directory")
    ap.add_argument("--diag", action="store_true", help="generator diagnostics only (no product)")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or list(cs.CLASSES)
    bad = [c for c in classes if c not in cs.CLASSES]
    if bad:
        ap.error(f"unknown classes {bad}; known: {', '.join(cs.CLASSES)}")
    jobs = [(c, s, a.keep) for c in classes for s in range(a.first_seed, a.first_seed + a.seeds)]
    t0 = time.time()
    if a.diag:
        with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as ex:
            for text in ex.map(diagnose, jobs):
                print(text, flush=True)
        return 0
    results = []
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as ex:
        for res in ex.map(run_case, jobs):
            print_case(res, a.verbose)
            results.append(res)
    rows, tot = table(results)
    print(f"wall {time.time() - t0:.0f} s")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(dict(results=results, table=rows, total=tot), f, indent=1, default=float)
    return 0 if tot["cpass"] == tot["cases"] else 1


if __name__ == "__main__":
    sys.exit(main())
