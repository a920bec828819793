"""The ``bench`` command line (Typer).  Each group of commands lives in ``bench/commands/``."""
from __future__ import annotations

import typer

from bench.commands import fitting

app = typer.Typer(help="Gyro thermal-calibration bench: simulators, runs, fitting, close-the-loop, service.",
                  no_args_is_help=True, pretty_exceptions_show_locals=False)
fitting.register(app)


def _optional(module: str) -> None:
    """Command groups whose modules land later register themselves when importable."""
    import importlib

    try:
        mod = importlib.import_module(f"bench.commands.{module}")
    except ModuleNotFoundError as exc:
        if exc.name != f"bench.commands.{module}":
            raise
        return
    mod.register(app)


for _m in ("sim", "runs", "service", "demo"):
    _optional(_m)

if __name__ == "__main__":
    app()
