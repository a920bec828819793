"""Referee 6 scorer.

python -m tests.referee6.score --seeds N --first-seed S [--classes a,b] [--json out.json]
                               [--keep DIR] [--verbose]
"""
from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict

import numpy as np
import pandas as pd

from . import physics as ph
from .cases import CLASSES, build_case

# the repository this referee lives in, and the interpreter running it
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PY = sys.executable


def read_csv_text(text):
    lines = text.split("\n")
    k = 0
    while k < len(lines) and lines[k].startswith("#"):
        k += 1
    return pd.read_csv(io.StringIO("\n".join(lines[k:])))


def smooth_rate(x, t, window_s=60.0):
    """dT/dt of a quantised reading: moving mean over `window_s`, then np.gradient."""
    h = float(np.median(np.diff(t)))
    w = max(1, int(round(window_s / h)))
    pad = np.concatenate([np.full(w, x[0]), x, np.full(w, x[-1])])
    xs = np.convolve(pad, np.ones(w) / w, mode="same")[w:-w]
    return np.gradient(xs, t)


def declared(model, df, probe):
    tc = df[f"temp_{probe}"].to_numpy(float)
    t = df["time_s"].to_numpy(float)
    T = tc - 25.0
    cols = [T, T ** 2, T ** 3]
    inputs = [tc]
    if "dtc" in model:
        cols.append(smooth_rate(tc, t))
    if "t4" in model:
        t4 = df["temp_t4"].to_numpy(float)
        cols.append(tc - t4)
        inputs.append(t4)
    return np.column_stack(cols), inputs


def fit_eval(Xtr, ytr, oktr, Xva, yva, okva, tva, per_block):
    A = np.column_stack([np.ones(len(ytr)), Xtr])
    sc = np.abs(A[oktr]).max(axis=0)
    sc[sc == 0] = 1
    beta, *_ = np.linalg.lstsq(A[oktr] / sc, ytr[oktr], rcond=None)
    beta = beta / sc
    r = yva - np.column_stack([np.ones(len(yva)), Xva]) @ beta
    r = np.where(okva, r, 0.0)
    return ph.std100(tva, r, okva, per_block)


def norm_probe(p):
    p = str(p)
    return p[5:] if p.startswith("temp_") else p


def added_matches(truth_e, added):
    """Does the product's added effect `added` match truth effect `truth_e`?"""
    pk = truth_e["product_kind"]
    kind = added.get("kind")
    if kind != pk:
        return False
    prm = added.get("params") or {}
    if truth_e["kind"] == "gradient":
        raw = prm.get("probes")
        if isinstance(raw, str):
            got = [norm_probe(x.strip()) for x in raw.split("-")]
        elif isinstance(raw, (list, tuple)):
            got = [norm_probe(x) for x in raw]
        else:
            return False
        return sorted(got) == sorted(truth_e["probes"])
    if truth_e["kind"] == "relay":
        if str(prm.get("form")) not in ("relay", "reversal"):
            return False
    if "probe" in truth_e and truth_e["kind"] not in ("warmup", "drift"):
        return norm_probe(prm.get("probe")) == truth_e["probe"]
    return True


def desc_added(a):
    prm = a.get("params") or {}
    bits = [str(a.get("kind"))]
    for k in ("probe", "probes", "form"):
        if k in prm:
            bits.append(str(prm[k]))
    return ":".join(bits)


def desc_truth(e):
    bits = [e["kind"]]
    if "probe" in e:
        bits.append(e["probe"])
    if "probes" in e:
        bits.append("-".join(e["probes"]))
    return ":".join(bits)


def get_channel(rep, ch):
    chs = rep.get("channels", {})
    for key in (ch, f"gyro_{ch}"):
        if key in chs:
            return chs[key]
    return None


