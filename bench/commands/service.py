"""``bench serve``, ``bench worker``, ``bench coefficients`` and ``bench import``.

* ``serve``: the HTTP API plus one worker per configured bench in one process, and an analysis worker
  (``bench worker --analysis``) as a child process.  Embedded default: the SQLite file
  (``BENCH_DATABASE_URL`` overrides) and a simulated bench at ``--speed``; with ``--config FILE``
  (repeatable) the workers drive the benches those files describe.
* ``worker``: one bench's worker on its own (the API may run elsewhere; killing either leaves the
  other going, and a killed worker's run is resumed when a worker for that bench returns); between
  runs it executes analysis jobs.  ``--analysis``: a worker for analysis jobs only.
* ``coefficients``: a gyro's accepted coefficients from the database, or one model exported for firmware
  (``--format json|px4|ardupilot|c-header``, ``bench.fit.firmware``; refused with the reason, exit code 3).
* ``import``: a measured-data CSV (v1) stored as a completed run, so it can be fitted like a recorded one.
"""
from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional

import typer

from bench.commands.common import db_option, fail, guarded


def register(app: typer.Typer) -> None:
    app.command("serve")(serve_command)
    app.command("worker")(worker_command)
    app.command("coefficients")(coefficients_command)
    app.command("import")(import_command)


# ------------------------------------------------------------------------------------ bench files
def load_bench_file(path: str):
    """A bench description: a ``BenchConfig`` JSON, or a simulated bench's endpoints file (``bench_config``
    plus the ``clock`` both sides must share).  Returns (BenchConfig, clock description or None)."""
    from bench.config import BenchConfig
    from bench.errors import DataFormatError

    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise DataFormatError("bench file not found", source=path) from None
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"not valid JSON: {exc.msg}", line=exc.lineno, source=path) from None
    if isinstance(doc, dict) and "bench_config" in doc:
        return BenchConfig.model_validate(doc["bench_config"]), doc.get("clock")
    return BenchConfig.load(p), None


def _check_optional_speed(value: str | None) -> str | None:
    from bench.clock import parse_speed

    if value is not None:
        try:
            parse_speed(value)
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None
    return value


def bench_clock(clock_doc: dict[str, Any] | None, speed: str | float | None):
    """The clock of a bench file: a simulated bench in another process is driven from here over its clock
    endpoint (``bench.clocklink``) at ``speed`` (a number or 'max'; None: the pace its ``bench sim up``
    published), holding at ``BENCH_SIM_HOLD_FILE``'s instants; another clock description is rebuilt as
    is; without one, ``speed`` makes an accelerated clock (None: real time)."""
    from bench.clock import clock_from_json, make_clock, parse_speed
    from bench.clocklink import LINK_KIND
    from bench.settings import load_settings

    if clock_doc and clock_doc.get("kind") == LINK_KIND:
        clock_doc = {**clock_doc, "hold_file": load_settings().sim_hold_file or None}
        if speed is not None:
            clock_doc["pace"] = parse_speed(speed)
        return clock_from_json(clock_doc)
    if clock_doc:
        return clock_from_json(clock_doc)
    if speed is not None and parse_speed(speed) is None:
        raise ValueError("--speed max: only for a simulated bench in lockstep (an endpoints file of `bench sim up`)")
    return make_clock(None if speed is None else parse_speed(speed))


