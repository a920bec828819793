"""Fixtures and frame builders shared by the storage tests (imported by tests/test_storage_*.py).

PostgreSQL variants use the session database of ``tests/conftest.py::pg_url``.
"""
from __future__ import annotations

import struct

import numpy as np
import pytest

from bench.interfaces import GyroFrame
from bench.storage import open_database, queries


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else crc << 1
        table.append(crc & 0xFFFFFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc32_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 (poly 0x04C11DB7, init 0xFFFFFFFF, no reflection, xorout 0) - device-protocols.md 3.1."""
    crc = 0xFFFFFFFF
    for b in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ _CRC_TABLE[((crc >> 24) ^ b) & 0xFF]
    return crc


def kvh_a_frame(host_time: float, seq: int, gyro_dps, accel_g=(0.0, 0.0, 1.0), status: int = 0x77,
                temp_centi: int = 2500) -> GyroFrame:
    """A KVH Format A frame exactly as on the wire (temperature set to 1/100 degC units)."""
    body = struct.pack(">I6fBBh", 0xFE81FF55, *gyro_dps, *accel_g, status, seq % 128, temp_centi)
    raw = body + struct.pack(">I", crc32_mpeg2(body))
    values = struct.unpack(">6f", raw[4:28])          # what a decoder would hand over (float32 values)
    return GyroFrame(host_time=host_time, sequence=seq % 128, gyro=values[:3], accel=values[3:], status=status,
                     temperature_c=temp_centi / 100.0, raw=raw)


def make_frames(n: int, *, t0: float = 1_700_000_000.0, rate_hz: float = 1000.0, seq0: int = 0,
                seed: int = 1) -> list[GyroFrame]:
    rng = np.random.default_rng(seed)
    gyro = rng.normal(0.0, 0.01, size=(n, 3)) + np.array([0.004, -0.002, 0.0042])
    accel = rng.normal(0.0, 0.001, size=(n, 3)) + np.array([0.0, 0.0, 1.0])
    temp = (2500 + np.arange(n) // 100).astype(int)
    jitter = rng.uniform(0, 2e-4, size=n)
    return [kvh_a_frame(t0 + i / rate_hz + jitter[i], seq0 + i, gyro[i], accel[i], temp_centi=int(temp[i]))
            for i in range(n)]


@pytest.fixture(scope="session", params=["sqlite", "postgresql"])
def db(request, tmp_path_factory):
    """A migrated database per backend, shared by the session (tests create their own runs).
    PostgreSQL comes from conftest's ``pg_url`` (fresh database; skip, or fail when CI=true)."""
    if request.param == "sqlite":
        database = open_database(f"sqlite:///{tmp_path_factory.mktemp('storage') / 'bench.sqlite'}")
    else:
        database = open_database(request.getfixturevalue("pg_url"))
    yield database
    database.dispose()


@pytest.fixture
def run_id(db) -> int:
    with db.session() as s:
        return queries.create_run(s, procedure="test", gyro_id="GYRO-1", bench_name="bench1",
                                  config_snapshot={"gyro": {"output_units": "deg/s"}}).id