def score_case(case, rep, verbose=False):
    truth = case["truth"]
    model = case["model"]
    P = truth["sample_period_s"]
    per_block = 100.0 / P
    dtr = read_csv_text(case["train_csv"])
    dva = read_csv_text(case["validate_csv"])
    ttr, tva = dtr["time_s"].to_numpy(float), dva["time_s"].to_numpy(float)
    res = {"channels": {}, "pass": True}
    for ch, tch in truth["channels"].items():
        f = []
        ytr = dtr[f"gyro_{ch}"].to_numpy(float)
        yva = dva[f"gyro_{ch}"].to_numpy(float)
        oktr, okva0 = np.isfinite(ytr), np.isfinite(yva)
        Xtr, in_tr = declared(model, dtr, tch["probe"])
        Xva, in_va = declared(model, dva, tch["probe"])
        inr = np.ones(len(yva), bool)
        for a, b in zip(in_tr, in_va):
            inr &= (b >= a[oktr].min()) & (b <= a[oktr].max())
        okva = okva0 & inr
        ytr0, yva0 = np.where(oktr, ytr, 0.0), np.where(okva0, yva, 0.0)
        before, nb = fit_eval(Xtr, ytr0, oktr, Xva, yva0, okva, tva, per_block)
        Otr = np.column_stack([Xtr, case["oracle_cols"]["train"][ch]])
        Ova = np.column_stack([Xva, case["oracle_cols"]["validate"][ch]])
        oracle, _ = fit_eval(Otr, ytr0, oktr, Ova, yva0, okva, tva, per_block)
        c = get_channel(rep, ch) if rep is not None else None
        row = {"type": tch["type"], "truth": [desc_truth(e) for e in tch["effects"]],
               "own_before": before, "oracle": oracle, "blocks": nb,
               "in_range_frac": float(okva.sum() / max(1, okva0.sum()))}
        if c is None:
            f.append("channel missing from report")
            row.update(failures=f, pass_=False)
            res["channels"][ch] = row
            res["pass"] = False
            continue
        verdict = c.get("verdict")
        pb = (c.get("before") or {}).get("validation_std100_dph")
        pa = (c.get("after") or {}).get("validation_std100_dph")
        floor = c.get("noise_floor_dph")
        added = c.get("effects_added") or []
        row.update(verdict=verdict, before=pb, after=pa, floor=floor,
                   added=[desc_added(a) for a in added])
        notes = []
        if pb is not None and before == before and abs(pb - before) > 0.05 * max(before, 1e-12):
            notes.append(f"before differs from own {before:.4f}")
        # kinds
        if tch["type"] == "complete":
            if added:
                f.append("added effects on a complete channel")
        elif tch["type"] == "library":
            for e in tch["effects"]:
                if not any(added_matches(e, a) for a in added):
                    f.append(f"missed {desc_truth(e)}")
            for a in added:
                if not any(added_matches(e, a) for e in tch["effects"]):
                    f.append(f"extra {desc_added(a)}")
        # verdict
        if tch["type"] == "complete":
            if verdict != "no_effect_missing":
                f.append(f"verdict {verdict} (want no_effect_missing)")
        elif tch["type"] == "library":
            if verdict == "partly_explained":
                if not (floor is not None and oracle > 1.2 * floor):
                    f.append("verdict partly_explained but oracle <= 1.2x floor")
            elif verdict != "explained":
                f.append(f"verdict {verdict} (want explained)")
        else:
            if verdict != "unexplained_structure_remains":
                f.append(f"verdict {verdict} (want unexplained_structure_remains)")
        # error
        if pa is None or pb is None:
            f.append("before/after missing")
        else:
            if pa > pb * (1 + 1e-9) + 1e-12:
                f.append(f"after {pa:.4f} > before {pb:.4f}")
            if tch["type"] == "library" and oracle == oracle and pa > 1.15 * oracle:
                f.append(f"after {pa:.4f} > 1.15x oracle {oracle:.4f}")
        row.update(failures=f, notes=notes, pass_=not f)
        res["channels"][ch] = row
        if f:
            res["pass"] = False
    return res


def fmt(x):
    return "-" if x is None or x != x else f"{x:.4f}"


