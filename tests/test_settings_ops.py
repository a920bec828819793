"""Settings in one place (BENCH_* through pydantic-settings), generated tokens kept out of the log,
``GET /`` to the dashboard, ``python -m bench``."""
from __future__ import annotations

import stat
import subprocess
import sys

import pytest

from api.auth import parse_tokens
from bench.settings import load_settings, variables


def test_settings_read_the_environment_and_name_a_bad_variable(monkeypatch, tmp_path):
    for name, _, _ in variables():
        monkeypatch.delenv(name, raising=False)
    s = load_settings()
    assert s.database_url_or_default == "sqlite:///var/bench.sqlite" and s.stale_after_s == 15.0
    monkeypatch.setenv("BENCH_DATABASE_URL", f"sqlite:///{tmp_path / 'x.sqlite'}")
    monkeypatch.setenv("BENCH_STALE_AFTER_S", "2.5")
    from bench.storage.db import default_url
    assert default_url() == f"sqlite:///{tmp_path / 'x.sqlite'}" and load_settings().stale_after_s == 2.5
    monkeypatch.setenv("BENCH_STALE_AFTER_S", "soon")
    with pytest.raises(ValueError, match="BENCH_STALE_AFTER_S='soon'"):
        load_settings()
    monkeypatch.setenv("BENCH_STALE_AFTER_S", "-1")
    with pytest.raises(ValueError, match="BENCH_STALE_AFTER_S"):
        load_settings()
    monkeypatch.setenv("BENCH_STALE_AFTER_S", "1")
    monkeypatch.setenv("BENCH_LOG_FORMAT", "xml")
    with pytest.raises(ValueError, match="BENCH_LOG_FORMAT='xml'"):
        load_settings()


def test_readme_lists_every_variable():
    from pathlib import Path
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for name, _, _ in variables():
        assert f"| `{name}` |" in readme, name


def test_generated_tokens_go_to_a_private_file_not_the_log(monkeypatch, tmp_path, capsys):
    from bench.commands.service import _tokens_or_generate

    monkeypatch.delenv("BENCH_TOKENS", raising=False)
    target = tmp_path / "secrets" / "tokens"
    monkeypatch.setenv("BENCH_TOKENS_FILE", str(target))
    text = _tokens_or_generate()
    err = capsys.readouterr().err
    tokens = parse_tokens(text)
    assert sorted(tokens.values()) == ["admin", "operator", "viewer"]
    assert target.read_text().strip() == text
    assert stat.S_IMODE(target.stat().st_mode) == 0o600
    assert str(target.resolve()) in err
    for token in tokens:
        assert token not in err
    # a second start over an existing (say, world-readable) file: new tokens, still 0600
    target.chmod(0o644)
    again = _tokens_or_generate()
    assert again != text and stat.S_IMODE(target.stat().st_mode) == 0o600
    monkeypatch.setenv("BENCH_TOKENS", "admin:given-token-1")
    assert _tokens_or_generate() == "admin:given-token-1"


def test_root_redirects_to_the_dashboard(tmp_path):
    from fastapi.testclient import TestClient

    from api.app import create_app
    from bench.storage import open_database
    from tests.api_support import TOKENS

    db = open_database(f"sqlite:///{tmp_path / 'r.sqlite'}")
    with TestClient(create_app(db, tokens=TOKENS)) as c:
        r = c.get("/", follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"] == "/ui/"
        assert c.get("/").status_code == 200
    db.dispose()


def test_python_m_bench_runs_the_cli():
    r = subprocess.run([sys.executable, "-m", "bench", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "coefficients" in r.stdout and "Usage: bench" in r.stdout
    r = subprocess.run([sys.executable, "-m", "bench", "no-such-command"], capture_output=True, text=True)
    assert r.returncode == 2
