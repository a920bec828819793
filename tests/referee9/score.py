"""Referee 9 scorer.

python -m tests.referee9.score --seeds N [--first-seed K] [--classes a,b] [--json out.json] [--verbose] [--keep DIR]

Per channel: kinds and probes of `effects_added` against the truth (a different one is accepted as a
look-alike only when its own reconstruction here - least squares with the declared terms on TRAIN,
evaluated on the in-range VALIDATE part - comes within half a noise floor of the true effect's),
an honest verdict, `after` within 1.15x this referee's oracle and never above `before`; `before` is
compared with this referee's own declared-model-only number (ratio reported).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from . import cases as C
from . import physics as P

BENCH = os.path.join(os.path.dirname(sys.executable), "bench")


def run_product(case, d):
    tr, va, js = (os.path.join(d, f) for f in ("train.csv", "validate.csv", "report.json"))
    C.write_run(case, case.train, tr, "train")
    C.write_run(case, case.validate, va, "validate")
    t0 = time.time()
    p = subprocess.run([BENCH, "close-loop", tr, va, "--model", case.model, "--latitude", f"{case.latitude:.4f}",
                        "--json", js], capture_output=True, text=True,
                       env=dict(os.environ, BENCH_DATABASE_URL=f"sqlite:///{d}/bench.sqlite"))
    el = time.time() - t0
    if p.returncode != 0:
        return None, el, p.stderr[-1500:]
    with open(js) as fh:
        return json.load(fh), el, ""


# ---------------------------------------------------------------------------------------------
# oracle

def _y(case, run, ch):
    return run.gyro[ch] - C.earth(case, run)[ch]


def fit_eval(case, ch, extra_tr, extra_va):
    """Declared terms + extra columns, least squares on TRAIN block means, prediction on VALIDATE."""
    tr, va = case.train, case.validate
    ytr, yva = _y(case, tr, ch), _y(case, va, ch)
    ctr = C.declared_cols(case, tr, ch) + list(extra_tr)
    cva = C.declared_cols(case, va, ch) + list(extra_va)
    beta = P.lstsq_blocks(tr.t, ytr, ctr, np.isfinite(ytr))
    pred = P.predict(beta, cva, len(va.t))
    return yva, pred, beta


def oracle(case, ch):
    tr, va = case.train, case.validate
    blocks = C.in_range_blocks(case, ch)
    effs = case.truth[ch]["effects"]
    # a rate's derivative window is a measurement choice, not part of the physics: the one that fits
    # TRAIN best (100-s block residual) is taken for the oracle
    best = None
    wins = [120.0, 240.0, 480.0, 900.0] if any(e["kind"] in ("rate", "rate2", "trate") for e in effs) else [120.0]
    for w in wins:
        xtr = [C.effect_col(case, tr, e, w) for e in effs]
        xva = [C.effect_col(case, va, e, w) for e in effs]
        ytr = _y(case, tr, ch)
        ctr = C.declared_cols(case, tr, ch) + xtr
        beta = P.lstsq_blocks(tr.t, ytr, ctr, np.isfinite(ytr))
        rtr = P.std100(tr.t, ytr - P.predict(beta, ctr, len(tr.t)))
        if best is None or rtr < best[0]:
            best = (rtr, w, xtr, xva)
    _, win, xtr, xva = best
    yva, pred, _ = fit_eval(case, ch, xtr, xva)
    yva0, pred0, _ = fit_eval(case, ch, [], [])
    noise = np.where(np.isfinite(yva), va.noise[ch], np.nan)
    return dict(oracle=P.std100(va.t, yva - pred, blocks), before=P.std100(va.t, yva0 - pred0, blocks),
                floor=P.std100(va.t, noise, blocks), coverage=float(blocks.mean()), pred=pred, blocks=blocks,
                window_s=win)


# ---------------------------------------------------------------------------------------------
# the product's effects, rebuilt here from their reported kind and parameters

def _params(e):
    return e.get("params") or {}


def _probe_list(e):
    pr = _params(e)
    for k in ("probes", "pair"):
        if k in pr:
            v = pr[k]
            return sorted(v.split("-") if isinstance(v, str) else list(v))
    return [pr["probe"]] if "probe" in pr else []


def _num(pr, *names, default=None):
    for n in names:
        if n in pr and pr[n] is not None:
            try:
                return float(pr[n])
            except (TypeError, ValueError):
                pass
    return default


def product_cols(case, run, ch, e):
    """Columns for one product effect on one run; None when this referee cannot rebuild it."""
    k = e.get("kind", "")
    pr = _params(e)
    probes = _probe_list(e)
    win = _num(pr, "window_s", "rate_window_s", default=120.0)
    if k == C.PRODUCT_KIND["lag"] and probes:
        p = probes[0]
        tau = _num(pr, "tau_s", "tau")
        if tau is None:
            return None
        L = P.lag_irregular(run.t, run.temps[p], tau)
        T = P.fill_nan(run.t, run.temps[p])
        form = str(pr.get("form", "") or "")
        if form == "absolute":
            return [L]
        if form in ("", "minus", "lag_minus_t", "relative"):
            return [L - T]
        if "declared" in form or "model" in form:
            # f(lag T) - f(T), f the declared model's temperature part as TRAIN fits it (own probe)
            if p != case.probes[ch] or case.declared not in ("static", "cubic", "cubic_rate"):
                return None
            ytr = case.train.gyro[ch] - C.earth(case, case.train)[ch]
            cols = C.declared_cols(case, case.train, ch)
            beta = P.lstsq_blocks(case.train.t, ytr, cols, np.isfinite(ytr))
            d0 = 25.0 if case.declared == "static" else 0.0
            f = lambda x: beta[1] * (x - d0) + beta[2] * (x - d0) ** 2 + beta[3] * (x - d0) ** 3
            return [f(L) - f(T)]
        return None
    if k == C.PRODUCT_KIND["gradient"] and len(probes) == 2:
        a, b = probes
        return [P.fill_nan(run.t, run.temps[a]) - P.fill_nan(run.t, run.temps[b])]
    if k in (C.PRODUCT_KIND["rate"], C.PRODUCT_KIND["rate2"], C.PRODUCT_KIND["trate"]) and probes:
        p = probes[0]
        r = P.centred_slope(run.t, run.temps[p], win)
        if k == C.PRODUCT_KIND["rate"]:
            return [r]
        if k == C.PRODUCT_KIND["rate2"]:
            return [r * r]
        T = P.fill_nan(run.t, run.temps[p])
        return [(T - 25.0) * r, r]
    if k == C.PRODUCT_KIND["warmup"]:
        tau = _num(pr, "tau_s", "tau")
        if tau is None:
            return None
        return [np.exp(-C.time_on(run) / tau)]
    if k == C.PRODUCT_KIND["drift"]:
        return [(run.t - run.t[0]) / 3600.0]
    if k == C.PRODUCT_KIND["gsens"]:
        g = C.gravity(run)
        return [g[:, 0], g[:, 1], g[:, 2]]
    return None


def lookalike(case, ch, added, o):
    """Does the product's effect set, rebuilt here, reproduce the true effect?  Declared terms + the
    rebuilt columns are fitted (least squares, 100-s block means) to the noise-free TRAIN signal and
    evaluated on VALIDATE; the distance is the std of 100-s means, over the in-range VALIDATE blocks,
    of the difference from the noise-free true signal (a question of form, not of this noise draw).
    None when an effect cannot be rebuilt."""
    tr, va = case.train, case.validate
    xtr, xva = [], []
    for e in added:
        a, b = product_cols(case, tr, ch, e), product_cols(case, va, ch, e)
        if a is None or b is None:
            return None
        xtr += a
        xva += b
    ytr = _y(case, tr, ch) - tr.noise[ch]
    yva = _y(case, va, ch) - va.noise[ch]
    ctr = C.declared_cols(case, tr, ch) + xtr
    cva = C.declared_cols(case, va, ch) + xva
    beta = P.lstsq_blocks(tr.t, ytr, ctr, np.isfinite(ytr))
    pred = P.predict(beta, cva, len(va.t))
    d = np.where(np.isfinite(yva), pred - yva, np.nan)
    plain = P.std100(va.t, d, o["blocks"])
    span = va.t[-1] - va.t[0]
    offs = [np.exp(-(va.t - va.t[0]) / _num(_params(e), "tau_s", "tau")) for e in added
            if e.get("kind") == C.PRODUCT_KIND["lag"] and _num(_params(e), "tau_s", "tau")
            and _num(_params(e), "tau_s", "tau") <= span / 3]
    if offs:
        ids = P.block_ids(va.t)
        dm, _ = P.block_means(ids, d)
        X = np.column_stack([np.ones(len(dm))] + [P.block_means(ids, x)[0] for x in offs])
        m = o["blocks"][: len(dm)] & np.isfinite(dm) & np.all(np.isfinite(X), axis=1)
        b, *_ = np.linalg.lstsq(X[m], dm[m], rcond=None)
        d2 = d - sum(bi * x for bi, x in zip(b[1:], offs))
        return min(plain, P.std100(va.t, d2, o["blocks"]))
    return plain


# ---------------------------------------------------------------------------------------------

def truth_named(case, ch):
    out = []
    for e in case.truth[ch]["effects"]:
        if e["kind"] == "supply":
            continue
        out.append((C.PRODUCT_KIND[e["kind"]], tuple(sorted(e["probes"]))))
    return sorted(out)


def judge_channel(case, ch, rep):
    tru = case.truth[ch]
    o = oracle(case, ch)
    after = rep["after"].get("validation_std100_dph")
    before = rep["before"].get("validation_std100_dph")
    pfloor = rep.get("noise_floor_dph")
    verdict = rep.get("verdict")
    added = rep.get("effects_added", []) or []
    named = sorted((e.get("kind"), tuple(_probe_list(e))) for e in added)
    want = truth_named(case, ch)
    reasons = []
    look = None
    floor = o["floor"]
    if tru["unrecorded"]:
        if verdict != "unexplained_structure_remains":
            reasons.append(f"verdict {verdict} (want unexplained_structure_remains)")
    else:
        if named != want:
            if added and want:
                look = lookalike(case, ch, added, o)
            ok = look is not None and np.isfinite(look) and look <= 0.5 * floor
            if not ok:
                lk = "not rebuildable" if (added and want and look is None) else f"{look if look is not None else float('nan'):.4f}"
                reasons.append(f"named {named} truth {want} (look-alike distance {lk} vs 0.5 floor {0.5 * floor:.4f})")
        allowed = set(tru["verdicts"])
        if want and o["oracle"] > 1.2 * floor:
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
    nan = float("nan")
    return dict(ch=ch, ok=not reasons, reasons=reasons, named=[list(x) for x in named], want=[list(x) for x in want],
                verdict=verdict, after=nan if after is None else after, before=nan if before is None else before,
                oracle=o["oracle"], floor=floor, product_floor=nan if pfloor is None else pfloor,
                my_before=o["before"], before_ratio=(before / o["before"]) if before else nan,
                coverage=o["coverage"], lookalike=look, oracle_window_s=o["window_s"],
                effects_added=[dict(kind=e.get("kind"), params=_params(e)) for e in added],
                truth=[dict(kind=e["kind"], probes=list(e["probes"]),
                            params={k: v for k, v in e["params"].items()}, scale_dph=e.get("scale_dph"))
                       for e in tru["effects"]])


def score_case(cls, seed, keep=None):
    case = C.build(cls, seed)
    d = os.path.join(keep, f"{cls}-{seed}") if keep else tempfile.mkdtemp(prefix="r9-")
    os.makedirs(d, exist_ok=True)
    try:
        rep, el, err = run_product(case, d)
        if rep is None:
            return dict(cls=cls, seed=seed, ok=False, error=err, chans=[], elapsed=el)
        chans = [judge_channel(case, ch, rep["channels"][ch]) for ch in C.CHANNELS]
    finally:
        if not keep:
            shutil.rmtree(d, ignore_errors=True)
    return dict(cls=cls, seed=seed, ok=all(c["ok"] for c in chans), chans=chans, elapsed=el)


def fmt(r, verbose=False):
    if r.get("error") is not None:
        last = r["error"].strip().splitlines()[-1] if r["error"].strip() else ""
        return f"{r['cls']:<26} {r['seed']:>3}  ERROR {last}"
    parts = []
    for c in r["chans"]:
        s = (f"{c['ch']}:{'PASS' if c['ok'] else 'FAIL'} [{c['verdict']}; {c['after']:.4f}/{c['oracle']:.4f}/"
             f"{c['before']:.4f}/{c['floor']:.4f} pf={c['product_floor']:.4f} b={c['before_ratio']:.2f}]")
        if not c["ok"]:
            s += " (" + "; ".join(c["reasons"]) + ")"
        if c.get("lookalike") is not None and c["ok"]:
            s += f" (look-alike, distance {c['lookalike']:.4f} <= 0.5 floor)"
        if verbose and c["named"]:
            s += f" named {c['effects_added']}"
        parts.append(s)
    return f"{r['cls']:<26} {r['seed']:>3} {r['elapsed']:5.1f}s\n    " + "\n    ".join(parts)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None)
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or C.CLASSES
    print("per channel: [verdict; after/oracle/before/floor (deg/h, VALIDATE in range; floor = std of 100-s means of the true noise) pf=product floor b=before/own-before]")
    out = []
    per = {}
    for cls in classes:
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            r = score_case(cls, seed, a.keep)
            out.append(r)
            print(fmt(r, a.verbose), flush=True)
            pc = per.setdefault(cls, [0, 0, 0, 0])
            pc[0] += r["ok"]
            pc[1] += 1
            pc[2] += sum(c["ok"] for c in r["chans"])
            pc[3] += 3
            if a.json:
                with open(a.json, "w") as fh:
                    json.dump(dict(results=out, per_class=per), fh, indent=1, default=float)
    for cls, (a1, b1, c1, d1) in per.items():
        print(f"CLASS {cls:<26} cases {a1}/{b1}  channels {c1}/{d1}")
    nc = sum(v[0] for v in per.values())
    mc = sum(v[1] for v in per.values())
    nch = sum(v[2] for v in per.values())
    mch = sum(v[3] for v in per.values())
    print(f"SUMMARY {nc}/{mc} cases, {nch}/{mch} channels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
