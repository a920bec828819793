"""Score close-the-loop on held-out cases like an outside referee.

    python -m tests.heldout.score --seeds 5 [--first-seed 1] [--classes A,B] [--json out.json]

Each case's TRAIN and VALIDATE runs go through the product's CSV reader and the function that
``bench close-loop`` calls, on the target channel.  A channel passes when:

* kinds: the effects kept ("effects_added") are exactly the hidden library effects, each with its
  kind and probe(s) (a relay and a gradual hysteresis are told apart by the effect's ``form``);
* verdict: the verdict is one the issue's rules allow for the truth (``Case.honest_verdicts``);
* error: the in-range validation std of 100-s means after is at most 1.15x that of the oracle
  (declared model + the true effects in their true form, least squares on TRAIN) and not above
  before.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from tests.heldout import physics as ph
from tests.heldout.cases import CLASSES, Case, declared_design, _fill, in_range, make_case, reference_errors, std100

ERROR_RATIO_MAX = 1.15
LOOKALIKE_FLOOR_SHARE = 0.5
_PROBE = re.compile(r"^t\d+$")


def _probes_of(params: dict) -> tuple[str, ...]:
    """Every probe name an effect's parameters mention (probe, pair, probes ...), sorted."""
    found: set[str] = set()
    for value in params.values():
        items = value if isinstance(value, (list, tuple)) else [value]
        for v in items:
            if isinstance(v, str):
                found.update(p for p in re.split(r"[^A-Za-z0-9_]+", v) if _PROBE.match(p))
    return tuple(sorted(found))


def product_label(effect: dict) -> str:
    """The product's effect in the referee's vocabulary: kind(probes)."""
    kind = effect.get("kind", "?")
    params = effect.get("params") or {}
    if kind == "hysteresis" and params.get("form") == "gradual":
        kind = "gradual_hysteresis"
    probes = _probes_of(params)
    return f"{kind}({'-'.join(probes)})" if probes else kind


def truth_label(effect) -> str:
    probes = tuple(sorted(effect.probes))
    return f"{effect.kind}({'-'.join(probes)})" if probes else effect.kind


