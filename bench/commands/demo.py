"""``bench demo``: the product end to end on the embedded default (simulated bench + SQLite file).

It starts the service exactly as ``bench serve`` does (API + a worker for a simulated bench in
lockstep bench time), then acts as a lab operator over HTTP: queues two shortened thermal-ramp runs (a
cooling ramp for modelling; another cooling ramp, from another start at another rate, as the held-out
run), watches them, fetches the fitted coefficients by gyro ID, runs close-the-loop on the pair, and
prints the numbers.
"""
from __future__ import annotations

import json
import secrets
import socket
import threading
import time
from pathlib import Path

import typer

from bench.commands.common import fail, guarded

GYRO_ID = "DEMO-RLG-001"
# the declared model: S000's dynamic model with the static cubic, each channel in its own probe t_i
# (``tc``; the bench declares x=t1, y=t2, z=t3), which is the simulated RLG's own form: its channels
# depend on t1, t2, t3 with the gradients (t1-t3), (t2-t4) and (t3-t1) = -(t1-t3)...
DECLARED = "tc + tc^2 + tc^3 + (t1-t3) + (t2-t4) + dtc"
# ...and the simulated gyro has one effect it lacks: a warm-up drift after power-on (S004), which
# close-the-loop has to find on its own.  Its time constant (minutes, like a readout settling) is
# shorter than the unit's self-heating one, so the declared rate term dtc cannot stand in for it.
POLL_S = 0.25          # the demo's status polls and its worker's idle poll (wall seconds)
WARMUP = {"tau_s": 400.0, "amplitude_dph": {"x": 0.3, "y": -0.25, "z": 0.25}}
# modelling: cool 50 -> -30 C at 1 C/min; held out: power on at 40 C, cool to -20 C at 0.5 C/min (other
# start, rate and end, inside the modelled range of temperature and rate: where the model is valid, so
# the held-out run judges the model and not an extrapolation); its longer soak lets the unit settle
# after the 70 C swing from the modelling run's cold end, so at power-on it warms only by its own heat)
TRAIN = {"start_c": 50.0, "soak_h": 2.0, "warmup_min": 30.0, "rate_c_per_min": 1.0, "end_c": -30.0,
         "final_hold_min": 120.0, "fit_models": ["dynamic", "static"]}
# the held-out run only records (no Fit step): the coefficients served by gyro ID stay the modelling run's
VALIDATE = {"start_c": 40.0, "soak_h": 4.0, "warmup_min": 30.0, "rate_c_per_min": 0.5, "end_c": -20.0,
            "final_hold_min": 120.0, "fit": False}


def register(app: typer.Typer) -> None:
    app.command("demo")(demo_command)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@guarded
