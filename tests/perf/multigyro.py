"""Benchmarks: several gyros in one chamber (issue 16).

``python -m tests.perf.multigyro realtime [--gyros 8] [--rate 1000] [--minutes 10] [--db URL]``
    ``--gyros`` simulated gyros, each streaming KVH Format A at ``--rate`` Hz on its own TCP line, in
    real time (the lockstep clock paced at x1), one engine recording all of them into one multi-gyro
    run for ``--minutes`` (gyro power on, one ``record`` step).  Prints, per unit, the frames stored
    against the frames the simulator produced (``0 lost`` is the target) and the gaps; the pace held
    (bench seconds per wall second: 1.00 means the host kept up; a slower host slows the lockstep
    clock instead of dropping frames) and the CPU used by this process (user + system) over the wall
    time, as a share of the machine's cores (headroom = the rest).  Exit 1 when a frame was lost or
    the pace fell below 0.98.

``python -m tests.perf.multigyro campaign [--gyros 8] [--param k=v ...] [--budget-s 300] [--db URL]``
    The default ``eight_position`` campaign (S000) with ``--gyros`` gyros in one chamber, in lockstep
    bench time at ``--speed max`` through ``bench run ... --gyro G1 ... --sim``; prints the wall time,
    bench hours, frames per unit and the parent run's sampling summary; exit 1 over ``--budget-s`` or
    when a unit did not complete.  ``--param`` shortens the procedure (say so when reporting).

Both print the load average at the start and the end (the machine is shared).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _expected_frames(db, run_id: int, rate: float) -> int:
    """Frames a gap-free line delivers between a run's first and last stored frame."""
    from sqlalchemy import func, select

    from bench.storage.models import FrameChunk

    with db.session() as s:
        first, last = s.execute(select(func.min(FrameChunk.t_first), func.max(FrameChunk.t_last))
                                .where(FrameChunk.run_id == run_id)).one()
    return 0 if first is None else int(round((last - first) * rate)) + 1


def realtime(args: argparse.Namespace) -> int:
    from bench.engine import Engine
    from bench.engine.factory import build_devices, close_devices, engine_config_for
    from bench.engine.sqlstore import SqlRunStore, new_run, run_report
    from bench.engine.steps import GyroPower, Plan, Record
    from bench.sim.bench import lockstep_clock
    from bench.sim.multibench import MultiGyroBench
    from bench.storage import open_database

    tmp = Path(tempfile.mkdtemp(prefix="multigyro-rt-"))
    db = open_database(args.db or f"sqlite:///{tmp / 'rt.sqlite'}")
    clock = lockstep_clock(1.0, args.seed)
    bench = MultiGyroBench(units=args.gyros, clock=clock, seed=args.seed, data_rate_hz=args.rate).start()
    cfg = bench.bench_config()
    plan = Plan(name="realtime", steps=[GyroPower(on=True), Record(duration_s=args.minutes * 60.0, labels={"phase": "realtime"}),
                                        GyroPower(on=False)], params={})
    run_id = new_run(db, procedure="realtime", parameters={}, config_snapshot=cfg.model_dump(mode="json"),
                     gyro_id=None, bench_name=cfg.name,
                     units=cfg.assign_gyros([f"RT-{k + 1}" for k in range(args.gyros)]))
    store = SqlRunStore(db, geometry=cfg.turntable.geometry)
    devices = build_devices(cfg, clock)
    engine = Engine(devices, store, clock, cfg, engine_config=engine_config_for(clock))
    print(f"{args.gyros} gyros x {args.rate} Hz KVH Format A, {args.minutes:g} min at x1; "
          f"load average at start {_load()}; {os.cpu_count()} cores", flush=True)
    samples: list[tuple[float, float]] = []          # (wall, bench) every 0.5 s: the pace while recording
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.5):
            samples.append((time.monotonic(), clock.now()))

    sampler = threading.Thread(target=sample, daemon=True)
    cpu0, wall0, bench0 = os.times(), time.monotonic(), clock.now()
    sampler.start()
    try:
        status = engine.run(str(run_id), plan)
    finally:
        stop.set()
        store.close(run_id)
        wall = time.monotonic() - wall0
        cpu1 = os.times()
        bench_s = clock.now() - bench0
        overruns = {u.slot: u.gyro.overrun_frames for u in bench.units}
        close_devices(devices)
        bench.stop()
    cpu = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    report = run_report(db, run_id)
    lost = 0
    # the pace of the recording itself: from its first bench second to its last (start-up and the
    # end's safe state are not real-time work)
    rec = [(w, b) for w, b in samples if bench0 + 2.0 <= b <= bench0 + args.minutes * 60.0 - 1.0]
    pace = (rec[-1][1] - rec[0][1]) / (rec[-1][0] - rec[0][0]) if len(rec) > 2 else float("nan")
    print(f"run {run_id}: {status}; wall {wall:.1f} s for {bench_s:.1f} bench s in all; while recording "
          f"{rec[-1][1] - rec[0][1] if len(rec) > 2 else 0:.0f} bench s at pace x{pace:.3f} of the wall")
    for u in report["units"]:
        missing = sum(g.get("frames_missing") or 0 for g in u["gaps"])
        expected = _expected_frames(db, u["run_id"], args.rate)
        short = expected - u["frames"]
        lost += missing + overruns[u["slot"]] + max(0, short)
        print(f"  {u['slot']} {u['gyro_id']}: {u['status']}, {u['frames']} frames stored of {expected} over their "
              f"span at {args.rate} Hz, {len(u['gaps'])} gaps ({missing} frames missing), simulator overruns "
              f"{overruns[u['slot']]}")
    costs = sorted(clock.wall_cost_s.items(), key=lambda kv: -kv[1])
    print("wall seconds the lockstep clock spent serving / receiving, by participant: "
          + ", ".join(f"{name} {cost:.1f}" for name, cost in costs[:6]))
    cores = os.cpu_count() or 1
    share = cpu / (wall * cores)
    need = cpu / bench_s / cores            # of the machine, to run this at x1 with nothing else on it
    print(f"CPU of this process (simulators + engine + database writers): {cpu:.1f} s user + system over "
          f"{wall:.1f} s wall = {100 * share:.0f} % of {cores} cores; per bench second {cpu / bench_s:.3f} CPU s, "
          f"i.e. real time needs {100 * need:.0f} % of the {cores} cores (headroom {100 * (1 - need):.0f} %); "
          f"load average at end {_load()}")
    db.dispose()
    ok = status == "completed" and lost == 0 and pace >= 0.98
    return 0 if ok else 1


