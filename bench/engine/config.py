"""Engine timing and supervision settings (bench seconds throughout).

Not part of ``BenchConfig`` yet; the integrator may nest it there as ``engine``.  ``Engine`` takes
one explicitly or uses these defaults.
"""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class EngineConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tick_s: float = Field(1.0, gt=0)             # loop period while recording / ramping / moving
    max_tick_s: float = Field(10.0, gt=0)        # loop period during plain soaks (data is drained every tick)
    probe_period_s: float = Field(2.0, gt=0)     # DS18B20 read period
    telemetry_period_s: float = Field(5.0, gt=0)  # chamber status period (also alarm checks)
    table_psu_period_s: float = Field(10.0, gt=0)  # turntable position / rate and PSU V, I, output period
    frame_batch: int = Field(2000, ge=1)         # frames handed to the store per batch at most
    frame_flush_s: float = Field(2.0, gt=0)      # ... or at least this often
    checkpoint_period_s: float = Field(120.0, gt=0)
    settle_s: float = Field(300.0, ge=0)         # after a suspension condition clears
    suspension_cap_s: float = Field(4 * 3600.0, gt=0)   # total suspended time before aborting
    frames_timeout_s: float = Field(10.0, gt=0)  # gyro powered but no frames for this long -> suspend
    frames_grace_s: float = Field(10.0, ge=0)    # after power-on before frames are expected
    probe_lost_reads: int = Field(3, ge=1)       # consecutive rejected/missing reads -> probe lost
    ramp_grace_s: float = Field(120.0, ge=0)     # wait this (+10 %) past the planned ramp end for the chamber
    ramp_done_tol_c: float = Field(0.1, gt=0)
    table_settle_s: float = Field(2.0, ge=0)     # duration estimate per orientation move
