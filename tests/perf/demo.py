"""``bench demo`` twice with the same seed: wall and CPU time of each (the demo process and its
children, user + system), the load average, whether the two ``close-loop.json`` are identical byte for
byte, and the story (verdict and effects per channel).

    python -m tests.perf.demo [--seed 0]

Target (issue "what the lab engineer sees"): the same story on every run, the hidden warm-up named and
explained on every channel, each demo in at most 60 s.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_demo(directory: Path, seed: int) -> tuple[float, float]:
    """(wall s, CPU s of the demo process and everything it started) of one ``bench demo``."""
    cpu0, t0 = _children_cpu_s(), time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "bench.cli", "demo", "--dir", str(directory), "--seed", str(seed)],
                          capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    if proc.returncode != 0:
        sys.exit(f"bench demo failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    if proc.stderr.strip():
        sys.exit(f"bench demo wrote to stderr (warnings?):\n{proc.stderr[-2000:]}")
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-demo-") as tmp:
        dirs = [Path(tmp) / "a", Path(tmp) / "b"]
        times = [run_demo(d, args.seed) for d in dirs]
        texts = [(d / "close-loop.json").read_bytes() for d in dirs]
        report = json.loads(texts[0])
    load_after = os.getloadavg()
    print(f"bench demo --seed {args.seed}: " + " and ".join(f"{w:.1f} s wall ({c:.1f} s CPU)" for w, c in times)
          + f" (target <= 60 s wall on 2 cores); close-loop.json identical: {texts[0] == texts[1]}")
    print(f"load average (1, 5, 15 min) before {', '.join(f'{v:.2f}' for v in load_before)}; "
          f"after {', '.join(f'{v:.2f}' for v in load_after)}; {os.cpu_count()} CPUs")
    for ch, r in report["channels"].items():
        effects = ", ".join(f"{e['kind']}({', '.join(f'{k}={v}' for k, v in e['params'].items())})"
                            for e in r["effects_added"]) or "nothing"
        print(f"  {ch}: {r['verdict']}; added {effects}; validation std of 100-s means "
              f"{r['before']['validation_std100_dph']:.4f} -> {r['after']['validation_std100_dph']:.4f} deg/h, "
              f"noise floor {r['noise_floor_dph']:.4f} deg/h")


if __name__ == "__main__":
    main()
