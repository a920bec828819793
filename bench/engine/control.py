"""Operator control requests: the engine polls ``control.poll()`` once per loop tick.

Requests: ``stop`` (finish the current recording, then safe state), ``abort`` (safe state now),
``pause`` and ``resume``.  The CLI wires signals to a ``QueueControl``; the service can implement
``poll`` over a database flag.
"""
from __future__ import annotations

import collections
from typing import Protocol

COMMANDS = ("stop", "abort", "pause", "resume")


class Control(Protocol):
    def poll(self) -> str | None:
        """Next pending request, or None."""


class NoControl:
    def poll(self) -> str | None:
        return None


class QueueControl:
    """Thread-safe (and signal-handler-safe: append/popleft on a deque) request queue."""

    def __init__(self) -> None:
        self._queue: collections.deque[str] = collections.deque()

    def request(self, command: str) -> None:
        if command not in COMMANDS:
            raise ValueError(f"unknown control request {command!r}; expected one of {', '.join(COMMANDS)}")
        self._queue.append(command)

    def poll(self) -> str | None:
        try:
            return self._queue.popleft()
        except IndexError:
            return None
