"""Helpers for the operator-service tests (tests/test_api_*.py): tokens, a database per test, the
device doubles of tests/test_engine_doubles.py on an accelerated or a lockstep clock, an in-process
worker."""
from __future__ import annotations

import itertools
import uuid
from typing import Any

from bench.clock import LockstepClock
from bench.config import BenchConfig, TurntableConfig
from bench.devices.orientation import EIGHT_POSITION_GEOMETRY
from bench.engine import Devices, EngineConfig
from tests.service_support import wait_for  # noqa: F401 - the tests' one wait helper
from tests.test_engine_doubles import DoubleChamber, DoubleLink, DoubleProbes, DoublePsu, DoubleTable, Thermal

TOKENS = {"viewer-token-1": "viewer", "operator-token-1": "operator", "admin-token-1": "admin"}
VIEWER = {"Authorization": "Bearer viewer-token-1"}
OPERATOR = {"Authorization": "Bearer operator-token-1"}
ADMIN = {"Authorization": "Bearer admin-token-1"}
TOKENS_TEXT = ",".join(f"{role}:{tok}" for tok, role in TOKENS.items())

SHORT_RAMP = dict(orientation="WSU", start_c=30.0, soak_h=0.05, warmup_min=1.0, rate_c_per_min=2.0, end_c=20.0,
                  final_hold_min=2.0)
_names = itertools.count()
T0 = 1_767_225_600.0          # the bench instant a lockstep ``DoublesBench`` starts at


def bench_config(name: str) -> BenchConfig:
    return BenchConfig(name=name, turntable=TurntableConfig(geometry=EIGHT_POSITION_GEOMETRY),
                       probes={"probes": {n: f"0000000000{i + 1:02x}" for i, n in enumerate(("t1", "t2", "t3", "t4"))}})


def engine_config() -> EngineConfig:
    return EngineConfig(tick_s=1.0, max_tick_s=10.0, probe_period_s=2.0, telemetry_period_s=5.0,
                        checkpoint_period_s=30.0, settle_s=60.0, frames_timeout_s=10.0, frames_grace_s=5.0)


class DoublesBench:
    """Device doubles sharing one thermal model on ``clock``; ``factory`` opens a fresh bundle per run
    (as real drivers would be).  Tests build them with ``lockstep``: on a clock that runs ahead of the
    wall (an ``AcceleratedClock``) a loaded host falls behind the frames it must store and a run never
    ends."""

    def __init__(self, clock, start_c: float = 30.0) -> None:
        self.clock = clock
        self.thermal = Thermal(self.clock, start_c)
        self.opened = 0

    @classmethod
    def lockstep(cls, pace: float | None = None, start_c: float = 30.0) -> "DoublesBench":
        """The doubles on a ``LockstepClock`` starting at ``T0``: bench time moves only when a run's engine
        sleeps (at most ``pace`` x wall; None: as fast as the host can), so ``hold_at`` can stop a run at
        a known bench instant whatever the load (``tests.service_support.hold_clock_at``)."""
        return cls(LockstepClock(T0, pace), start_c=start_c)

    def factory(self, config: BenchConfig) -> Devices:
        self.opened += 1
        psu = DoublePsu()
        return Devices(DoubleChamber(self.thermal), DoubleTable(self.clock), DoubleLink(self.clock, psu, self.thermal),
                       DoubleProbes(self.thermal), psu)


def unique_bench() -> str:
    return f"b{next(_names)}-{uuid.uuid4().hex[:4]}"


def start_worker(db, name: str, doubles: DoublesBench, **kw: Any):
    from bench.worker import Worker
    opts = dict(engine_config=engine_config(), heartbeat_s=0.2, stale_after_s=1.5, poll_s=0.05)
    opts.update(kw)
    w = Worker(db, name, bench_config(name), doubles.factory, doubles.clock, **opts)
    t = w.start_thread()
    return w, t


def register_bench(db, name: str) -> None:
    import json

    from bench.storage import queries
    with db.session() as s:
        queries.ensure_bench(s, name, json.loads(bench_config(name).model_dump_json()))

