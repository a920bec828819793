"""Service processes for the tests, started one way: the API under uvicorn, ``bench serve``, ``bench
worker`` (a bench or analysis worker) and helper modules run with ``python -m``; and waiting on state.

Every wait here is for an event (a health answer, a marker file, a stored status), never for a span of
time.  Deadlines are safety nets only, sized for a loaded 2-core machine (two CPU-bound processes beside
the suite): ``SAFETY_S`` is well over ten times what any of these waits takes on an idle machine.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import httpx

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
SAFETY_S = 300.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.05,
             proc: subprocess.Popen | None = None, log: Path | None = None):
    """The first truthy value of ``predicate()``, polled every ``interval`` wall seconds.  Fails naming
    ``what`` after ``timeout`` wall seconds, or as soon as ``proc`` (the process that should bring the
    event about) has ended, with the tail of its ``log``."""
    deadline = time.monotonic() + timeout
    last = None
    while True:
        last = predicate()
        if last:
            return last
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"waiting for {what}: the process ended with {proc.returncode}"
                                 f"{_tail(log)}")
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r}){_tail(log)}")
        time.sleep(interval)


def _tail(log: Path | None, chars: int = 3000) -> str:
    if log is None or not log.exists():
        return ""
    return f"\n--- {log.name} ---\n{log.read_text(errors='replace')[-chars:]}"


def http_ok(url: str, headers: dict[str, str] | None = None):
    """The JSON document at ``url`` when it answers 200, else None (not up yet)."""
    try:
        r = httpx.get(url, headers=headers, timeout=5)
    except httpx.HTTPError:
        return None
    return (r.json() if r.headers.get("content-type", "").startswith("application/json") else True) \
        if r.status_code == 200 else None


def hold_bench_at(hold: Path, t: float, timeout: float = SAFETY_S, proc: subprocess.Popen | None = None,
                  log: Path | None = None) -> None:
    """Let a lockstep clock's bench time (``BENCH_SIM_HOLD_FILE`` / ``LockstepClock(hold_file=...)``) run
    on to ``t`` and wait until it stands there (its ``.held`` marker names ``t``)."""
    tmp = hold.with_name(hold.name + ".tmp")
    tmp.write_text(repr(t))
    tmp.replace(hold)
    marker = hold.with_name(hold.name + ".held")
    wait_for(lambda: marker.exists() and marker.read_text() == repr(t), timeout, f"bench time held at {t}",
             proc=proc, log=log)


def start_held_run(cli_args: list[str], cwd: Path, hold: Path, hold_t: float) -> tuple[subprocess.Popen, int]:
    """Start ``bench <cli_args>`` (with ``--json``) in a process whose lockstep bench time stops at
    ``hold_t`` (its ``BENCH_SIM_HOLD_FILE``), and return the process and the run id it prints first on
    stderr.  The caller kills the process (it is left running)."""
    hold.write_text(repr(hold_t))
    env = dict(os.environ, PYTHONPATH=str(ROOT), BENCH_SIM_HOLD_FILE=str(hold))
    proc = subprocess.Popen([sys.executable, "-m", "bench.cli", *cli_args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stderr.readline().decode()      # with --json, "run <ID>" goes to stderr
    while first and not first.startswith("run "):
        first = proc.stderr.readline().decode()
    if not first.startswith("run "):
        proc.kill()
        raise AssertionError(f"bench {' '.join(cli_args)} printed no run id: {proc.stderr.read().decode()[-3000:]}")
    return proc, int(first.split()[1])


def hold_clock_at(clock, t: float, ended: Callable[[], Any] | None = None, timeout: float = SAFETY_S) -> None:
    """The same in one process: let the thread driving ``clock`` (a ``LockstepClock``) go on to bench time
    ``t`` and wait until it stands there (``t`` served, nothing done at ``t`` yet); it stays there until
    ``clock.release()`` or the next hold.  ``ended()`` true means the driver can no longer get there
    (its run ended): fail at once rather than at the safety net."""
    clock.hold_at(t)

    def held():
        if clock.wait_held(0.05):
            return True
        if ended is not None and ended():
            raise AssertionError(f"the run ended before bench time {t} (it stopped at {clock.now()})")
        return False
    wait_for(held, timeout, f"bench time held at {t}", interval=0.0)


def hold_clock_until(clock, predicate: Callable[[], Any], step_s: float, limit_s: float,
                     ended: Callable[[], Any] | None = None) -> float:
    """Hold ``clock`` at every ``step_s`` bench seconds from now until ``predicate()`` is true at a hold
    (evaluated while the driver stands still); fails after ``limit_s`` bench seconds.  The instant it
    holds at: the same one on every run of a deterministic bench, however loaded the host."""
    t = clock.now()
    end = t + limit_s
    while True:
        t += step_s
        hold_clock_at(clock, t, ended)
        if predicate():
            return t
        if t >= end:
            raise AssertionError(f"not there after {limit_s} bench seconds of holds every {step_s} s")


class Services:
    """The processes one test starts, each logging to ``<tmp>/<log>``; ``close()`` (or leaving the
    ``with`` block) ends those still running: SIGTERM, then SIGKILL after ``SAFETY_S / 10``.  ``env``
    adds to the environment of every process (a value ``None`` removes the variable)."""

    def __init__(self, tmp: Path, **env: str | None) -> None:
        self.tmp = tmp
        self.env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", **env}
        self.procs: list[subprocess.Popen] = []
        self.logs: dict[int, Path] = {}

    def __enter__(self) -> "Services":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def spawn(self, args: list[str], log: str, **env: str | None) -> subprocess.Popen:
        path = self.tmp / log
        full_env = {k: v for k, v in {**self.env, **env}.items() if v is not None}
        with open(path, "ab") as out:
            proc = subprocess.Popen(args, cwd=self.tmp, env=full_env, stdout=out, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        self.logs[proc.pid] = path
        return proc

    def log_of(self, proc: subprocess.Popen) -> Path:
        return self.logs[proc.pid]

    def wait_for(self, predicate: Callable[[], Any], what: str, proc: subprocess.Popen | None = None,
                 timeout: float = SAFETY_S, interval: float = 0.05):
        return wait_for(predicate, timeout, what, interval, proc=proc,
                        log=self.log_of(proc) if proc is not None else None)

    # ---- the services ------------------------------------------------------------------------------
    def api(self, log: str = "api.log", **env: str | None) -> tuple[subprocess.Popen, str]:
        """The HTTP API (``api.app:app_from_env``) on a free port, once ``/health`` answers."""
        port = free_port()
        proc = self.spawn([PY, "-m", "uvicorn", "--factory", "api.app:app_from_env", "--host", "127.0.0.1",
                           "--port", str(port), "--log-level", "warning"], log, **env)
        base = f"http://127.0.0.1:{port}"
        self.wait_for(lambda: http_ok(f"{base}/health"), "the API to answer /health", proc)
        return proc, base

    def serve(self, *args: str, token: str, log: str = "serve.log", **env: str | None) -> tuple[subprocess.Popen, str]:
        """``bench serve ARGS`` on a free port, once it lists an online bench to a viewer's ``token``."""
        port = free_port()
        proc = self.spawn([PY, "-m", "bench.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
                           "--log-level", "warning", *args], log, **env)
        base = f"http://127.0.0.1:{port}"

        def online():
            doc = http_ok(f"{base}/benches", {"Authorization": f"Bearer {token}"})
            return bool(doc and doc["benches"] and doc["benches"][0]["online"])
        self.wait_for(online, "bench serve to show an online bench", proc)
        return proc, base

    def worker(self, *args: str, log: str = "worker.log", **env: str | None) -> subprocess.Popen:
        """``bench worker ARGS`` (``--bench NAME ...`` or ``--analysis``)."""
        return self.spawn([PY, "-m", "bench.cli", "worker", *args], log, **env)

    # ---- ending them --------------------------------------------------------------------------------
    def kill(self, proc: subprocess.Popen) -> None:
        """kill -9, and reap it."""
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=SAFETY_S / 10)

    def stop(self, proc: subprocess.Popen, sig: int = signal.SIGTERM) -> int:
        """Ask it to end (``sig``); SIGKILL when it has not within the safety net.  Its exit code."""
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(timeout=SAFETY_S / 10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def close(self) -> None:
        for proc in self.procs:
            self.stop(proc)
        self.procs.clear()
