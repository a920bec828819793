"""``bench sim up``: the whole simulated bench in one process, its bench time driven from another.

The simulators run on a lockstep clock (``bench.clock.LockstepClock``) that this process never moves
by itself: the process that runs the engine (``bench run --sim-endpoints FILE``, ``bench worker`` or
``bench serve`` with ``--config FILE``) drives it over the clock endpoint listed in the endpoints file
(``bench.clocklink``), at its own ``--speed``; ``--speed`` here is only the pace those commands use
when they give none.  Until a driver connects, the bench stands still at its first instant (a seeded
bench at the fixed instant of ``bench.sim.bench.SEEDED_EPOCH_S``), so the same ``--seed`` records the
same data whatever the pace and the host's load.
"""
from __future__ import annotations

import signal
import threading
from typing import Optional

import typer

from bench.commands.common import guarded

sim_app = typer.Typer(help="The simulated bench (every device on a real loopback transport).", no_args_is_help=True)


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")


def _check_speed(value: str) -> str:
    from bench.clock import parse_speed

    try:
        parse_speed(value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    return value


@sim_app.command("up")
@guarded
def up(
    speed: str = typer.Option("3600", "--speed", callback=_check_speed,
                              help="pace the driving process uses unless it gives its own --speed: at most this "
                                   "many bench seconds per wall second, or 'max' (as fast as the host can)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="noise seed (default: the scenario's); a seeded "
                                       "bench starts at a fixed bench instant"),
    scenario: str = typer.Option("default", "--scenario", help="scenario JSON file or a built-in name"),
    endpoints_json: Optional[str] = typer.Option(None, "--endpoints-json",
                                                 help="write the endpoints and a bench config here"),
    seconds: Optional[float] = typer.Option(None, "--seconds", help="stop after this many wall seconds"),
    gyros: Optional[int] = typer.Option(None, "--gyros", min=1, max=64, help="this many gyros in one chamber "
                                        "(each its own line, probes and supply channel; the bench config lists them)"),
) -> None:
    """Start chamber (Modbus TCP + RTU over TCP), turntable, gyro, PSU, DS18B20 tree and the clock
    endpoint; run until interrupted."""
    from bench.clock import parse_speed
    from bench.clocklink import ClockLinkServer
    from bench.sim.bench import lockstep_clock
    from bench.sim.multibench import simulated_bench

    pace = parse_speed(speed)
    # unpaced here: the driving process applies its pace before it asks for the next instant
    clock = lockstep_clock(None, seed)
    bench = simulated_bench(gyros, clock=clock, scenario=scenario, seed=seed).start()
    link = None
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    try:
        link = ClockLinkServer(clock).start()
        bench.clock_endpoint = link.to_json(pace)
        if endpoints_json:
            bench.write_endpoints(endpoints_json)
        for key, value in bench.endpoints.items():
            if key not in ("clock", "probes", "units"):
                typer.echo(f"{key}: {value}")
        typer.echo(f"clock: {link.address}")
        for slot, unit in (bench.endpoints.get("units") or {}).items():
            typer.echo(f"{slot}: gyro {unit['gyro']}, probes {unit['w1_root']}, supply channel {unit['psu_channel']}")
        typer.echo(f"simulated bench up in lockstep bench time, driven over {link.address} "
                   f"(default pace {'x' + format(pace, 'g') if pace else 'max'}); Ctrl-C to stop", err=True)
        done.wait(seconds)
    finally:
        if link is not None:
            link.stop()
        bench.stop()