def campaign(args: argparse.Namespace) -> int:
    from bench.engine.sqlstore import run_report
    from bench.storage import open_database, queries

    tmp = Path(tempfile.mkdtemp(prefix="multigyro-campaign-"))
    url = args.db or f"sqlite:///{tmp / 'campaign.sqlite'}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    py = [sys.executable, "-m", "bench.cli"]
    run_args = py + ["run", "eight_position", "--json", "--no-progress", "--db", url, "--sim", "--speed", "max",
                     "--seed", str(args.seed)]
    for k in range(args.gyros):
        run_args += ["--gyro", f"CAMP-{k + 1}"]
    for p in args.param:
        run_args += ["--param", p]
    print(f"{args.gyros}-gyro eight_position campaign, --speed max{', params ' + ' '.join(args.param) if args.param else ''}; "
          f"load average at start {_load()}", flush=True)
    t0 = time.monotonic()
    done = subprocess.run(run_args, env=env, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if not done.stdout.strip():
        print(done.stderr[-3000:], file=sys.stderr)
        return 1
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    show = json.loads(subprocess.run(py + ["runs", "show", str(doc["run_id"]), "--json", "--db", url], env=env,
                                     capture_output=True, text=True, check=True).stdout)
    sampling = show["sampling"]
    units = doc["units"]
    db = open_database(url)
    try:
        unit_reports = [run_report(db, u["run_id"]) for u in units]
        with db.session() as s:
            live = queries.get_run(s, doc["run_id"]).live or {}
        t_span = float(live.get("status_t", 0.0)) - float(live.get("started_t", 0.0))
    finally:
        db.dispose()
    print(f"run {doc['run_id']}: {doc['status']} ({doc['outcome']}); wall {wall:.1f} s for {t_span / 3600:.2f} h "
          f"of bench time (x{t_span / wall:.0f}); load average at end {_load()}")
    for u, r in zip(units, unit_reports):
        g = r["sampling"].get("gyro") or {}
        print(f"  {u['slot']} {u['gyro_id']}: {u['status']}, {u['frames']} frames, {len(u['gaps'])} gaps; gyro every "
              f"{g.get('median_interval_s')} s (max {g.get('max_interval_s')}); probes every "
              f"{(r['sampling'].get('probes') or {}).get('median_interval_s')} s")
    print("parent sampling: " + ", ".join(f"{k} {v['readings']} every {v['median_interval_s']} s (max {v['max_interval_s']})"
                                          for k, v in sampling.items() if v and k != "units"))
    ok = doc["status"] == "completed" and all(u["status"] == "completed" for u in units) and wall <= args.budget_s
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    rt = sub.add_parser("realtime")
    rt.add_argument("--gyros", type=int, default=8)
    rt.add_argument("--rate", type=int, default=1000)
    rt.add_argument("--minutes", type=float, default=10.0)
    rt.add_argument("--seed", type=int, default=1)
    rt.add_argument("--db", default=None)
    cp = sub.add_parser("campaign")
    cp.add_argument("--gyros", type=int, default=8)
    cp.add_argument("--seed", type=int, default=1)
    cp.add_argument("--param", action="append", default=[])
    cp.add_argument("--budget-s", type=float, default=300.0)
    cp.add_argument("--db", default=None)
    args = ap.parse_args(argv)
    return realtime(args) if args.what == "realtime" else campaign(args)


if __name__ == "__main__":
    raise SystemExit(main())
