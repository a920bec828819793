"""``bench run``, ``bench resume``, ``bench runs list|show`` and ``bench export``.

``bench run PROCEDURE --gyro ID [--gyro ID ...] [--sim [--sim-gyros N]] [--speed K] [--param key=value ...] [--json]``
    Validates the parameters through the procedure's pydantic ``Params`` (``--param stable.tol_c=0.5``
    reaches nested fields; values are JSON when they parse as JSON, else text; ``key=null`` gives
    None), builds and validates the plan against the bench (a bad plan is refused with the reason
    before a run row exists or anything moves), creates the run, prints ``run <ID>`` on stdout,
    shows a progress bar on stderr and executes the plan.  With ``--json`` stdout holds exactly one
    JSON object (run_id, status, outcome, frames, gaps, suspensions...) and ``run <ID>`` goes to stderr.
    ``--sim`` starts a ``SimulatedBench`` in this process at ``--speed`` (bench seconds per wall
    second) and uses its bench config; otherwise the config comes from ``--config PATH`` or
    ``$BENCH_CONFIG`` and time is real, or with ``--sim-endpoints FILE`` from a simulated bench running in
    another process (``bench sim up --endpoints-json FILE``: its bench config, and its lockstep clock driven
    from here over its clock endpoint at ``--speed``, ``bench.clocklink``; the simulator then has a CPU
    core of its own).
    Several gyros in one chamber: ``--gyro`` repeated (``--gyro ID`` takes the next free slot of the
    bench config's ``gyros`` list, ``--gyro SLOT=ID`` a given one); with ``--sim`` a ``MultiGyroBench``
    with ``--sim-gyros N`` units (default: one per ``--gyro`` when more than one is named).  The run is
    a parent run with one run per gyro (``bench runs show`` lists them under ``units``).
    Ctrl-C (SIGINT) asks the engine to stop after the current recording; a second Ctrl-C or SIGTERM
    aborts to the safe state at once.  Exit code 0 when the run completed (or stopped on request),
    1 when it was aborted or failed, 2 for refused input.

``bench resume RUN``
    Continues a run interrupted by a crash or kill from its last checkpoint (same output as
    ``run``).  A ``--sim`` run restarts a simulated bench with the recorded speed, scenario and data
    rate on the *same* accelerated clock (its bench time went on while nothing ran, so the
    interruption is a real gap in bench time).  The simulated physics restarts from the current
    conditions: the chamber air at the last recorded chamber temperature, the table at zero (the
    engine moves it back), the power supply off (the engine restores it) and the gyro's thermal
    state at the chamber air; a real bench would not have lost its thermal state.  Refused when the
    run ended or its process still runs (same host: pid alive; else a heartbeat fresher than 10 s)
    unless ``--force``.

``bench runs list`` / ``bench runs show RUN [--json]``; ``bench export RUN --format csv|parquet [-o FILE]``
    (stdout by default; csv is measured-data CSV v1 from ``bench.storage.export.run_dataset``; parquet
    holds every export column at 1 s or per frame).

Database: ``--db URL``, else ``$BENCH_DATABASE_URL``, else the SQLite file ``var/bench.sqlite``.
"""
from __future__ import annotations

import gc
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Optional

import typer

from bench.commands.common import db_option, fail, guarded, step

runs_app = typer.Typer(help="Stored runs: list and show.", no_args_is_help=True)
HEARTBEAT_S = 1.0
CONFIG_ENV = "BENCH_CONFIG"


def register(app: typer.Typer) -> None:
    app.command("run")(run_command)
    app.command("resume")(resume_command)
    app.add_typer(runs_app, name="runs")
    app.command("export")(export_command)


# ---- parameters ------------------------------------------------------------------------------------
def parse_params(items: list[str]) -> dict[str, Any]:
    """``key=value`` items -> nested dict (``a.b=1`` -> {"a": {"b": 1}}); JSON values when they parse."""
    data: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise typer.BadParameter(f"--param {item!r}: expected key=value")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise typer.BadParameter(f"--param {key}: {part!r} is given a value and sub-keys")
            node = child
        node[parts[-1]] = value
    return data


