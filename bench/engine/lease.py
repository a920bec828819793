"""A worker's lease on the run it executes, checked before every owner write and every device command.

``RunLease(db, run_id, owner, stale_after_s)``: the worker's heartbeat thread calls ``confirm()`` after
each ``UPDATE runs SET heartbeat_at ... WHERE worker = owner`` that found its row, and ``lose(holder)``
when it did not.  ``check()`` (before a device command) trusts a confirmation younger than half the
staleness limit (no other worker may take a run over before its heartbeat is ``stale_after_s`` old);
beyond that (the process was frozen, SIGSTOP, a long GC pause) it asks the database, in one guarded
``UPDATE``, before anything is sent.  A lost lease raises ``bench.errors.LeaseLost`` from then on.
``fence_devices`` wraps every driver of a ``Devices`` bundle so each call checks the lease first.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

from sqlalchemy import select, update

from bench.engine.devices import Devices
from bench.errors import LeaseLost
from bench.storage.db import Database
from bench.storage.models import Run, utcnow

log = logging.getLogger(__name__)


class RunLease:
    def __init__(self, db: Database, run_id: int, owner: str, stale_after_s: float) -> None:
        self.db = db
        self.run_id = int(run_id)
        self.owner = owner
        self.trust_s = stale_after_s / 2
        self.confirmed_at = time.monotonic()
        self.lost_to: str | None = None
        self._lock = threading.Lock()

    def confirm(self) -> None:
        self.confirmed_at = time.monotonic()

    def lose(self, holder: str | None) -> None:
        with self._lock:
            if self.lost_to is None:
                self.lost_to = holder or "nobody"
                log.warning("worker %s lost its lease on run %s (now held by %s): it stops touching the run "
                            "and the hardware", self.owner, self.run_id, self.lost_to)

    def fail(self) -> LeaseLost:
        return LeaseLost(f"worker {self.owner} no longer owns run {self.run_id} (held by {self.lost_to})")

    def check(self) -> None:
        """Raise ``LeaseLost`` unless this worker still owns the run."""
        if self.lost_to is not None:
            raise self.fail()
        if time.monotonic() - self.confirmed_at < self.trust_s:
            return
        with self.db.session() as s:
            took = s.execute(update(Run).where(Run.id == self.run_id, Run.worker == self.owner)
                             .values(heartbeat_at=utcnow()).execution_options(synchronize_session=False)).rowcount
            holder = None if took == 1 else s.scalar(select(Run.worker).where(Run.id == self.run_id))
        if took == 1:
            self.confirm()
            return
        self.lose(holder)
        raise self.fail()

    def check_row(self, run: Run) -> None:
        """Inside an owner write's transaction (the run row locked): raise ``LeaseLost`` unless the row
        names this worker."""
        self.check_worker(run.worker)

    def check_worker(self, worker: str | None) -> None:
        """``check_row`` given the locked row's ``worker`` column only."""
        if self.lost_to is not None:
            raise self.fail()
        if worker != self.owner:
            self.lose(worker)
            raise self.fail()


class FencedDevice:
    """A driver whose every method call first checks the lease (attributes pass through)."""

    def __init__(self, device: Any, lease: RunLease) -> None:
        object.__setattr__(self, "_device", device)
        object.__setattr__(self, "_lease", lease)

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._device, name)
        if not callable(attr):
            return attr
        lease = self._lease

        def fenced(*args: Any, **kwargs: Any) -> Any:
            lease.check()
            return attr(*args, **kwargs)

        return fenced

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._device, name, value)


def fence_devices(devices: Devices, lease: RunLease) -> Devices:
    """Every driver wrapped in ``FencedDevice``; a driver that can (``guard_requests``) also checks the lease
    before each request it puts on the wire, so a call that passed the check before the process froze
    sends nothing more once it wakes without the lease (a status read is several requests).  On a
    multi-gyro bench that is every unit's line, probes and supply too."""
    for driver in devices.drivers():
        guard = getattr(driver, "guard_requests", None)
        if callable(guard):
            guard(lease.check)
    return devices.wrapped(lambda device: FencedDevice(device, lease))
