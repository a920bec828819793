"""Fencing drill, on SQLite and PostgreSQL: the worker executing a run freezes past its lease (a
simulated SIGSTOP: its engine thread is held inside a device call and its heartbeat thread is held),
a second worker takes the run over and completes it; when the first wakes (SIGCONT), it sends no
command to any device, writes nothing to the run, leaves its run loop; the run ends ``completed`` and
every frame index is stored once.

The doubles run on a lockstep clock: bench time stands at a known instant (a third into the run)
while the test checks that A drives the run and arms the freeze, so A freezes there, mid-run, whatever
the load.  The freeze is deterministic: the first worker cannot go on while frozen, whatever the wall
clock does; the test waits on states (hold, takeover, completion), never on a duration.
"""
from __future__ import annotations

import threading

from sqlalchemy import select

from bench.storage import queries
from bench.storage.models import Event, FrameChunk
from bench.engine import Devices
from tests.api_support import SHORT_RAMP, T0, DoublesBench, register_bench, start_worker, unique_bench, wait_for
from tests.service_support import SAFETY_S, hold_clock_at

FREEZE_AT = T0 + 400.0          # in the 720-s soak of the run (about 1300 bench s in all)


class Freezer:
    """Records every call the worker's devices receive; once ``freeze`` is set, the next call (made, so
    sent before the stop) holds its thread until ``thaw``."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.freeze = threading.Event()
        self.frozen = threading.Event()
        self.thaw = threading.Event()
        self.calls_at_freeze: int | None = None

    def hold(self) -> None:
        if self.freeze.is_set() and not self.thaw.is_set():
            if self.calls_at_freeze is None:
                self.calls_at_freeze = len(self.calls)
                self.frozen.set()
            self.thaw.wait()


class Recorded:
    def __init__(self, name: str, device, freezer: Freezer) -> None:
        self._name, self._device, self._freezer = name, device, freezer

    def __getattr__(self, attr):
        value = getattr(self._device, attr)
        if not callable(value):
            return value

        def call(*args, **kwargs):
            result = value(*args, **kwargs)
            self._freezer.calls.append(f"{self._name}.{attr}")
            self._freezer.hold()
            return result

        return call


def test_a_worker_frozen_past_its_lease_wakes_fenced_and_the_run_completes(db):
    name = unique_bench()
    register_bench(db, name)
    doubles = DoublesBench.lockstep()
    clock = doubles.clock
    clock.hold_at(FREEZE_AT)                                   # before any worker drives the clock
    freezer = Freezer()

    plain = doubles.factory

    def recorded_factory(config):              # worker A's devices only
        d = plain(config)
        return Devices(**{k: Recorded(k, getattr(d, k), freezer) for k in ("chamber", "turntable", "gyro",
                                                                          "probes", "psu")})

    with db.session() as s:
        run_id = queries.create_run(s, procedure="thermal_ramp", parameters=dict(SHORT_RAMP, soak_h=0.2),
                                    gyro_id="RLG-F", bench_name=name).id
    doubles.factory = recorded_factory
    a, a_thread = start_worker(db, name, doubles)
    doubles.factory = plain
    beat = a._heartbeat

    def frozen_heartbeat(rid):
        if freezer.freeze.is_set():
            freezer.thaw.wait()
        beat(rid)

    a._heartbeat = frozen_heartbeat
    b = None
    try:
        hold_clock_at(clock, FREEZE_AT, ended=lambda: run_id in dict(a.runs_done))
        assert a.current_run == run_id and len(freezer.calls) > 50, "worker A driving the run"
        assert _run(db, run_id).status == "running"
        freezer.freeze.set()                                   # SIGSTOP at A's next device call
        clock.release()
        wait_for(freezer.frozen.is_set, SAFETY_S, "worker A frozen")
        assert FREEZE_AT <= clock.now() < FREEZE_AT + 10.0     # mid-run: within a tick of the hold
        b, b_thread = start_worker(db, name, doubles)
        wait_for(lambda: _run(db, run_id).worker == b.worker_id, SAFETY_S, "worker B taking the run over")
        done = wait_for(lambda: (r := _run(db, run_id)).status in ("completed", "failed", "aborted") and r, SAFETY_S,
                        "the run to end under worker B")
        assert done.status == "completed", done.error
        frozen_at = freezer.calls_at_freeze
        freezer.thaw.set()                                     # SIGCONT
        wait_for(lambda: any(rid == run_id for rid, _ in a.runs_done), SAFETY_S,
                 "worker A leaving its run loop")
        assert dict(a.runs_done)[run_id] == "lost"
        # after the wake: no command; only its own connections released (close_devices: the link's reader
        # thread and ports closed, nothing sent)
        assert freezer.calls[frozen_at:] == ["gyro.stop", "chamber.close", "turntable.close", "psu.close"], \
            "worker A touched a device after losing its lease"
        final = _run(db, run_id)
        assert final.status == "completed" and final.worker == b.worker_id and final.error is None
        with db.session() as s:
            chunks = s.execute(select(FrameChunk.first_index, FrameChunk.count).where(FrameChunk.run_id == run_id)
                               .order_by(FrameChunk.first_index)).all()
            kinds = [e.kind for e in s.scalars(select(Event).where(Event.run_id == run_id))]
        expected = 0
        for first_index, count in chunks:                     # every index exactly once
            assert first_index == expected
            expected += count
        assert expected > 0 and "worker_takeover" in kinds and "run_failed" not in kinds
    finally:
        clock.release()
        freezer.thaw.set()
        a.stop()
        if b is not None:
            b.stop()
        a_thread.join(30)
        if b is not None:
            b_thread.join(30)


def _run(db, run_id):
    with db.session() as s:
        run = queries.get_run(s, run_id)
        s.expunge(run)
        return run


def test_a_run_left_suspended_before_its_first_checkpoint_is_started_again_by_the_next_worker(db):
    """A worker died (or froze) after its run was suspended from the first chamber reading, before any
    checkpoint: the worker taking the run over starts it from the beginning (it used to fail it: 'only
    a queued run can start')."""
    import datetime as dt

    from bench.storage.models import utcnow

    name = unique_bench()
    register_bench(db, name)
    with db.session() as s:
        run = queries.create_run(s, procedure="thermal_ramp", parameters=SHORT_RAMP, gyro_id="RLG-S", bench_name=name)
        run_id = run.id
        queries.stamp_run_status(run, "running", utcnow())
        queries.stamp_run_status(run, "suspended", utcnow())
        run.worker, run.heartbeat_at = "gone@elsewhere", utcnow() - dt.timedelta(hours=1)
    w, thread = start_worker(db, name, DoublesBench.lockstep())
    try:
        done = wait_for(lambda: (r := _run(db, run_id)).status in ("completed", "failed", "aborted") and r, SAFETY_S,
                        "the run to end under the new worker")
    finally:
        w.stop()
        thread.join(30)
    assert done.status == "completed" and done.error is None and done.worker == w.worker_id
    with db.session() as s:
        kinds = [e.kind for e in s.scalars(select(Event).where(Event.run_id == run_id))]
    assert "worker_takeover" in kinds and "run_started" in kinds and "run_failed" not in kinds
