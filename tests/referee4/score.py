"""Score ``bench close-loop`` on the fourth referee's cases, through the CLI and its JSON only.

    python -m tests.referee4.score --seeds 5 --first-seed 1 [--classes a,b] [--json out.json] [--verbose]

Per channel (truth: complete, library effect(s), or a driver no column records):

* kinds: the effect families added (and their probes) are exactly the true ones; nothing is added
  to a complete channel or to one whose driver is unrecorded;
* verdict: complete -> ``no_effect_missing``; library -> ``explained`` (``partly_explained`` is
  accepted only when even the oracle stays above 1.2x the product's reported floor); unrecorded ->
  ``unexplained_structure_remains``;
* error: ``after`` <= ``before`` (the product's own numbers) and, for library effects, ``after`` <=
  1.15x the oracle (declared terms + the true effects in their true form, least squares on TRAIN).

The referee's own "before" is printed next to the product's; a difference over 5 % is flagged.
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
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tests.referee4.cases import CLASSES, Case, build_case
from tests.referee4.effects import FAMILY, probes_of
from tests.referee4.generator import CHANNELS
from tests.referee4.oracle import channel_score

ORACLE_TOLERANCE = 1.15
PARTLY_FLOOR_RATIO = 1.2
BEFORE_MATCH = 0.05
REPO_ROOT = Path(__file__).resolve().parents[2]


def product_family(kind: str) -> str:
    """The truth family a product effect kind belongs to (by its name)."""
    k = kind.lower()
    if "hyster" in k or "relay" in k or "duhem" in k:
        return "hysteresis"
    if "lag" in k:
        return "lag"
    if "gradient" in k:
        return "gradient"
    if "warm" in k:
        return "warmup"
    if "drift" in k or "time" in k:
        return "drift"
    if ("temp" in k and "rate" in k) or "cross" in k:
        return "temp_rate"
    if "rate" in k or "dtdt" in k or "derivative" in k:
        return "rate_squared" if ("squar" in k or "^2" in k) else "rate"
    return k


_PROBE = re.compile(r"\bt\d+\b")


def product_probes(params: dict) -> tuple[str, ...]:
    """Probe names found in an effect's params (``probe: t2``, ``probes: t3-t4``, a list)."""
    found = []
    for v in params.values():
        items = v if isinstance(v, (list, tuple)) else [v]
        for x in items:
            if isinstance(x, str):
                found += _PROBE.findall(x)
    return tuple(found)


def run_product(case: Case, workdir: Path, timeout_s: float = 1800.0) -> tuple[dict, float]:
    """Run ``bench close-loop`` on the case's CSVs; returns (report JSON, CPU seconds of the child)."""
    paths = {}
    for k, text in case.texts.items():
        paths[k] = workdir / f"{k}.csv"
        paths[k].write_text(text)
    out = workdir / "close-loop.json"
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    before = os.times()
    proc = subprocess.run([sys.executable, "-m", "bench", "close-loop", str(paths["train"]),
                           str(paths["validate"]), "--model", case.model, "--json", str(out)],
                          cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout_s)
    after = os.times()
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    if proc.returncode != 0:
        raise RuntimeError(f"bench close-loop failed ({proc.returncode}) on {case.cls} seed {case.seed}:\n"
                           f"{proc.stderr[-2000:]}")
    return json.loads(out.read_text()), cpu


@dataclass
class ChannelResult:
    channel: str
    truth: str                      # complete | library | unrecorded
    expected: list[str]
    added: list[str]
    verdict: str
    before: float | None
    after: float | None
    floor: float
    oracle: float
    referee_before: float
    in_range_blocks: int = 0
    blocks: int = 0
    failures: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures


def _label(family: str, probes: tuple[str, ...]) -> str:
    return f"{family}({','.join(probes)})" if probes else family


