"""Third-party Modbus master (Debian ``mbpoll``) against the chamber simulator, TCP and RTU.

RTU: ``socat`` bridges a pty to the simulator's RTU-over-TCP port, so mbpoll drives a real tty
with RTU framing.  ``-0`` makes mbpoll use PDU addressing, so register 100 goes out as 100.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import time

import pytest

from bench.clock import SteppedClock
from bench.sim.chamber import ChamberSimulator
from bench.sim.chamber_physics import ChamberModel

pytestmark = pytest.mark.skipif(shutil.which("mbpoll") is None or shutil.which("socat") is None,
                                reason="needs Debian mbpoll and socat")


@pytest.fixture
def sim():
    simulator = ChamberSimulator(ChamberModel(air_c=25.0, setpoint_c=25.0), SteppedClock()).start()
    yield simulator
    simulator.stop()


@pytest.fixture
def pty_link(sim, tmp_path):
    link = str(tmp_path / "ttyF4")
    port = sim.rtu_url.rsplit(":", 1)[1]
    bridge = subprocess.Popen(["socat", f"pty,link={link},raw,echo=0", f"tcp:127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 5
        while not os.path.exists(link):
            if time.monotonic() > deadline or bridge.poll() is not None:
                pytest.fail("socat did not create the pty link")
            time.sleep(0.02)
        yield link
    finally:
        bridge.terminate()
        bridge.wait(5)


def _run(cmd: list[str], values) -> tuple[int, str]:
    proc = subprocess.run([*cmd, *[str(v) for v in values]], capture_output=True, text=True, timeout=15)
    return proc.returncode, proc.stdout + proc.stderr


def read_value(output: str, reg: int) -> int:
    match = re.search(rf"^\[{reg}\]:\s+(-?\d+)", output, re.MULTILINE)
    assert match, output
    return int(match.group(1))


def _tcp(sim) -> tuple[list[str], str]:
    return ["-m", "tcp", "-p", sim.tcp_address.rsplit(":", 1)[1]], "127.0.0.1"


def _rtu(link: str) -> tuple[list[str], str]:
    return ["-m", "rtu", "-b", "9600", "-P", "none"], link


def _check_read_write(sim, options: list[str], target: str) -> None:
    base = ["mbpoll", *options, "-a", "1", "-0", "-1", "-o", "1"]
    code, out = _run([*base, "-r", "100", "-c", "1", target], [])
    assert code == 0, out
    assert read_value(out, 100) == 250
    code, out = _run([*base, "-r", "300", target], [412])
    assert code == 0, out
    assert sim.model.setpoint_c == pytest.approx(41.2)
    code, out = _run([*base, "-r", "300", "-c", "1", target], [])
    assert read_value(out, 300) == 412
    code, out = _run([*base, "-r", "300", target], [2000])        # 200.0 C > 180.0 limit
    assert code != 0 and "Illegal data value" in out, out
    assert sim.model.setpoint_c == pytest.approx(41.2)


def test_mbpoll_tcp_reads_pv_and_writes_setpoint(sim):
    _check_read_write(sim, *_tcp(sim))


def test_mbpoll_rtu_through_pty_reads_pv_and_writes_setpoint(sim, pty_link):
    _check_read_write(sim, *_rtu(pty_link))
