"""What a simulated instrument received, and on which link: the bench side's record of who commanded it.

Every simulator keeps a ``CommandLog`` (``received``): one ``Received`` per request, stamped with this
process's monotonic clock, the sender's link (the client socket's ``host:port`` as the simulator sees it,
or the transport when the server does not tell connections apart) and the request itself.  Drills use it
to prove which worker touched the hardware when (``SimulatedBench.received()`` merges all of them).
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class Received:
    mono: float          # time.monotonic() in the simulator's process when the request arrived
    device: str
    link: str
    request: str


class CommandLog:
    """Thread-safe, bounded (the newest ``limit`` requests) log of the requests one simulator received.
    Kept as plain tuples (mono, link, request), given out as ``Received``: a long run logs a hundred
    thousand requests, and tuples of strings and numbers are not watched by the garbage collector."""

    def __init__(self, device: str, limit: int = 200_000) -> None:
        self.device = device
        self._entries: collections.deque[tuple[float, str, str]] = collections.deque(maxlen=limit)
        self._lock = threading.Lock()

    def record(self, link: str, request: str) -> None:
        entry = (time.monotonic(), link, request)
        with self._lock:
            self._entries.append(entry)

    def entries(self) -> list[Received]:
        with self._lock:
            entries = list(self._entries)
        return [Received(mono, self.device, link, request) for mono, link, request in entries]


def link_name(peer: tuple | None) -> str:
    """``host:port`` of a socket peer (``"?"`` when unknown)."""
    return f"{peer[0]}:{peer[1]}" if peer else "?"
