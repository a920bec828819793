"""Helpers shared by the ``tests/test_runs_*`` files (calling the ``bench`` CLI in-process), and unit
tests of the small pieces of ``bench.commands.runs``."""
from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from bench.cli import app


def cli(args: list[str]) -> tuple[int, str, str]:
    """Run ``bench ARGS`` in this process; (exit code, stdout, stderr)."""
    result = CliRunner().invoke(app, [str(a) for a in args], catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


def last_json(out: str) -> dict:
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert lines, "no output"
    return json.loads(lines[-1])


def test_parse_params_nested_json_and_text():
    from bench.commands.runs import parse_params

    got = parse_params(["points_c=[20, 30]", "soak_h=0.5", "orientation=NUE", "stable.tol_c=0.5",
                        "stable.probe_tol_c=null", "settle=stable"])
    assert got == {"points_c": [20, 30], "soak_h": 0.5, "orientation": "NUE", "settle": "stable",
                   "stable": {"tol_c": 0.5, "probe_tol_c": None}}
    with pytest.raises(typer.BadParameter, match="expected key=value"):
        parse_params(["soak_h"])
    with pytest.raises(typer.BadParameter, match="sub-keys"):
        parse_params(["stable=1", "stable.tol_c=2"])