def write_secret_file(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` readable by its owner only (mode 0600, also when the file existed)."""
    import os

    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)
    return path


def _tokens_or_generate() -> str:
    """``BENCH_TOKENS``, or fresh tokens written to ``BENCH_TOKENS_FILE`` (0600) whose path is printed;
    the tokens themselves never go to the log."""
    from api.auth import ENV_TOKENS
    from bench.settings import load_settings

    settings = load_settings()
    if settings.tokens:
        return settings.tokens
    pairs = {role: secrets.token_urlsafe(18) for role in ("viewer", "operator", "admin")}
    text = ",".join(f"{r}:{t}" for r, t in pairs.items())
    path = write_secret_file(settings.tokens_file, text + "\n").resolve()
    typer.secho(f"{ENV_TOKENS} is not set; generated viewer, operator and admin tokens are in {path} (mode 0600, "
                f"{ENV_TOKENS} format)", fg=typer.colors.YELLOW, err=True)
    return text


# ------------------------------------------------------------------------------------------ serve
def _exit_on_sigterm(signum, _frame) -> None:
    raise SystemExit(128 + signum)


@guarded
def serve_command(
    host: str = typer.Option("127.0.0.1", "--host", help="address to listen on"),
    port: int = typer.Option(8000, "--port", min=0, max=65535, help="TCP port"),
    speed: Optional[str] = typer.Option(None, "--speed", callback=_check_optional_speed,
                                        help="simulated bench (embedded, or another process's endpoints file given "
                                        "with --config): at most this many bench seconds per wall second, or 'max' "
                                        "(as fast as the host can; the data are the same); default 3600, or the "
                                        "pace `bench sim up` published"),
    seed: Optional[int] = typer.Option(None, "--seed", help="simulated bench noise seed (default: the scenario's); "
                                       "a seeded bench starts at a fixed bench instant"),
    config: Optional[list[str]] = typer.Option(None, "--config", help="bench config JSON (repeatable); "
                                               "default: one simulated bench"),
    scenario: str = typer.Option("default", "--scenario", help="simulated bench scenario (name or JSON file)"),
    bench_name: str = typer.Option("sim1", "--bench-name", help="name of the simulated bench"),
    sim_gyros: Optional[int] = typer.Option(None, "--sim-gyros", min=1, max=64, help="simulated bench: this many "
                                            "gyros in one chamber (runs then name them with gyro_ids)"),
    log_level: str = typer.Option("info", "--log-level", help="debug, info, warning or error"),
    log_format: Optional[str] = typer.Option(None, "--log-format", help="text or json (JSON lines); "
                                             "default $BENCH_LOG_FORMAT or text"),
    db_url: Optional[str] = db_option(),
) -> None:
    """Run the API (metrics at /metrics) and one worker per configured bench in this process."""
    import uvicorn

    from api.app import create_app
    from bench.logs import configure_logging, uvicorn_log_config
    from bench.storage import open_database
    from bench.worker import Worker

    log_format = configure_logging(log_level, log_format)
    db = open_database(db_url)
    tokens = _tokens_or_generate()
    sim = None
    workers = []
    analysis_worker = None
    try:
        if config:
            for path in config:
                cfg, clock_doc = load_bench_file(path)
                workers.append(Worker(db, cfg.name, cfg, None, bench_clock(clock_doc, speed if clock_doc else None),
                                      run_jobs=False))
        else:
            from bench.clock import parse_speed
            from bench.settings import load_settings
            from bench.sim.bench import lockstep_clock
            from bench.sim.multibench import simulated_bench

            pace = parse_speed(speed)
            clock = lockstep_clock(pace, seed)
            # tests hold the bench time at known instants through this file (bench.clock.LockstepClock)
            clock.hold_file = load_settings().sim_hold_file or None
            sim = simulated_bench(sim_gyros, clock=clock, scenario=scenario, bench_name=bench_name,
                                  seed=seed).start()
            cfg = sim.config
            workers.append(Worker(db, cfg.name, cfg, None, sim.clock, bench_state=sim, run_jobs=False))
            typer.echo(f"simulated bench {cfg.name!r} in lockstep, "
                       f"{'at most x' + format(pace, 'g') if pace else 'as fast as the host can'}", err=True)
        for w in workers:
            w.start_thread()
        analysis_worker = _start_analysis_worker(db.url, log_level, log_format)
        typer.echo(f"database {db.dialect}; benches: {', '.join(w.bench_name for w in workers)}; "
                   f"API on http://{host}:{port}/docs", err=True)
        # uvicorn shuts down gracefully on SIGINT and SIGTERM, then raises the signal again with the
        # handler it found: make SIGTERM end this function through ``finally`` (workers stopped, the
        # simulated bench's w1 tree removed) as SIGINT's KeyboardInterrupt does
        signal.signal(signal.SIGTERM, _exit_on_sigterm)
        uvicorn.run(create_app(db, tokens=tokens), host=host, port=port, log_level=log_level.lower(),
                    log_config=uvicorn_log_config(log_format))
    finally:
        for w in workers:
            w.stop()
        if analysis_worker is not None:
            analysis_worker.terminate()
            try:
                analysis_worker.wait(timeout=10)
            except subprocess.TimeoutExpired:
                analysis_worker.kill()
        if sim is not None:
            sim.stop()
        db.dispose()


def _start_analysis_worker(database_url: str, log_level: str, log_format: str) -> subprocess.Popen:
    """`bench worker --analysis` as a child process on the same database: fits, close-the-loop and report
    rendering never run in the API's process."""
    env = {**os.environ, "BENCH_DATABASE_URL": database_url}
    return subprocess.Popen([sys.executable, "-m", "bench", "worker", "--analysis", "--log-level", log_level,
                             "--log-format", log_format], env=env)


# ----------------------------------------------------------------------------------------- worker
@guarded
def worker_command(
    bench: Optional[str] = typer.Option(None, "--bench", help="name of the bench this worker serves (it also "
                                        "executes analysis jobs between runs)"),
    analysis: bool = typer.Option(False, "--analysis", help="an analysis worker: executes the queued fit, "
                                  "close-the-loop and report jobs only (no bench)"),
    jobs: bool = typer.Option(True, "--jobs/--no-jobs", help="a bench worker executes analysis jobs between runs"),
    config: Optional[str] = typer.Option(None, "--config", help="bench config JSON or a simulated bench's "
                                         "endpoints file; default: the configuration stored for the bench"),
    speed: Optional[str] = typer.Option(None, "--speed", callback=_check_optional_speed,
                                        help="a simulated bench's endpoints file: at most this many bench seconds "
                                        "per wall second, or 'max' (default: the pace `bench sim up` published); "
                                        "a bench file without a clock: an accelerated clock"),
    heartbeat_s: float = typer.Option(1.0, "--heartbeat", min=0.05, help="heartbeat period, wall seconds"),
    stale_after_s: float = typer.Option(15.0, "--stale-after", min=0.2, help="a heartbeat older than this means "
                                        "the worker died (wall seconds)"),
    poll_s: float = typer.Option(0.5, "--poll", min=0.01, help="queue polling period, wall seconds"),
    log_level: str = typer.Option("info", "--log-level", help="debug, info, warning or error"),
    log_format: Optional[str] = typer.Option(None, "--log-format", help="text or json (JSON lines); "
                                             "default $BENCH_LOG_FORMAT or text"),
    metrics_port: Optional[int] = typer.Option(None, "--metrics-port", min=0, max=65535,
                                               help="serve Prometheus metrics on this port (0: any free port)"),
    metrics_addr: str = typer.Option("127.0.0.1", "--metrics-addr", help="address of the metrics server"),
    db_url: Optional[str] = db_option(),
) -> None:
    """Serve one bench: claim its queued runs, execute them, resume a run whose worker died; or, with
    --analysis, execute analysis jobs (fits, close-the-loop, reports) and re-run those whose worker died."""
    from bench.config import BenchConfig
    from bench.storage import open_database
    from bench.storage.models import Bench
    from bench.worker import Worker
    from sqlalchemy import select

    from bench.logs import configure_logging

    configure_logging(log_level, log_format)
    if analysis == (bench is not None):
        fail("give either --bench NAME (a bench worker) or --analysis (an analysis worker)")
    db = open_database(db_url)
    if analysis:
        from bench.jobs import JobRunner
        from bench.settings import load_settings

        runner = JobRunner(db, heartbeat_s=heartbeat_s, stale_after_s=stale_after_s, poll_s=poll_s,
                           hold_file=load_settings().job_hold_file or None)
        signal.signal(signal.SIGTERM, lambda *_: runner.stop())
        typer.echo(f"analysis worker {runner.worker_id} ({db.dialect})", err=True)
        runner.run_forever()
        return
    clock_doc = None
    if config:
        cfg, clock_doc = load_bench_file(config)
        if cfg.name != bench:
            cfg = cfg.model_copy(update={"name": bench})
    else:
        with db.session() as s:
            row = s.scalars(select(Bench).where(Bench.name == bench)).first()
            if row is None or not row.config:
                fail(f"bench {bench!r} has no stored configuration; give --config FILE")
            cfg = BenchConfig.model_validate(row.config)
    try:
        clock = bench_clock(clock_doc, speed)
    except ValueError as exc:
        fail(str(exc))
    worker = Worker(db, bench, cfg, None, clock, heartbeat_s=heartbeat_s,
                    stale_after_s=stale_after_s, poll_s=poll_s, run_jobs=jobs)
    signal.signal(signal.SIGTERM, lambda *_: worker.stop())
    if metrics_port is not None:
        from bench.metrics import serve_worker_metrics

        server, _thread = serve_worker_metrics(worker, metrics_port, metrics_addr)
        typer.echo(f"worker metrics on http://{metrics_addr}:{server.server_port}/metrics", err=True)
    typer.echo(f"worker {worker.worker_id} serving bench {bench!r} ({db.dialect})", err=True)
    worker.run_forever()


# ----------------------------------------------------------------------------------- coefficients
@guarded
def coefficients_command(
    gyro: str = typer.Argument(..., help="gyro ID"),
    model: Optional[str] = typer.Option(None, "--model", help="only this model"),
    version: Optional[int] = typer.Option(None, "--version", min=1, help="this version (needs --model)"),
    as_json: bool = typer.Option(False, "--json", help="print the JSON document"),
    fmt: Optional[str] = typer.Option(None, "--format",
                                      help="export one model (--model) as json | px4 | ardupilot | c-header"),
    output: Optional[str] = typer.Option(None, "-o", "--output", help="write the export to this file"),
    px4_instance: int = typer.Option(0, "--px4-instance", min=0, max=3, help="PX4 gyro instance (TC_G<i>_)"),
    px4_device_id: int = typer.Option(0, "--px4-device-id", help="PX4 TC_G<i>_ID: the gyro's device id"),
    ardupilot_imu: int = typer.Option(1, "--ardupilot-imu", min=1, max=3, help="ArduPilot IMU number (INS_TCAL<n>_)"),
    ardupilot_caltemp: Optional[float] = typer.Option(None, "--ardupilot-caltemp",
                                                      help="temperature of the exported gyro offsets (default 35 C)"),
    db_url: Optional[str] = db_option(),
) -> None:
    """Print a gyro's coefficients: the latest accepted fit of each model, or export one model for firmware."""
    from api.coefficients import NoCoefficients, load_coefficients
    from bench.storage import open_database

    db = open_database(db_url)
    if fmt is not None:
        from api.coefficients import export_coefficients
        from bench.fit.firmware import NotExpressible

        if model is None:
            fail("--format needs --model: an export holds one model")
        options = {"px4_instance": px4_instance, "px4_device_id": px4_device_id, "ardupilot_imu": ardupilot_imu,
                   "ardupilot_caltemp_c": ardupilot_caltemp}
        try:
            text, _media, _suffix = export_coefficients(db, gyro, model, fmt, version=version, options=options)
        except NoCoefficients as exc:
            fail(str(exc), code=1)
        except NotExpressible as exc:
            fail(f"cannot export: {exc}", code=3)
        if output is None or output == "-":
            sys.stdout.write(text)
        else:
            from bench.files import write_text_atomic

            write_text_atomic(output, text)
            typer.echo(f"wrote {output}", err=True)
        return
    try:
        doc = load_coefficients(db, gyro, model=model, version=version)
    except NoCoefficients as exc:
        fail(str(exc), code=1)
    if as_json:
        sys.stdout.write(json.dumps(doc, indent=2) + "\n")
        return
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for m in doc["models"]:
        table = Table(title=f"{gyro}: {m['model']} v{m['version']}{' (accepted)' if m['accepted'] else ''}, "
                            f"runs {m['run_ids']}")
        table.add_column("channel")
        table.add_column("term")
        table.add_column("value", justify="right")
        table.add_column("unit")
        for ch, entry in m["channels"].items():
            units = entry.get("units") or {}
            label = f"{ch} ({entry['probe']})" if entry.get("probe") else ch
            for term, value in entry["coefficients"].items():
                table.add_row(label, term, f"{value:.9g}" if isinstance(value, (int, float)) else str(value),
                              str(units.get(term, "")))
        console.print(table)


# ----------------------------------------------------------------------------------------- import
from bench.commands.importing import import_csv, import_dataset  # noqa: E402,F401  (public here too)


@guarded
def import_command(
    file: str = typer.Argument(..., help="measured-data CSV (v1)"),
    gyro: str = typer.Option(..., "--gyro", help="gyro ID the data belongs to"),
    bench_name: Optional[str] = typer.Option(None, "--bench", help="bench the data was measured on"),
    operator: str = typer.Option("", "--operator", help="who measured the data (stored with the run)"),
    db_url: Optional[str] = db_option(),
) -> None:
    """Store a measured-data CSV as a completed run (then fit it with ``bench fit MODEL RUN_ID``)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from bench.fit.csvio import CsvStream
    from bench.storage import open_database

    CsvStream(file)          # a missing or unreadable file, or a bad header: one line, before the database
    db = open_database(db_url)
    rows = [0]

    def advance(k: int) -> None:
        rows[0] += k
        bar.advance(task, k)

    with Progress(TextColumn("[bold]import"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=Console(stderr=True), transient=False) as bar:
        task = bar.add_task("rows", total=None)
        run_id = import_csv(db, file, gyro, bench_name=bench_name, operator=operator, progress=advance)
    typer.echo(f"run {run_id}: {rows[0]} rows of {file} stored for gyro {gyro}")
