"""Score the product's close-the-loop on the referee corpus.

    python -m tests.corpus.score [--seeds N] [--first-seed S] [--classes A,B] [--json out.json]

Prints one row per case class (seeds passed / total, failure reasons) and a summary line.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import asdict

from tests.corpus.cases import CLASSES, make_case
from tests.corpus.referee import score_case


def _reason_tag(reason: str) -> str:
    return reason.split(":", 1)[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.corpus.score", description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds per case class (default 5)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="", help="comma-separated case classes (default: all)")
    ap.add_argument("--json", default="", help="write every channel score to this JSON file")
    ap.add_argument("--verbose", action="store_true", help="print each failing case's reasons")
    args = ap.parse_args(argv)
    names = [c for c in args.classes.split(",") if c] or list(CLASSES)
    unknown = [c for c in names if c not in CLASSES]
    if unknown:
        ap.error(f"unknown case class(es): {', '.join(unknown)} (have: {', '.join(CLASSES)})")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    rows, scores = [], []
    t0 = time.perf_counter()
    width = max(len(n) for n in names)
    print(f"{'case class':<{width}}  passed  failure reasons")
    for name in names:
        passed, total, tags = 0, 0, Counter()
        for seed in seeds:
            for s in score_case(make_case(name, seed)):
                scores.append(s)
                total += 1
                passed += s.passed
                tags.update(_reason_tag(r) for r in s.reasons)
                if args.verbose and not s.passed:
                    print(f"    seed {seed} {s.channel}: " + "; ".join(s.reasons), flush=True)
        reasons = ", ".join(f"{k} x{v}" for k, v in sorted(tags.items())) or "-"
        rows.append({"case_class": name, "passed": passed, "total": total, "reasons": dict(tags)})
        print(f"{name:<{width}}  {passed:>2}/{total:<3}  {reasons}", flush=True)
    n_pass = sum(r["passed"] for r in rows)
    n_all = sum(r["total"] for r in rows)
    classes_ok = sum(r["passed"] == r["total"] for r in rows)
    elapsed = time.perf_counter() - t0
    print(f"summary: {n_pass}/{n_all} case-runs passed; {classes_ok}/{len(rows)} classes fully passed; "
          f"{len(seeds)} seeds per class; {elapsed:.0f} s")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"classes": rows, "scores": [asdict(s) for s in scores],
                       "summary": {"passed": n_pass, "total": n_all, "classes_fully_passed": classes_ok,
                                   "classes": len(rows), "seeds": list(seeds)}}, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
