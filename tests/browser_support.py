"""The dashboard's browser tests, one way: ``bench serve`` on a seeded simulated bench in lockstep (a
hold file stops bench time at known instants) and headless Chromium (Debian
``chromium`` driven by PyPI ``playwright``, never ``playwright install``).  Screenshots go to
``test-artifacts/dashboard/``."""
from __future__ import annotations

import contextlib
import json
import shutil
import urllib.request
from pathlib import Path
from typing import Iterator

import pytest

from tests.service_support import ROOT, SAFETY_S, Services, hold_bench_at

ARTIFACTS = ROOT / "test-artifacts" / "dashboard"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-quic", "--disable-component-update", "--disable-sync"]
TOKENS = {"viewer": "viewer-dash-token", "operator": "operator-dash-token", "admin": "admin-dash-token"}
T0 = 1_767_225_600.0          # a seeded simulated bench starts at this bench instant (bench.sim.bench)
SAFETY_MS = SAFETY_S * 1000   # a safety net for waits on the page (see tests/service_support.py)


def get_json(url: str, token: str | None = None, timeout: float = 30.0):
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


def post_json(url: str, body: dict, token: str, timeout: float = 60.0):
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


class Dashboard:
    """A running ``bench serve``: its URL, and its simulated bench's hold file."""

    def __init__(self, base: str, hold: Path, services: Services, proc) -> None:
        self.base, self.hold, self.services, self.proc = base, hold, services, proc

    def hold_at(self, t: float) -> None:
        """Let bench time run on to ``t`` and wait until it stands there."""
        hold_bench_at(self.hold, t, proc=self.proc, log=self.services.log_of(self.proc))

    def release(self) -> None:
        self.hold.unlink(missing_ok=True)


@contextlib.contextmanager
def dashboard_service(tmp: Path, database_url: str | None = None, hold_at: float | None = None,
                      speed: str = "max", serve_args: tuple[str, ...] = ()) -> Iterator[Dashboard]:
    """``bench serve --speed SPEED --seed 0 [SERVE_ARGS]`` on ``database_url`` (default: an SQLite file in ``tmp``);
    with ``hold_at`` its bench time stops at that instant until ``Dashboard.hold_at``/``release``
    moves or lifts the hold.  What a held run shows: its stored progress (``progress_percent``) as of
    its last checkpoint, taken on the bench-time schedule; its live document (elapsed, remaining) as of
    the worker's last publish, about every wall second, so a page that reads those at a hold needs a
    paced clock (``speed``: at most that many bench seconds per wall second) to have it recent."""
    database_url = database_url or f"sqlite:///{tmp / 'bench.sqlite'}"
    hold = tmp / "bench.hold"
    if hold_at is not None:
        hold.write_text(repr(hold_at))
    with Services(tmp, BENCH_DATABASE_URL=database_url, BENCH_SIM_HOLD_FILE=str(hold),
                  BENCH_TOKENS=",".join(f"{role}:{tok}" for role, tok in TOKENS.items())) as services:
        proc, base = services.serve("--speed", speed, "--seed", "0", *serve_args, token=TOKENS["viewer"])
        try:
            yield Dashboard(base, hold, services, proc)
        finally:
            hold.unlink(missing_ok=True)
            services.stop(proc)
            if ARTIFACTS.exists():
                shutil.copy(services.log_of(proc), ARTIFACTS / f"serve-{tmp.name}.log")


@contextlib.contextmanager
def chromium_context(viewport: dict[str, int]):
    """A fresh context of headless Chromium with this viewport (skips when Chromium is not installed)."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} is missing: apt-get install -y chromium chromium-driver (scripts/install.sh)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            context = browser.new_context(viewport=viewport)
            context.set_default_timeout(SAFETY_MS)
            try:
                yield context
            finally:
                context.close()
        finally:
            browser.close()


def shot(page, name: str) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def use_token(page, token: str) -> None:
    if page.locator("#token-form").is_hidden():
        page.click("#token-change")
    page.fill("#token-input", token)
    page.click("#token-save")