def demo_command(
    directory: str = typer.Option("var/demo", "--dir", help="where the demo database and reports go"),
    speed: str = typer.Option("max", "--speed", help="simulated bench: at most this many bench seconds per wall "
                              "second, or 'max' (as fast as the host can; the data are the same)"),
    seed: int = typer.Option(0, "--seed", help="simulated bench noise seed (same seed, same demo)"),
    port: int = typer.Option(0, "--port", help="API port (0: a free one)"),
    timeout_s: float = typer.Option(600.0, "--timeout", help="give up after this many wall seconds"),
    keep: bool = typer.Option(False, "--keep", help="keep the service and dashboard up afterwards, until Ctrl-C"),
) -> None:
    """Short accelerated campaign on the simulated bench, fit, coefficients over HTTP, close-the-loop."""
    import httpx
    import uvicorn

    from api.app import create_app
    from bench.sim.bench import SimulatedBench
    from bench.storage import open_database
    from bench.worker import Worker

    out = Path(directory)
    _fresh_directory(out)
    db_url = f"sqlite:///{(out / 'bench.sqlite').resolve()}"
    db = open_database(db_url)
    token = secrets.token_urlsafe(16)
    port = port or _free_port()
    base = f"http://127.0.0.1:{port}"
    from bench.sim.scenario import Scenario

    scenario = Scenario.builtin("default").with_changes(effects={"warmup": WARMUP})
    from bench.clock import parse_speed
    from bench.sim.bench import lockstep_clock

    try:
        pace = parse_speed(speed)
    except ValueError as exc:
        fail(str(exc))
    sim = SimulatedBench(clock=lockstep_clock(pace, seed), scenario=scenario, bench_name="sim1", seed=seed).start()
    # the worker looks for the next queued run or job every POLL_S when idle (bench serve: 0.5 s), so the
    # demo's steps follow each other without waiting out a poll period each time
    worker = Worker(db, "sim1", sim.config, None, sim.clock, bench_state=sim, poll_s=POLL_S)
    server = uvicorn.Server(uvicorn.Config(create_app(db, tokens={token: "admin"}), host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, name="demo-api", daemon=True)
    deadline = time.monotonic() + timeout_s
    try:
        worker.start_thread()
        thread.start()
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                fail("the API did not start")
            time.sleep(0.05)
        typer.echo(f"service up: {base}  (simulated bench in lockstep, "
                   f"{'at most x' + format(pace, 'g') if pace else 'as fast as the host can'}, seed {seed}, "
                   f"database {db_url})")
        http = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=30.0)
        train_id = _run(http, "thermal_ramp", TRAIN, "modelling run: +50 -> -30 C at 1 C/min", deadline)
        # the coefficients served by gyro ID are the modelling run's (the held-out run does not fit)
        coeff = _ok(http.get(f"/gyros/{GYRO_ID}/coefficients", params={"model": "dynamic"}))
        typer.echo(f"\nGET {base}/gyros/{GYRO_ID}/coefficients?model=dynamic  (fitted on run {train_id})")
        for line in coefficient_lines(coeff):
            typer.echo(f"  {line}")

        val_id = _run(http, "thermal_ramp", VALIDATE, "held-out run: +40 -> -20 C at 0.5 C/min", deadline)
        after = _ok(http.get(f"/gyros/{GYRO_ID}/coefficients", params={"model": "dynamic"}))
        if _versions(after) != _versions(coeff):
            fail(f"the held-out run {val_id} changed the coefficients served for {GYRO_ID}: "
                 f"{_versions(coeff)} -> {_versions(after)}")

        typer.echo("\nclose-the-loop: queued; fitting the declared model, searching the effect library on the "
                   "modelling run, confirming on the held-out run...")
        job = _ok(http.post("/close-loop", json={"model": DECLARED, "train_run_id": train_id,
                                                 "validation_run_id": val_id}))
        report = _wait_analysis(http, f"/close-loop/{job['id']}", deadline)
        if report["status"] != "done":
            fail(f"close-the-loop failed: {report.get('error')}")
        typer.echo(f"\nclose-the-loop (declared model: {DECLARED}; trained on run {train_id}, "
                   f"validated on run {val_id}):")
        for ch, r in report["result"]["channels"].items():
            added = ", ".join(e["kind"] for e in r["effects_added"]) or "nothing"
            typer.echo(f"  {ch}: {r['verdict']}; validation std of 100-s means "
                       f"{r['before']['validation_std100_dph']:.4f} -> {r['after']['validation_std100_dph']:.4f} "
                       f"deg/h (noise floor {r['noise_floor_dph']:.4f}); added: {added}")
        html = http.get(f"/close-loop/{job['id']}/report", timeout=max(30.0, deadline - time.monotonic()))
        (out / "close-loop.json").write_text(json.dumps(report["result"], indent=2, sort_keys=True) + "\n")
        typer.echo(f"  result: {out / 'close-loop.json'}")
        if html.status_code == 200 and html.text.lstrip().startswith("<!DOCTYPE"):
            (out / "close-loop.html").write_text(html.text)
            typer.echo(f"  report: {out / 'close-loop.html'}")
        browse = (f"BENCH_DATABASE_URL={db_url} BENCH_TOKENS=admin:{token} .venv/bin/bench serve"
                  f"  -> http://127.0.0.1:8000/ui/")
        if keep:
            typer.echo(f"\nDashboard: {base}/ui/ (token admin:{token}); Ctrl-C to stop.")
            try:
                while not server.should_exit:
                    time.sleep(0.5)
            except KeyboardInterrupt:
                pass
        typer.echo(f"\nTo browse these results again:\n  {browse}")
    finally:
        server.should_exit = True
        worker.stop()
        thread.join(timeout=10)
        sim.stop()
        db.dispose()


# what a demo directory holds (the SQLite file with its journal, the analysis' JSON and HTML): the only
# files ``bench demo`` removes when it starts again in the same directory
DEMO_FILES = ("bench.sqlite", "bench.sqlite-journal", "bench.sqlite-wal", "bench.sqlite-shm", "close-loop.json",
              "close-loop.html")


