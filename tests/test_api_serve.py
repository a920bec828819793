"""``bench serve`` end to end: API + worker + simulated bench (real drivers over loopback) in one
process, on the embedded SQLite default and on PostgreSQL.  Through HTTP: start a shortened thermal_ramp, watch its
progress, stop it, start another, let it finish, fetch the coefficients by gyro ID.  The bench runs in
lockstep at x200 at most (the run's live document, ETA included, is published about every wall second);
the first run is held at a known bench instant (the lockstep clock's hold file) while it is watched and
stopped, so the test does not race the wall clock."""
from __future__ import annotations

import signal
from pathlib import Path

import httpx
import pytest

from tests.api_support import OPERATOR, SHORT_RAMP, TOKENS, TOKENS_TEXT, VIEWER
from tests.service_support import Services

T0 = 1_767_225_600.0          # a seeded simulated bench starts at this bench instant
VIEWER_TOKEN = next(tok for tok, role in TOKENS.items() if role == "viewer")


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request):
    """None = the embedded SQLite default; else a fresh PostgreSQL database of its own."""
    return None if request.param == "sqlite" else request.getfixturevalue("pg_fresh_url")


def test_serve_simulated_bench_end_to_end(tmp_path, database_url):
    hold = tmp_path / "hold"
    hold.write_text(repr(T0 + 150.0))       # in the first run's soak, about a fifth of the run
    # BENCH_DATABASE_URL None: the embedded default
    with Services(tmp_path, BENCH_DATABASE_URL=database_url, BENCH_TOKENS=TOKENS_TEXT,
                  BENCH_SIM_HOLD_FILE=str(hold)) as services:
        proc, base = services.serve("--speed", "200", "--seed", "3", token=VIEWER_TOKEN)
        bench = httpx.get(f"{base}/benches", headers=VIEWER, timeout=30).json()["benches"][0]
        assert bench["name"] == "sim1" and bench["devices"]["chamber"]["transport"] == "modbus_tcp"
        assert (tmp_path / "var" / "bench.sqlite").exists() == (database_url is None)
        params = dict(SHORT_RAMP, orientation=None)
        body = {"procedure": "thermal_ramp", "gyro_id": "SIM-42", "bench": "sim1", "params": params}
        first = httpx.post(f"{base}/runs", json=body, headers=OPERATOR, timeout=30).json()["id"]
        get = lambda rid: httpx.get(f"{base}/runs/{rid}", headers=VIEWER, timeout=30).json()   # noqa: E731
        marker = Path(str(hold) + ".held")
        services.wait_for(lambda: marker.exists() and float(marker.read_text()) == T0 + 150.0, "the hold instant",
                          proc)
        seen = services.wait_for(lambda: (d := get(first))["progress_percent"] > 10 and d["latest"].get("chamber")
                                 and d, "progress and readings at the hold", proc)
        assert seen["status"] == "running" and seen["eta_utc"]
        assert seen["sampling"]["probes"]["max_interval_s"] <= 2.0
        assert httpx.post(f"{base}/runs/{first}/stop", headers=OPERATOR, timeout=30).status_code == 202
        hold.unlink()
        ended = services.wait_for(lambda: (d := get(first))["status"] in ("completed", "aborted", "failed") and d,
                                  "first run stopped", proc)
        assert ended["outcome"] == "stopped", ended
        second = httpx.post(f"{base}/runs", json=body, headers=OPERATOR, timeout=30).json()["id"]
        done = services.wait_for(lambda: (d := get(second))["status"] in ("completed", "aborted", "failed") and d,
                                 "second run finished", proc)
        assert done["outcome"] == "completed", done
        assert list(done["fits"].values())[-1]["status"] == "done", done["fits"]
        coeffs = httpx.get(f"{base}/gyros/SIM-42/coefficients", headers=VIEWER, timeout=30)
        assert coeffs.status_code == 200, coeffs.text
        dyn = coeffs.json()["models"][0]
        assert dyn["model"] == "dynamic" and dyn["run_ids"] == [second] and set(dyn["channels"]) == {"x", "y", "z"}
        services.stop(proc, signal.SIGINT)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_serve_removes_its_w1_tree_on_sigint_and_sigterm(tmp_path, sig):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    # the simulated w1 tree goes under TMPDIR
    with Services(tmp_path, BENCH_DATABASE_URL=None, BENCH_TOKENS=TOKENS_TEXT, TMPDIR=str(tmp)) as services:
        proc, _ = services.serve("--speed", "200", token=VIEWER_TOKEN)
        assert list(tmp.glob("bench-w1-*")), "the simulated bench's w1 tree is not under TMPDIR"
        code = services.stop(proc, sig)
    assert code in (0, 128 + sig, -sig, 1), code
    assert list(tmp.glob("bench-w1-*")) == [], services.log_of(proc).read_text()[-2000:]
