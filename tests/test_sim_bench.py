"""The whole simulated bench in one process (``bench sim up``), driven by the real drivers through the
endpoints it publishes: every device answers on its transport, the physics is wired (chamber air
heats the gyro probes, power switches the gyro on, the table orientation shows in the Earth rate)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.clock import clock_from_json
from bench.config import BenchConfig
from bench.devices.chamber import WatlowF4Chamber
from bench.devices.ds18b20 import W1ProbeArray
from bench.devices.gyro import GyroSerialLink
from bench.devices.orientation import angles_for
from bench.devices.psu import ScpiPowerSupply
from bench.devices.turntable import AcutrolTurntable
from bench.fit.base import EARTH_RATE_DPH
from bench.sim.bench import SimulatedBench
from tests.service_support import SAFETY_S

KEYS = {"chamber_modbus_tcp", "chamber_modbus_rtu", "turntable", "gyro", "psu", "w1_root"}


def _wait_for(path: Path, proc: subprocess.Popen, timeout_s: float = SAFETY_S) -> dict:
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        if path.exists():
            return json.loads(path.read_text())
        if proc.poll() is not None:
            raise AssertionError(f"bench sim up exited early: {proc.stderr.read()}")
        time.sleep(0.1)
    raise AssertionError("endpoints file never appeared")


def test_bench_sim_up_publishes_endpoints_that_the_drivers_use_unchanged(tmp_path):
    endpoints = tmp_path / "endpoints.json"
    proc = subprocess.Popen([sys.executable, "-m", "bench.cli", "sim", "up", "--speed", "600",
                             "--endpoints-json", str(endpoints), "--seconds", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        doc = _wait_for(endpoints, proc)
        assert KEYS <= set(doc)
        assert doc["chamber_modbus_tcp"].startswith("127.0.0.1:")
        for key in ("chamber_modbus_rtu", "turntable", "gyro", "psu"):
            assert doc[key].startswith("socket://127.0.0.1:"), key
        assert Path(doc["w1_root"]).is_dir()
        config = BenchConfig.model_validate(doc["bench_config"])
        clock = clock_from_json(doc["clock"])            # drives the simulator process's bench time
        chamber = WatlowF4Chamber(config.chamber, clock)
        assert -40 < chamber.read_temperature() < 60
        chamber.set_setpoint(30.0)
        assert chamber.read_setpoint() == pytest.approx(30.0)
        rtu = WatlowF4Chamber(config.chamber.model_copy(update={"transport": "modbus_rtu",
                                                                "address": doc["chamber_modbus_rtu"]}), clock)
        assert rtu.read_setpoint() == pytest.approx(30.0)
        table = AcutrolTurntable(config.turntable, clock)
        assert table.identify().startswith("Acutronic")
        psu = ScpiPowerSupply(config.psu)
        psu.output(True)
        assert psu.output_state() is True
        probes = W1ProbeArray(config.probes)
        readings = probes.read_all()
        assert {r.name for r in readings} == set(config.probes.probes)
        assert all(r.celsius is not None for r in readings)
        link = GyroSerialLink(config.gyro, clock)
        link.start()
        try:
            frames = []
            for _ in range(20):                           # 1 Hz frames: one per bench second served
                clock.sleep(1.0)
                frames += link.drain()
            assert len(frames) >= 20
            assert link.stats.bad_crc == 0
        finally:
            link.stop()
        for dev in (chamber, rtu, table, psu):
            dev.close()
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert proc.returncode == 0, proc.stderr.read()


def test_physics_is_wired_between_devices():
    """Chamber heat reaches the probes; the table orientation shows in the gyro's Earth-rate reading."""
    with SimulatedBench(speed=1200, scenario="default") as bench:
        cfg = bench.config
        chamber = WatlowF4Chamber(cfg.chamber, bench.clock)
        table = AcutrolTurntable(cfg.turntable, bench.clock)
        psu = ScpiPowerSupply(cfg.psu)
        probes = W1ProbeArray(cfg.probes)
        t_start = np.mean([r.celsius for r in probes.read_all()])
        chamber.ramp_to(45.0, 5.0)
        psu.output(True)
        bench.clock.sleep(3600)                       # an hour of bench time
        t_end = np.mean([r.celsius for r in probes.read_all()])
        assert t_end > t_start + 10
        # orientation: z up (ENU) vs z down (ESD); the z channel sees +/- the vertical Earth rate
        link = GyroSerialLink(cfg.gyro, bench.clock)
        link.start()
        try:
            means = {}
            for code in ("ENU", "ESD"):
                outer, inner = angles_for(code, cfg.turntable.geometry)
                table.interlock_close(1)
                table.interlock_close(2)
                table.move_to(1, outer)
                table.move_to(2, inner)
                bench.clock.sleep(60)
                link.drain()
                t_from = bench.clock.now()
                frames = []
                deadline = time.time() + 20
                while len(frames) < 300 and time.time() < deadline:
                    bench.clock.sleep(120)
                    frames += [f for f in link.drain() if f.host_time > t_from]
                assert len(frames) >= 300
                means[code] = np.mean([f.gyro[2] for f in frames]) * 3600.0   # deg/h
            vertical = EARTH_RATE_DPH * np.sin(np.radians(bench.scenario.latitude_deg))
            assert means["ENU"] - means["ESD"] == pytest.approx(2 * vertical, abs=1.5)
        finally:
            link.stop()
            for dev in (chamber, table, psu):
                dev.close()