def _fresh_directory(out: Path) -> None:
    """Make ``out`` an empty demo directory: the files of an earlier demo there are removed; anything else
    (``--dir`` naming a directory that holds other work) stops the demo before it deletes a thing."""
    if out.exists() and not out.is_dir():
        fail(f"--dir {out}: exists and is not a directory")
    if out.exists():
        others = sorted(p.name for p in out.iterdir() if p.name not in DEMO_FILES or not p.is_file())
        if others:
            shown = ", ".join(others[:5]) + (f" and {len(others) - 5} more" if len(others) > 5 else "")
            fail(f"--dir {out}: holds files the demo did not write ({shown}); give an empty or new directory")
        for name in DEMO_FILES:
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)


def coefficient_lines(doc: dict) -> list[str]:
    """``GET /gyros/{id}/coefficients`` as one line per model and channel, each coefficient with four
    significant digits and its unit (``B0=0.1625 deg/h, k=0.002084 deg/h/C``)."""
    lines = []
    for model in doc.get("models", [doc]):
        for ch, entry in (model.get("channels") or {}).items():
            units = entry.get("units") or {}
            terms = ", ".join(f"{k}={v:.4g}" + (f" {units[k]}" if units.get(k) else "")
                              for k, v in entry["coefficients"].items())
            lines.append(f"{model.get('model', 'dynamic')} / {ch} (probe {entry.get('probe')}): {terms}")
    return lines


def _versions(doc: dict) -> list[tuple]:
    """(model, version, runs fitted on) of each model a coefficients document serves."""
    return [(m.get("model"), m.get("version"), tuple(m.get("run_ids") or ())) for m in doc.get("models", [doc])]


def _ok(resp):
    if resp.status_code >= 400:
        fail(f"{resp.request.method} {resp.request.url.path}: HTTP {resp.status_code}: {resp.text[:500]}")
    return resp.json()


def _wait_analysis(http, path: str, deadline: float) -> dict:
    """Poll the analysis job until it is done or failed, showing its status and the time it has taken."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("  analysis"), SpinnerColumn(), TimeElapsedColumn(), TextColumn("{task.fields[status]}"),
                  transient=False) as bar:
        task = bar.add_task("analysis", total=None, status="queued")
        while True:
            doc = _ok(http.get(path))
            bar.update(task, status=doc.get("status"))
            if doc.get("status") in ("done", "failed"):
                bar.update(task, total=1, completed=1)
                return doc
            if time.monotonic() > deadline:
                fail(f"timed out waiting for {path} (status {doc.get('status')})")
            time.sleep(POLL_S)


def _run(http, procedure: str, params: dict, label: str, deadline: float) -> int:
    from rich.progress import BarColumn, Progress, TextColumn

    run = _ok(http.post("/runs", json={"procedure": procedure, "gyro_id": GYRO_ID, "bench": "sim1",
                                       "params": params, "operator": "demo"}))
    run_id = run["id"]
    typer.echo(f"queued run {run_id}: {procedure} ({label})")
    with Progress(TextColumn("  run {task.fields[run]}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TextColumn("{task.fields[status]}"), transient=False) as bar:
        task = bar.add_task("run", total=100, run=run_id, status="queued")
        while True:
            doc = _run_summary(http, run_id)
            bar.update(task, completed=min(100.0, float(doc.get("progress_percent") or 0.0)), status=doc["status"])
            if doc["status"] in ("completed", "aborted", "failed"):
                break
            if time.monotonic() > deadline:
                fail(f"timed out waiting for run {run_id}")
            time.sleep(POLL_S)
    if doc["status"] != "completed":
        fail(f"run {run_id} ended {doc['status']}: {doc.get('error')}")
    return run_id


def _run_summary(http, run_id: int) -> dict:
    """The run's summary row (status, progress) from the run list: ``GET /runs/{id}`` is the run page's
    document (latest readings, sampling summary), far costlier to build, and the service shares the
    host with the bench it reports on."""
    doc = _ok(http.get("/runs", params={"gyro_id": GYRO_ID, "limit": 10}))
    for row in doc["runs"]:
        if row["id"] == run_id:
            return row
    fail(f"run {run_id} is not in GET /runs?gyro_id={GYRO_ID}")