def validate_params(module, data: dict[str, Any]):
    """The procedure's ``Params`` from ``data``; a refusal names the key, the value and the reason."""
    from pydantic import ValidationError

    try:
        return module.Params.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            key = ".".join(str(p) for p in err["loc"]) or "(parameters)"
            given = err.get("input")
            shown = "" if err["type"] == "missing" else f" (got {given!r})"
            problems.append(f"--param {key}: {err['msg']}{shown}")
        fields = ", ".join(module.Params.model_fields)
        fail(f"procedure {module.NAME}: " + "; ".join(problems) + f". Parameters: {fields}")


# ---- shared execution ----------------------------------------------------------------------------
def _open_db(url: str | None):
    from bench.storage.db import open_database

    return open_database(url)


def _bench_config_from_file(config_path: str | None):
    from bench.config import BenchConfig

    from bench.settings import load_settings

    path = config_path or load_settings().config
    if not path:
        fail(f"no bench config: give --config PATH, set ${CONFIG_ENV}, or use --sim for the simulated bench")
    return BenchConfig.load(path)


class _Signals:
    """SIGINT: stop after the current recording (twice: abort); SIGTERM: abort."""

    def __init__(self, control) -> None:
        self.control = control
        self.interrupts = 0
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> "_Signals":
        if threading.current_thread() is threading.main_thread():
            self.previous = {sig: signal.signal(sig, self._handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def _handle(self, signum, _frame) -> None:
        if signum == signal.SIGINT:
            self.interrupts += 1
            self.control.request("stop" if self.interrupts == 1 else "abort")
        else:
            self.control.request("abort")

    def __exit__(self, *exc) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def _progress_loop(engine, stop: threading.Event, label: str) -> None:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    columns = [TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
               TextColumn("{task.fields[step]}"), TextColumn("{task.fields[left]}"), TimeElapsedColumn()]
    with Progress(*columns, console=console, transient=False) as bar:
        task = bar.add_task(label, total=100.0, step="", left="")
        while True:
            finished = stop.wait(0.25)
            try:
                p = engine.progress()
            except Exception:  # noqa: BLE001 - the bar must never break the run
                p = None
            if p:
                left = p.get("remaining_bench_s") or 0.0
                bar.update(task, completed=p["percent"],
                           step=f"step {min(p['step_index'] + 1, p['n_steps'])}/{p['n_steps']} "
                                f"{p.get('step_kind') or ''} [{p['status']}]",
                           left=f"{left / 3600:.2f} h bench left")
            if finished:
                break


def _heartbeat_loop(store, run_id: int, owner: str, engine, stop: threading.Event) -> None:
    while not stop.wait(HEARTBEAT_S):
        try:
            store.heartbeat(run_id, owner, engine.progress() if engine.plan is not None else None)
        except Exception:  # noqa: BLE001 - a missed heartbeat is retried next time
            pass


def _execute(db, run_id: int, config, clock, engine_config, *, plan=None, show_progress: bool, label: str,
             bench_state=None) -> str:
    """Run (``plan`` given) or resume ``run_id`` on the real drivers; returns the engine's final status."""
    from bench.engine import Engine, QueueControl
    from bench.engine.factory import build_devices, close_devices, make_fit_hook, writer_options_for
    from bench.engine.sqlstore import SqlRunStore, process_name

    store = SqlRunStore(db, geometry=config.turntable.geometry, frame_kind=config.gyro.frame,
                        nominal_rate_hz=config.gyro.data_rate_hz, writer_options=writer_options_for(clock))
    owner = process_name()
    devices = build_devices(config, clock)
    control = QueueControl()
    engine = Engine(devices, store, clock, config, control, engine_config,
                    make_fit_hook(db, store, latitude_deg=config.latitude_deg), bench_state=bench_state)
    stop = threading.Event()
    store.heartbeat(run_id, owner)
    threads = [threading.Thread(target=_heartbeat_loop, args=(store, run_id, owner, engine, stop), daemon=True,
                                name=f"heartbeat-run{run_id}")]
    if show_progress:
        threads.append(threading.Thread(target=_progress_loop, args=(engine, stop, label), daemon=True,
                                        name="progress"))
    for t in threads:
        t.start()
    _settle_heap()
    try:
        with _Signals(control):
            if plan is not None:
                status = engine.run(str(run_id), plan)
            else:
                status = engine.resume(str(run_id))
    finally:
        stop.set()
        for t in threads:
            t.join(5)
        try:
            store.close(run_id)
        finally:
            for problem in close_devices(devices):
                typer.secho(f"warning: closing {problem}", err=True, fg=typer.colors.YELLOW)
    return status


def _settle_heap() -> None:
    """Before a run: what this process built so far (modules, the drivers, a simulated bench) lives as long
    as the run, so it leaves the garbage collector's generations (``gc.freeze``).  A run allocates at every
    bench instant objects that live a few instants (frames waiting for the database), which reach the oldest
    generation; each full collection then walks only the objects made during the run, not the whole heap
    (on an eight-gyro campaign the full collections cost a tenth of the process's time otherwise)."""
    gc.collect()
    gc.freeze()


def _announce(run_id: int, as_json: bool) -> None:
    """``run <ID>`` as soon as the run exists: on stdout, or on stderr with ``--json`` (stdout then
    carries exactly one JSON object)."""
    if as_json:
        typer.echo(f"run {run_id}", err=True)
        return
    sys.stdout.write(f"run {run_id}\n")
    sys.stdout.flush()


def _finish(db, run_id: int, status: str, as_json: bool) -> None:
    from bench.engine.sqlstore import run_report

    report = run_report(db, run_id)
    doc = {"run_id": run_id, "status": report["status"], "outcome": status, "error": report["error"],
           "step": report["step"], "n_steps": report["n_steps"], "progress": report["progress"],
           "frames": report["frames"], "frames_lost": report["frames_lost"],
           "bench_seconds_lost": report["bench_seconds_lost"], "segments": report["segments"], "gaps": report["gaps"],
           "suspensions": report["suspensions"], "fits": report["fits"],
           "status_reason": report["status_reason"], "units": report["units"]}
    typer.secho(f"run {run_id} {status}: {report['frames']} frames, {len(report['gaps'])} gaps, "
                f"{len(report['suspensions'])} suspensions" + (f"; {report['error']}" if report["error"] else "")
                + "".join(f"\n  {u['slot']} gyro {u['gyro_id']} (run {u['run_id']}): {u['status']}, {u['frames']} "
                          f"frames, {len(u['gaps'])} gaps" + (f"; {u['error']}" if u["error"] else "")
                          for u in report["units"]),
                err=True, fg=typer.colors.GREEN if status in ("completed", "stopped") else typer.colors.RED)
    if as_json:
        sys.stdout.write(json.dumps(doc, allow_nan=False) + "\n")
        sys.stdout.flush()
    if status not in ("completed", "stopped"):
        raise typer.Exit(1)


def _attach_sim(path: str, speed: str | float | None = None):
    """Bench config and clock of a running ``bench sim up --endpoints-json PATH``: its lockstep bench time is
    driven from this process at ``speed`` (None: the pace it published; ``bench.clocklink``)."""
    from bench.commands.service import bench_clock, load_bench_file
    from bench.errors import DataFormatError

    if not Path(path).exists():
        fail(f"--sim-endpoints {path}: no such file (start `bench sim up --endpoints-json {path}` first)")
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"not valid JSON: {exc.msg}", line=exc.lineno, source=path) from None
    if not (isinstance(doc, dict) and isinstance(doc.get("bench_config"), dict) and isinstance(doc.get("clock"), dict)):
        raise DataFormatError("not an endpoints file of `bench sim up` (it has no bench_config and clock)",
                              source=path)
    config, clock_doc = load_bench_file(path)
    try:
        return config, bench_clock(clock_doc, speed)
    except (KeyError, ValueError) as exc:
        raise DataFormatError(f"not an endpoints file of `bench sim up`: {exc}", source=path) from None


def _sim_launch(sim, speed: float | None, scenario: str, chamber_transport: str) -> dict[str, Any]:
    return {"speed": speed, "scenario": scenario, "seed": sim.seed, "data_rate_hz": sim.data_rate_hz,
            "clock": sim.clock.to_json(), "chamber_transport": chamber_transport,
            "units": len(getattr(sim, "units", ())) or None}


def _sim_bench(units: int | None, **kwargs: Any):
    from bench.sim.multibench import simulated_bench

    return simulated_bench(units, **kwargs)


def _units_for(config, gyros: list[str]) -> list[tuple[str, str]] | None:
    """(slot, gyro id) of a multi-gyro bench, or None (one gyro, the simple case)."""
    if not config.multi:
        if len(gyros) != 1:
            fail(f"--gyro given {len(gyros)} times but this bench carries one gyro (its config has no gyros list)")
        return None
    try:
        return config.assign_gyros(gyros)
    except (ValueError, KeyError) as exc:
        fail(f"--gyro: {str(exc).strip(chr(34) + chr(39))}")


# ---- bench run -------------------------------------------------------------------------------------
@guarded
def run_command(
    procedure: str = typer.Argument(..., help="eight_position, thermal_ramp, rate_cycle, hrg_calibration, fog_startup"),
    gyro: list[str] = typer.Option(..., "--gyro", help="ID of the gyro under test; repeat for several gyros in one "
                                   "chamber (ID: the next free slot; SLOT=ID: that slot)"),
    sim: bool = typer.Option(False, "--sim", help="start a simulated bench in this process"),
    sim_gyros: Optional[int] = typer.Option(None, "--sim-gyros", min=1, max=64, help="simulated bench: this many "
                                            "gyros in one chamber (default: one per --gyro when several)"),
    speed: Optional[str] = typer.Option(None, "--speed", help="simulated bench: at most this many bench seconds "
                                        "per wall second, or 'max' (as fast as the host can; the data are the "
                                        "same); default 3600 (--sim) or the pace `bench sim up` published "
                                        "(--sim-endpoints)"),
    scenario: str = typer.Option("default", "--scenario", help="simulated bench: scenario name or JSON file"),
    seed: Optional[int] = typer.Option(None, "--seed", help="simulated bench: noise seed (default: the "
                                       "scenario's); a seeded bench starts at a fixed bench instant"),
    data_rate: Optional[int] = typer.Option(None, "--data-rate", help="simulated gyro data rate, Hz (bench time)"),
    chamber_transport: str = typer.Option("modbus_tcp", "--chamber-transport",
                                          help="simulated bench: modbus_tcp or modbus_rtu (RTU over TCP)"),
    param: list[str] = typer.Option([], "--param", help="procedure parameter key=value (repeatable)"),
    sim_endpoints: Optional[str] = typer.Option(None, "--sim-endpoints", help="attach to a simulated bench "
                                                "running in another process (`bench sim up --endpoints-json FILE`)"),
    config_path: Optional[str] = typer.Option(None, "--config", help=f"bench config JSON (default ${CONFIG_ENV})"),
    db_url: Optional[str] = db_option(),
    operator: str = typer.Option("", "--operator", help="who starts the run"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON object on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Run a procedure on the bench (or the simulated bench) and store everything."""
    import procedures
    from bench.clock import RealClock, parse_speed
    from bench.engine import plan_summary
    from bench.engine.factory import engine_config_for
    from bench.engine.sqlstore import new_run

    try:
        module = procedures.get(procedure)
    except KeyError as exc:
        fail(str(exc).strip("'\""))
    params = validate_params(module, parse_params(param))
    plan = module.build(params)
    if chamber_transport not in ("modbus_tcp", "modbus_rtu"):
        fail(f"--chamber-transport {chamber_transport!r}: use modbus_tcp or modbus_rtu")
    bench = None
    if sim:
        try:
            pace = parse_speed(speed)
        except ValueError as exc:
            fail(str(exc))
        from bench.config import BenchConfig
        from bench.sim.bench import lockstep_clock

        lockstep = lockstep_clock(pace, seed)
        # tests hold the bench time at known instants through this file (bench.clock.LockstepClock)
        from bench.settings import load_settings

        lockstep.hold_file = load_settings().sim_hold_file or None
        # the simulated bench keeps the default limits and table geometry: refuse a bad plan before
        # starting it (checked again below against the started bench's own config)
        procedures.check_duration(plan_summary(plan, BenchConfig(), engine_config_for(lockstep)))
        units = sim_gyros or (len(gyro) if len(gyro) > 1 else None)
        bench = _sim_bench(units, clock=lockstep, scenario=scenario, data_rate_hz=data_rate, seed=seed).start()
        config, clock = bench.bench_config(chamber_transport=chamber_transport), bench.clock
    elif sim_endpoints:
        try:
            parse_speed(speed)
        except ValueError as exc:
            fail(str(exc))
        config, clock = _attach_sim(sim_endpoints, speed)
        pace = getattr(clock, "pace", None)
    else:
        config, clock = _bench_config_from_file(config_path), RealClock()
    try:
        engine_config = engine_config_for(clock)
        summary = plan_summary(plan, config, engine_config)     # PlanError here: nothing created, nothing moved
        procedures.check_duration(summary)
        db = _open_db(db_url)
        launch = {"launched_by": "bench run", "engine_config": engine_config.model_dump(),
                  "sim": _sim_launch(bench, pace, scenario, chamber_transport) if bench else None,
                  "sim_endpoints": str(Path(sim_endpoints).resolve()) if sim_endpoints else None,
                  "sim_pace": ("max" if pace is None else pace) if sim_endpoints else None}
        units = _units_for(config, gyro)
        run_id = new_run(db, procedure=module.NAME, parameters=params.model_dump(mode="json"),
                         config_snapshot=config.model_dump(mode="json"), gyro_id=None if units else gyro[0],
                         bench_name=config.name, operator=operator, launch=launch, units=units)
        _announce(run_id, as_json)
        named = ", ".join(f"{g} ({slot})" for slot, g in units) if units else gyro[0]
        typer.echo(f"{module.NAME} on gyro{'s' if units else ''} {named}: {summary['n_steps']} steps, about "
                   f"{summary['total_bench_h']:.2f} h of bench time"
                   + ((f" (simulated bench in lockstep, at most x{pace:g}: at least "
                       f"{summary['total_bench_s'] / pace:.0f} s wall)" if pace else
                       " (simulated bench in lockstep, as fast as the host can)")
                      if bench or getattr(clock, "lockstep", False) else ""), err=True)
        status = _execute(db, run_id, config, clock, engine_config, plan=plan, show_progress=not no_progress,
                          label=f"run {run_id} {module.NAME}", bench_state=bench)
        _finish(db, run_id, status, as_json)
    finally:
        if bench is not None:
            bench.stop()


# ---- bench resume ------------------------------------------------------------------------------------
def _last_chamber_pv(db, run_id: int) -> float | None:
    from sqlalchemy import select

    from bench.storage.models import Telemetry

    with db.session() as s:
        return s.scalar(select(Telemetry.chamber_pv).where(Telemetry.run_id == run_id, Telemetry.device == "chamber",
                                                           Telemetry.chamber_pv.is_not(None))
                        .order_by(Telemetry.t.desc()).limit(1))


@guarded
def resume_command(
    run: int = typer.Argument(..., help="run ID"),
    config_path: Optional[str] = typer.Option(None, "--config", help=f"bench config JSON (default ${CONFIG_ENV}); "
                                                                     "not used for a simulated run"),
    db_url: Optional[str] = db_option(),
    sim_endpoints: Optional[str] = typer.Option(None, "--sim-endpoints", help="attach to this running simulated "
                                                "bench (default: the one the run was started on)"),
    force: bool = typer.Option(False, "--force", help="resume even if the run's process looks alive"),
    outage: Optional[float] = typer.Option(None, "--outage", min=0.0, help="simulated bench: bench seconds the "
                                           "interruption lasted (default: its wall duration at the run's speed)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON object on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Continue an interrupted run from its last checkpoint."""
    from bench.clock import RealClock, clock_from_json
    from bench.engine import EngineConfig
    from bench.engine.factory import engine_config_for
    from bench.engine.sqlstore import claim_for_resume, process_name
    from bench.storage import queries

    db = _open_db(db_url)
    with db.session() as s:
        row = queries.get_run(s, run)
        live, procedure = dict(row.live or {}), row.procedure
    claim_for_resume(db, run, process_name(), force=force)
    sim_info = live.get("sim")
    bench = None
    if sim_info:
        if sim_info["clock"].get("kind") == "lockstep":
            # a fresh lockstep clock: the engine puts the checkpointed bench state back and lets the
            # outage pass in bench time before the run continues
            from bench.sim.bench import lockstep_clock

            clock = lockstep_clock(sim_info.get("speed"), sim_info.get("seed"))
            clock.fixed_outage_s = outage
            bench = _sim_bench(sim_info.get("units"), clock=clock, scenario=sim_info["scenario"],
                               seed=sim_info.get("seed"), data_rate_hz=int(sim_info["data_rate_hz"])).start()
        else:
            clock = clock_from_json(sim_info["clock"])       # the same bench time axis, still running
            pv = _last_chamber_pv(db, run)
            bench = _sim_bench(sim_info.get("units"), speed=float(sim_info["speed"]), scenario=sim_info["scenario"],
                               clock=clock, data_rate_hz=int(sim_info["data_rate_hz"]),
                               initial_air_c=float(pv) if pv is not None else 23.0).start()
        config = bench.bench_config(chamber_transport=sim_info.get("chamber_transport", "modbus_tcp"))
    elif sim_endpoints or live.get("sim_endpoints"):
        config, clock = _attach_sim(sim_endpoints or live["sim_endpoints"], live.get("sim_pace"))
        if getattr(clock, "lockstep", False):
            clock.fixed_outage_s = outage       # the simulator process kept its state: only the outage passes
    else:
        config, clock = _bench_config_from_file(config_path), RealClock()
    try:
        stored = live.get("engine_config")
        engine_config = EngineConfig.model_validate(stored) if stored else engine_config_for(clock)
        _announce(run, as_json)
        typer.echo(f"resuming run {run} ({procedure})" + (" on a restarted simulated bench" if sim_info else ""),
                   err=True)
        status = _execute(db, run, config, clock, engine_config, show_progress=not no_progress,
                          label=f"run {run} {procedure} (resumed)", bench_state=bench)
        _finish(db, run, status, as_json)
    finally:
        if bench is not None:
            bench.stop()


# ---- bench runs list / show ---------------------------------------------------------------------
@runs_app.command("list")
@guarded
def list_command(
    db_url: Optional[str] = db_option(),
    status: Optional[str] = typer.Option(None, "--status", help="only runs with this status"),
    limit: int = typer.Option(50, "--limit", help="at most this many (newest first)"),
    as_json: bool = typer.Option(False, "--json", help="JSON list"),
) -> None:
    """Stored runs, newest first."""
    from bench.storage import queries

    db = _open_db(db_url)
    with db.session() as s:
        rows = [{"run_id": r.id, "procedure": r.procedure, "gyro_id": r.gyro_id, "status": r.status,
                 "outcome": (r.live or {}).get("outcome"), "progress": float(r.progress or 0.0),
                 "created_at": r.created_at.isoformat() if r.created_at else None,
                 "finished_at": r.finished_at.isoformat() if r.finished_at else None}
                for r in queries.list_runs(s, status=status, limit=limit)]
    if as_json:
        sys.stdout.write(json.dumps(rows) + "\n")
        return
    from rich.console import Console
    from rich.table import Table

    table = Table("run", "procedure", "gyro", "status", "progress", "created (UTC)")
    for r in rows:
        shown = r["status"] + (f" ({r['outcome']})" if r["outcome"] and r["outcome"] != r["status"] else "")
        table.add_row(str(r["run_id"]), r["procedure"], r["gyro_id"] or "", shown, f"{100 * r['progress']:.1f}%",
                      (r["created_at"] or "")[:19])
    Console().print(table)


@runs_app.command("show")
@guarded
def show_command(
    run: int = typer.Argument(..., help="run ID"),
    db_url: Optional[str] = db_option(),
    as_json: bool = typer.Option(False, "--json", help="one JSON object"),
) -> None:
    """Status, step, progress, frames, gaps and suspensions of a run."""
    from bench.engine.sqlstore import run_report

    report = run_report(_open_db(db_url), run)
    if as_json:
        sys.stdout.write(json.dumps(report, allow_nan=False) + "\n")
        return
    status = report["status"] + (f" ({report['outcome']})" if report["outcome"] not in (None, report["status"]) else "")
    lines = [f"run {report['run_id']}: {report['procedure']} on gyro {report['gyro_id']}", f"status: {status}"]
    if report["error"]:
        lines.append(f"error: {report['error']}")
    lines += [f"step: {report['step']} / {report['n_steps']} {report['step_name'] or ''}",
              f"progress: {100 * report['progress']:.1f}%", f"frames: {report['frames']}",
              f"lost: {report['frames_lost']} frames, {report['bench_seconds_lost']:.3f} bench seconds",
              f"segments: {report['segments']}", f"gaps: {len(report['gaps'])}"]
    lines += [f"  {g['t_from']:.1f} .. {g['t_to']:.1f} ({g['duration_s']:.1f} s) {g['reason']}, "
              f"{g['frames_missing']} frames missing" for g in report["gaps"]]
    lines.append(f"suspensions: {len(report['suspensions'])}")
    lines += [f"  {x['t_from']:.1f} .. {x['t_to'] if x['t_to'] is None else round(x['t_to'], 1)} {x['reason']}"
              for x in report["suspensions"]]
    typer.echo("\n".join(lines))


# ---- bench export --------------------------------------------------------------------------------
@guarded
def export_command(
    run: int = typer.Argument(..., help="run ID"),
    fmt: str = typer.Option("csv", "--format", help="csv (measured-data CSV v1) or parquet"),
    output: Optional[str] = typer.Option(None, "-o", "--output", help="file (default stdout)"),
    db_url: Optional[str] = db_option(),
    recorded_only: bool = typer.Option(False, "--recorded-only", help="csv: only seconds inside recorded segments"),
    resolution: str = typer.Option("second", "--resolution", help="parquet: second (1-s means) or frame"),
) -> None:
    """Export a stored run: measured-data CSV v1 (1-s means) or Parquet (every export column)."""
    db = _open_db(db_url)
    if fmt == "csv":
        from bench.fit.csvio import format_csv, write_csv
        from bench.storage.export import run_dataset

        with step(f"reading run {run}"):
            ds = run_dataset(run, db, recorded_only=recorded_only)
        if len(ds) == 0:
            fail(f"run {run}: no frames stored{' inside recorded segments' if recorded_only else ''}; nothing to export")
        if output:
            write_csv(ds, output)
        else:
            sys.stdout.write(format_csv(ds))
    elif fmt == "parquet":
        import tempfile

        from bench.storage.export import export_parquet

        if resolution not in ("second", "frame"):
            fail(f"--resolution {resolution!r}: use second or frame")
        if output:
            with step(f"writing run {run} to {output}"):
                export_parquet(db, run, output, resolution=resolution)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                path = export_parquet(db, run, Path(tmp) / f"run{run}.parquet", resolution=resolution)
                sys.stdout.buffer.write(path.read_bytes())
                sys.stdout.flush()
    else:
        fail(f"--format {fmt!r}: use csv or parquet")
