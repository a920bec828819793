"""A daemon thread running ``_run`` until ``stop()``: the start/stop/context-manager lifecycle shared by
the gyro serial link and the w1 simulator.  Subclasses call ``BackgroundLoop.__init__``, implement
``_run`` (loop until ``self._stop`` is set) and may override ``_before_start`` / ``_after_stop``."""
from __future__ import annotations

import threading


class BackgroundLoop:
    thread_name = "background"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        raise NotImplementedError

    def _before_start(self) -> None:
        """Called in ``start()`` before the thread starts (open ports, create files)."""

    def _after_stop(self) -> None:
        """Called in ``stop()`` after the thread ended (close ports)."""

    def start(self) -> None:
        if self._thread is not None:
            return
        self._before_start()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._after_stop()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
