"""``bench serve`` end to end: API + worker + simulated bench (real drivers over loopback) in one
process, on the embedded SQLite default and on PostgreSQL.  Through HTTP: start a shortened thermal_ramp, watch its
progress, stop it, start another, let it finish, fetch the coefficients by gyro ID.  The first run is
held at a known bench instant (the lockstep clock's hold file) while it is watched and stopped, so the
test does not race the wall clock."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.api_support import OPERATOR, SHORT_RAMP, TOKENS_TEXT, VIEWER, wait_for
from tests.test_api_process import free_port

BENCH = str(Path(sys.executable).with_name("bench"))
T0 = 1_767_225_600.0          # a seeded simulated bench starts at this bench instant


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request):
    """None = the embedded SQLite default; else the session's fresh PostgreSQL database."""
    return None if request.param == "sqlite" else request.getfixturevalue("pg_url")


def test_serve_simulated_bench_end_to_end(tmp_path, database_url):
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "BENCH_DATABASE_URL"}   # the embedded default
    if database_url:
        env["BENCH_DATABASE_URL"] = database_url
    env["BENCH_TOKENS"] = TOKENS_TEXT
    hold = tmp_path / "hold"
    env["BENCH_SIM_HOLD_FILE"] = str(hold)
    hold.write_text(repr(T0 + 150.0))       # in the first run's soak, about a fifth of the run
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen([BENCH, "serve", "--port", str(port), "--speed", "200", "--seed", "3",
                             "--log-level", "warning"],
                            cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        def online():
            try:
                benches = httpx.get(f"{base}/benches", headers=VIEWER, timeout=2).json()["benches"]
            except httpx.HTTPError:
                return False
            return benches and benches[0]["online"] and benches[0]
        bench = wait_for(online, 30, "bench serve up with its simulated bench", interval=0.2)
        assert bench["name"] == "sim1" and bench["devices"]["chamber"]["transport"] == "modbus_tcp"
        assert (tmp_path / "var" / "bench.sqlite").exists() == (database_url is None)
        params = dict(SHORT_RAMP, orientation=None)
        body = {"procedure": "thermal_ramp", "gyro_id": "SIM-42", "bench": "sim1", "params": params}
        first = httpx.post(f"{base}/runs", json=body, headers=OPERATOR, timeout=10).json()["id"]
        get = lambda rid: httpx.get(f"{base}/runs/{rid}", headers=VIEWER, timeout=10).json()   # noqa: E731
        marker = Path(str(hold) + ".held")
        wait_for(lambda: marker.exists() and float(marker.read_text()) == T0 + 150.0, 60, "the hold instant")
        seen = wait_for(lambda: (d := get(first))["progress_percent"] > 10 and d["latest"].get("chamber") and d,
                        30, "progress and readings at the hold")
        assert seen["status"] == "running" and seen["eta_utc"]
        assert seen["sampling"]["probes"]["max_interval_s"] <= 2.0
        assert httpx.post(f"{base}/runs/{first}/stop", headers=OPERATOR, timeout=10).status_code == 202
        hold.unlink()
        ended = wait_for(lambda: (d := get(first))["status"] in ("completed", "aborted", "failed") and d, 30,
                         "first run stopped")
        assert ended["outcome"] == "stopped", ended
        second = httpx.post(f"{base}/runs", json=body, headers=OPERATOR, timeout=10).json()["id"]
        done = wait_for(lambda: (d := get(second))["status"] in ("completed", "aborted", "failed") and d, 40,
                        "second run finished")
        assert done["outcome"] == "completed", done
        assert list(done["fits"].values())[-1]["status"] == "done", done["fits"]
        coeffs = httpx.get(f"{base}/gyros/SIM-42/coefficients", headers=VIEWER, timeout=10)
        assert coeffs.status_code == 200, coeffs.text
        dyn = coeffs.json()["models"][0]
        assert dyn["model"] == "dynamic" and dyn["run_ids"] == [second] and set(dyn["channels"]) == {"x", "y", "z"}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_serve_removes_its_w1_tree_on_sigint_and_sigterm(tmp_path, sig):
    port = free_port()
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "BENCH_DATABASE_URL"}
    env.update(BENCH_TOKENS=TOKENS_TEXT, TMPDIR=str(tmp))           # the simulated w1 tree goes under TMPDIR
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen([BENCH, "serve", "--port", str(port), "--speed", "200", "--log-level", "warning"],
                            cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        def online():
            try:
                return httpx.get(f"http://127.0.0.1:{port}/benches", headers=VIEWER, timeout=2).json()["benches"]
            except httpx.HTTPError:
                return False
        wait_for(online, 30, "bench serve up", interval=0.2)
        assert list(tmp.glob("bench-w1-*")), "the simulated bench's w1 tree is not under TMPDIR"
        proc.send_signal(sig)
        code = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code in (0, 128 + sig, -sig, 1), code
    assert list(tmp.glob("bench-w1-*")) == [], (tmp_path / "serve.log").read_text()[-2000:]
