"""Benchmark: close-the-loop analysis on a day of 1-s data (86,400 samples per run, one channel, four
probes, two hidden effects).  Prints the wall and CPU time of the analysis (no HTML) and the wall time of the HTML report.

    python -m tests.perf.closeloop            # the target: a day at 1 s
    python -m tests.perf.closeloop --dt 0.1   # the same day logged at 10 Hz (864,000 samples per run)
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench.fit.closeloop import close_loop, public
from bench.fit.closeloop_report import render_close_loop_report
from tests import synth


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dt", type=float, default=1.0, help="sample period of both runs, s (default 1)")
    dt = ap.parse_args(argv).dt
    if not dt > 0:
        raise SystemExit(f"--dt must be a positive number of seconds, got {dt}")
    day = [("hold", 3600), ("ramp", 60, 1.0), ("hold", 14400), ("ramp", -20, 0.5), ("hold", 14400),
           ("ramp", 45, 2.0), ("hold", 14400), ("ramp", 0, 1.0), ("hold", 14400), ("ramp", 30, 0.25)]
    hidden = {"gradient": 0.06, "rate": 0.08}
    train, _ = synth.make_run(day, hidden, seed=1, dt=dt)
    validate, _ = synth.make_run(synth.VALIDATE_PROFILE * 2, hidden, seed=2, dt=dt)
    print(f"train: {len(train)} samples ({(train.time[-1] - train.time[0]) / 3600:.1f} h at {dt:g} s); "
          f"validation: {len(validate)} samples")
    t0, c0 = time.perf_counter(), time.process_time()
    report = close_loop(train, validate, "static", channels=["x"], bin_c=None)
    t1, c1 = time.perf_counter(), time.process_time()
    ch = public(report)["channels"]["x"]
    print(f"close-loop analysis: {t1 - t0:.2f} s wall, {c1 - c0:.2f} s CPU (all threads); verdict {ch['verdict']}; added "
          f"{[e['kind'] for e in ch['effects_added']]}; validation std100 "
          f"{ch['before']['validation_std100_dph']:.4f} -> {ch['after']['validation_std100_dph']:.4f} deg/h")
    page = render_close_loop_report(report, train, validate)
    t2 = time.perf_counter()
    print(f"HTML report: {t2 - t1:.2f} s wall ({len(page) / 1e6:.1f} MB)")
    assert np.isfinite(ch["after"]["validation_std100_dph"])


if __name__ == "__main__":
    main()
