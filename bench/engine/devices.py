"""The bundle of device interfaces the engine drives (protocols from ``bench.interfaces``)."""
from __future__ import annotations

from dataclasses import dataclass

from bench.interfaces import Chamber, GyroLink, PowerSupply, ProbeArray, Turntable


@dataclass
class Devices:
    chamber: Chamber
    turntable: Turntable
    gyro: GyroLink
    probes: ProbeArray
    psu: PowerSupply