def score_channel(case: Case, ch: str, report: dict) -> ChannelResult:
    tr = case.truth[ch]
    pc = report["channels"][ch]
    truth = "unrecorded" if tr["unrecorded"] else ("library" if tr["effects"] else "complete")
    expected = [(FAMILY[e["kind"]], tuple(sorted(probes_of(e["kind"], e["params"])))) for e in tr["effects"]]
    added = [(product_family(e["kind"]), tuple(sorted(product_probes(e.get("params", {})))))
             for e in pc.get("effects_added", [])]
    ref = channel_score(case, ch)
    res = ChannelResult(channel=ch, truth=truth, expected=[_label(*e) for e in expected],
                        added=[_label(*a) for a in added], verdict=pc["verdict"],
                        before=pc["before"]["validation_std100_dph"], after=pc["after"]["validation_std100_dph"],
                        floor=pc["noise_floor_dph"], oracle=ref.oracle_std100, referee_before=ref.before_std100,
                        in_range_blocks=ref.in_range_blocks, blocks=ref.blocks)
    if truth == "unrecorded":
        res.expected = [f"unrecorded:{tr['unrecorded']['kind']}"]
    # kinds (and probes), as sets: one physical hysteresis fitted as two operators on its own probe
    # is the right attribution; the same family on another probe is not
    if {f for f, _ in added} != {f for f, _ in expected}:
        res.failures.append(f"kinds {res.added or 'none'} != {res.expected if truth == 'library' else 'none'}")
    elif {a for a in added if a[1]} != {e for e in expected if e[1]}:
        res.failures.append(f"probes: added {res.added}, true {res.expected}")
    # verdict
    if truth == "complete" and res.verdict != "no_effect_missing":
        res.failures.append(f"verdict {res.verdict} (complete)")
    elif truth == "unrecorded" and res.verdict != "unexplained_structure_remains":
        res.failures.append(f"verdict {res.verdict} (unrecorded driver)")
    elif truth == "library" and res.verdict != "explained":
        floor = res.floor or float("nan")
        partly_ok = res.verdict == "partly_explained" and res.oracle > PARTLY_FLOOR_RATIO * floor
        if not partly_ok:
            res.failures.append(f"verdict {res.verdict} (oracle {res.oracle / floor:.2f}x floor)")
    # error
    if res.before is None or res.after is None:
        res.failures.append(f"no in-range validation std reported (before {res.before}, after {res.after})")
        return res
    if res.after > res.before * (1 + 1e-9):
        res.failures.append(f"after {res.after:.4g} > before {res.before:.4g}")
    if truth == "library" and res.after > ORACLE_TOLERANCE * res.oracle:
        res.failures.append(f"after {res.after / res.oracle:.2f}x oracle")
    if res.in_range_blocks < 10:
        res.notes.append(f"only {res.in_range_blocks} of {res.blocks} validation blocks in range")
    if abs(res.referee_before / res.before - 1) > BEFORE_MATCH:
        res.notes.append(f"before mismatch: referee {res.referee_before:.4g} vs product {res.before:.4g}")
    return res


def score_case(cls: str, seed: int, keep: Path | None = None, reuse: Path | None = None) -> dict:
    """Build the case, run the product on it (or read the report kept by an earlier run of the same
    code from ``reuse``), score every channel."""
    t0 = time.process_time()
    case = build_case(cls, seed)
    gen_cpu = time.process_time() - t0
    kept = reuse / f"{cls}-{seed}.json" if reuse is not None else None
    if kept is not None and kept.exists():
        report, prod_cpu = json.loads(kept.read_text()), 0.0
    else:
        with tempfile.TemporaryDirectory() as d:
            report, prod_cpu = run_product(case, Path(d))
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        (keep / f"{cls}-{seed}.json").write_text(json.dumps(report, indent=1))
    chans = [score_channel(case, ch, report) for ch in CHANNELS]
    return {"class": cls, "seed": seed, "ok": all(c.ok for c in chans), "logger": case.logger,
            "styles": case.styles, "gen_cpu_s": gen_cpu, "product_cpu_s": prod_cpu,
            "channels": [asdict(c) | {"ok": c.ok} for c in chans], "truth": case.truth}


def _g(x) -> str:
    return "n/a" if x is None else f"{x:.4g}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--classes", default="", help="comma-separated class names (default: all)")
    ap.add_argument("--json", default="", help="write every result here")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--keep", default="", help="keep each product report JSON in this directory")
    ap.add_argument("--reuse", default="", help="re-score the reports kept in this directory (same product "
                                                "code); cases without one are run")
    args = ap.parse_args(argv)
    classes = [c for c in args.classes.split(",") if c] or list(CLASSES)
    unknown = [c for c in classes if c not in CLASSES]
    if unknown:
        ap.error(f"unknown class(es) {unknown}; known: {', '.join(CLASSES)}")
    results = []
    for cls in classes:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = score_case(cls, seed, Path(args.keep) if args.keep else None,
                           Path(args.reuse) if args.reuse else None)
            results.append(r)
            status = "pass" if r["ok"] else "FAIL"
            print(f"{cls:34s} seed {seed:3d} {status}  ({r['logger']}, {r['styles']['train']}/"
                  f"{r['styles']['validate']}, product {r['product_cpu_s']:.1f} s CPU)", flush=True)
            for c in r["channels"]:
                if args.verbose or not c["ok"] or c["notes"]:
                    print(f"    {c['channel']}: {c['truth']:10s} true {c['expected']} added {c['added']} "
                          f"{c['verdict']}; before {_g(c['before'])} (referee {_g(c['referee_before'])}) "
                          f"after {_g(c['after'])} oracle {_g(c['oracle'])} floor {_g(c['floor'])}"
                          + "".join(f"\n        FAIL {f}" for f in c["failures"])
                          + "".join(f"\n        note {n}" for n in c["notes"]), flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    print("\nclass                               cases   channels")
    for cls in classes:
        rs = [r for r in results if r["class"] == cls]
        ch = [c for r in rs for c in r["channels"]]
        print(f"{cls:34s} {sum(r['ok'] for r in rs):2d}/{len(rs):<2d}   {sum(c['ok'] for c in ch):3d}/{len(ch)}")
    total = sum(r["ok"] for r in results)
    print(f"{'all':34s} {total}/{len(results)}   "
          f"{sum(c['ok'] for r in results for c in r['channels'])}/{sum(len(r['channels']) for r in results)}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