def _lag_irregular(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    y = np.empty(len(x))
    acc = float(x[0])
    a = np.exp(-np.diff(t, prepend=t[0]) / tau).tolist()
    for i, (v, ai) in enumerate(zip(x.tolist(), a)):
        acc = ai * acc + (1 - ai) * v
        y[i] = acc
    return y


def my_regressor(effect: dict, run) -> np.ndarray | None:
    """The referee's own version of an effect the product named (its kind, probes and parameters), on
    a run's kept rows; None when the referee has no such physics."""
    kind, params = effect.get("kind"), effect.get("params") or {}
    probes = _probes_of(params)
    tr = run.truth
    try:
        if kind == "thermal_lag" and probes:
            return _lag_irregular(run.t, tr[probes[0]], float(params.get("tau_s", 600.0)))
        if kind == "gradient" and len(probes) == 2:
            return tr[probes[0]] - tr[probes[1]]
        if kind == "rate" and probes:
            return np.gradient(_lag_irregular(run.t, tr[probes[0]], 30.0), run.t) * 60.0
        if kind == "hysteresis" and probes and "width_c" in params:
            mem = ph.duhem if params.get("form") == "gradual" else ph.relay
            return mem(tr[probes[0]], float(params["width_c"]))
        if kind == "warmup":
            return np.exp(-run.t / float(params.get("tau_s", 600.0)))
    except (KeyError, ValueError):
        return None
    return None


def lookalike_error(case: Case, added: list[dict]) -> float | None:
    """How well the product's named effects (the referee's version of them) reproduce the hidden
    library signal: std of 100-s means of what is left of it on the in-range validation run, after a
    TRAIN least-squares fit with the declared model, as a share of the noise there.  None when a
    named effect is outside the referee's physics."""
    own = case.channel_probes[case.channel]
    cols = {"train": [declared_design(_fill(case.train.readings[own]))],
            "validate": [declared_design(_fill(case.validate.readings[own]))]}
    for e in added:
        for which, run in (("train", case.train), ("validate", case.validate)):
            r = my_regressor(e, run)
            if r is None:
                return None
            cols[which].append(r[:, None])
    hidden = {w: sum((e.gain * e.rows[w] for e in case.library_effects), np.zeros(len(r.t)))
              for w, r in (("train", case.train), ("validate", case.validate))}
    a_tr, a_va = np.hstack(cols["train"]), np.hstack(cols["validate"])
    b, *_ = np.linalg.lstsq(a_tr, hidden["train"], rcond=None)
    left = hidden["validate"] - a_va @ b
    ok = in_range(case)
    noise = std100(case.validate.t, case.validate.noise[case.channel], ok, case.validate.dt)
    return std100(case.validate.t, left, ok, case.validate.dt) / noise


def run_product(case: Case) -> dict:
    """The product's close-the-loop report for the case's target channel (public JSON form)."""
    from bench.fit.closeloop import close_loop, public
    from bench.fit.csvio import parse_csv_text

    train = parse_csv_text(case.train_csv, source=f"{case.name}/train.csv")
    validate = parse_csv_text(case.validate_csv, source=f"{case.name}/validate.csv")
    report = public(close_loop(train, validate, case.declared, channels=[case.channel]))
    return report["channels"][case.channel]


def judge(case: Case, result: dict | None, error: str | None = None) -> dict:
    ref = reference_errors(case)
    out = {"case": case.name, "class": case.cls, "seed": case.seed, "channel": case.channel,
           "channel_probes": case.channel_probes,
           "truth": [truth_label(e) for e in case.effects],
           "truth_params": {truth_label(e): {k: round(v, 3) for k, v in e.params.items()} for e in case.effects},
           "honest_verdicts": sorted(case.honest_verdicts()),
           "oracle_std100_dph": ref["oracle"], "referee_before_std100_dph": ref["before"],
           "noise_std100_dph": ref["noise"], "referee_coverage": ref["coverage"],
           "sample_period_s": case.train.dt, "reasons": []}
    if result is None:
        out.update(passed=False, reasons=[f"error: {error}"])
        return out
    added = [product_label(e) for e in result.get("effects_added", [])]
    not_gen = [product_label(e) for e in result.get("effects_not_generalised", [])]
    before = result["before"]["validation_std100_dph"]
    after = result["after"]["validation_std100_dph"]
    out.update(verdict=result.get("verdict"), added=added, not_generalised=not_gen,
               before_std100_dph=before, after_std100_dph=after,
               noise_floor_dph=result.get("noise_floor_dph"),
               coverage=result["after"].get("validation_coverage"))
    want = sorted(truth_label(e) for e in case.library_effects)
    out["kinds_strict"] = sorted(added) == want
    share = None
    if not out["kinds_strict"] and case.library_effects and added:
        share = lookalike_error(case, result.get("effects_added", []))
        out["lookalike_share_of_noise"] = share
    if share is not None and share <= LOOKALIKE_FLOOR_SHARE:
        out["lookalike"] = (f"named {', '.join(sorted(added))} for {', '.join(want)}: reproduces the hidden "
                            f"signal within {share:.2f} of the noise (look-alike, accepted)")
    elif sorted(added) != want:
        missing = sorted(set(want) - set(added))
        extra = sorted(set(added) - set(want))
        out["reasons"].append("kinds: " + "; ".join(
            ([f"missed {', '.join(missing)}"] if missing else []) + ([f"added {', '.join(extra)}"] if extra else [])))
    if out["verdict"] not in case.honest_verdicts():
        out["reasons"].append(f"verdict: {out['verdict']} (honest: {' or '.join(sorted(case.honest_verdicts()))})")
    ratio = after / ref["oracle"] if ref["oracle"] > 0 else float("inf")
    out["after_to_oracle"] = ratio
    if ratio > ERROR_RATIO_MAX:
        out["reasons"].append(f"error: after {after:.4g} = {ratio:.2f}x the oracle {ref['oracle']:.4g} deg/h")
    if after > before * (1 + 1e-9):
        out["reasons"].append(f"error: after {after:.4g} worse than before {before:.4g} deg/h")
    out["passed"] = not out["reasons"]
    return out


def score_case(cls: str, seed: int) -> dict:
    case = make_case(cls, seed)
    t0 = time.process_time()
    try:
        result, error = run_product(case), None
    except Exception as exc:        # the referee records a crash as a miss with its message
        result, error = None, f"{type(exc).__name__}: {exc}"
    out = judge(case, result, error)
    out["cpu_s"] = time.process_time() - t0
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default=",".join(CLASSES))
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    unknown = [c for c in classes if c not in CLASSES]
    if unknown:
        ap.error(f"unknown class(es) {', '.join(unknown)} (known: {', '.join(CLASSES)})")
    results = []
    by_class: dict[str, list[dict]] = defaultdict(list)
    for cls in classes:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = score_case(cls, seed)
            results.append(r)
            by_class[cls].append(r)
            if args.verbose or not r["passed"]:
                print(f"  {r['case']} [{r['channel']}] truth {r['truth'] or 'none'}; product "
                      f"{r.get('verdict')} {r.get('added')}; after/oracle {r.get('after_to_oracle', float('nan')):.2f}"
                      f"{'; ' + ' | '.join(r['reasons']) if r['reasons'] else ''}"
                      f"{'; ' + r['lookalike'] if r.get('lookalike') else ''} ({r['cpu_s']:.1f} s CPU)",
                      file=sys.stderr, flush=True)
    print(f"{'case class':28s} passed  reasons")
    total = 0
    for cls in classes:
        rs = by_class[cls]
        ok = sum(r["passed"] for r in rs)
        total += ok
        counts: dict[str, int] = defaultdict(int)
        for r in rs:
            for reason in {x.split(":")[0] for x in r["reasons"]}:
                counts[reason] += 1
        looks = sum(bool(r.get("lookalike")) for r in rs)
        print(f"{cls:28s} {ok}/{len(rs)}    {', '.join(f'{k} {v}' for k, v in sorted(counts.items())) or '-'}"
              f"{f' (look-alike names accepted: {looks})' if looks else ''}")
    print(f"{'all':28s} {total}/{len(results)}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