def run_product(train, val, model, out):
    env = dict(os.environ, PYTHONPATH=ROOT)
    t0 = time.time()
    p = subprocess.run([PY, "-m", "bench", "close-loop", train, val, "--model", model, "--json", out],
                       cwd=ROOT, env=env, capture_output=True, text=True)
    return p, time.time() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--classes", default="")
    ap.add_argument("--json")
    ap.add_argument("--keep")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    classes = [c for c in a.classes.split(",") if c] or CLASSES
    for c in classes:
        if c not in CLASSES:
            ap.error(f"unknown class {c}; known: {','.join(CLASSES)}")
    tmp = tempfile.TemporaryDirectory(prefix="referee6-")
    results = []
    tab = defaultdict(lambda: [0, 0, 0, 0])   # cases pass, cases, channels pass, channels
    for seed in range(a.first_seed, a.first_seed + a.seeds):
        for cls in classes:
            t0 = time.time()
            case = build_case(cls, seed)
            tg = time.time() - t0
            d = os.path.join(a.keep, f"{cls}-{seed}") if a.keep else os.path.join(tmp.name, f"{cls}-{seed}")
            os.makedirs(d, exist_ok=True)
            tr, va, out = (os.path.join(d, n) for n in ("train.csv", "validate.csv", "report.json"))
            with open(tr, "w") as fh:
                fh.write(case["train_csv"])
            with open(va, "w") as fh:
                fh.write(case["validate_csv"])
            if a.keep:
                with open(os.path.join(d, "truth.json"), "w") as fh:
                    json.dump(case["truth"], fh, indent=1)
            p, tp = run_product(tr, va, case["model"], out)
            rep = None
            err = None
            if p.returncode != 0 or not os.path.exists(out):
                err = f"product exit {p.returncode}: {(p.stderr or p.stdout).strip()[-400:]}"
            else:
                with open(out) as fh:
                    rep = json.load(fh)
            sc = score_case(case, rep)
            if err:
                sc["pass"] = False
                sc["error"] = err
            ok = sc["pass"]
            parts = []
            for ch, r in sc["channels"].items():
                parts.append(
                    f"{ch}[{r['type']} truth={','.join(r['truth']) or '-'} added={','.join(r.get('added', [])) or '-'}"
                    f" v={r.get('verdict')} before={fmt(r.get('before'))}(own {fmt(r['own_before'])})"
                    f" after={fmt(r.get('after'))} oracle={fmt(r['oracle'])} floor={fmt(r.get('floor'))}"
                    + (f" FAIL: {'; '.join(r['failures'])}" if r.get("failures") else "")
                    + (f" note: {'; '.join(r['notes'])}" if r.get("notes") else "") + "]")
            line = (f"{'PASS' if ok else 'FAIL'} {cls}-{seed} model='{case['model']}' "
                    f"P={case['truth']['sample_period_s']:g} val={case['truth']['validate_kind']} "
                    + " ".join(parts) + (f" ERROR {err}" if err else ""))
            if a.verbose:
                line += f" (gen {tg:.1f}s, product {tp:.1f}s)"
            print(line, flush=True)
            t = tab[cls]
            t[0] += ok
            t[1] += 1
            for r in sc["channels"].values():
                t[2] += bool(r.get("pass_"))
                t[3] += 1
            results.append({"class": cls, "seed": seed, "pass": ok, "truth": case["truth"],
                            "score": sc})
    print(f"{'class':18s} {'cases':>8s} {'channels':>9s}")
    tot = [0, 0, 0, 0]
    for cls in classes:
        if cls in tab:
            t = tab[cls]
            print(f"{cls:18s} {t[0]:>3d}/{t[1]:<4d} {t[2]:>3d}/{t[3]:<4d}")
            tot = [x + y for x, y in zip(tot, t)]
    print(f"{'all':18s} {tot[0]:>3d}/{tot[1]:<4d} {tot[2]:>3d}/{tot[3]:<4d}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh, indent=1, default=float)
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
