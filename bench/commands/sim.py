"""``bench sim up``: the whole simulated bench in one process."""
from __future__ import annotations

import signal
import threading
from typing import Optional

import typer

from bench.commands.common import guarded

sim_app = typer.Typer(help="The simulated bench (every device on a real loopback transport).", no_args_is_help=True)


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")


@sim_app.command("up")
@guarded
def up(
    speed: float = typer.Option(3600.0, "--speed", help="bench seconds per wall second"),
    seed: Optional[int] = typer.Option(None, "--seed", help="noise seed (default: the scenario's)"),
    scenario: str = typer.Option("default", "--scenario", help="scenario JSON file or a built-in name"),
    endpoints_json: Optional[str] = typer.Option(None, "--endpoints-json",
                                                 help="write the endpoints and a bench config here"),
    seconds: Optional[float] = typer.Option(None, "--seconds", help="stop after this many wall seconds"),
    gyros: Optional[int] = typer.Option(None, "--gyros", min=1, max=64, help="this many gyros in one chamber "
                                        "(each its own line, probes and supply channel; the bench config lists them)"),
) -> None:
    """Start chamber (Modbus TCP + RTU over TCP), turntable, gyro, PSU and DS18B20 tree; run until
    interrupted."""
    from bench.sim.multibench import simulated_bench

    # another process drives this bench: it keeps a free-running accelerated clock shared through the
    # endpoints file (no lockstep across processes yet; the run's sampling summary shows late samples)
    bench = simulated_bench(gyros, speed=speed, scenario=scenario, seed=seed).start()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    try:
        if endpoints_json:
            bench.write_endpoints(endpoints_json)
        for key, value in bench.endpoints.items():
            if key not in ("clock", "probes", "units"):
                typer.echo(f"{key}: {value}")
        for slot, unit in (bench.endpoints.get("units") or {}).items():
            typer.echo(f"{slot}: gyro {unit['gyro']}, probes {unit['w1_root']}, supply channel {unit['psu_channel']}")
        typer.echo(f"simulated bench up at x{speed:g}; Ctrl-C to stop", err=True)
        done.wait(seconds)
    finally:
        bench.stop()
