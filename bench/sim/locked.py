"""Read accessors of the simulator models, each taken under the model's ``self._lock`` (the device
server thread and the bench clock thread both touch a model)."""
from __future__ import annotations

from typing import Any, Callable


def locked_property(attr: str, doc: str | None = None) -> property:
    """Read-only property returning ``self.<attr>`` under ``self._lock``."""
    def get(self: Any) -> Any:
        with self._lock:
            return getattr(self, attr)
    return property(get, doc=doc)


def locked_axis_reader(attr: str) -> Callable[[Any, int], Any]:
    """Method ``(axis) -> self._axis(axis).<attr>`` under ``self._lock``."""
    def read(self: Any, axis: int) -> Any:
        with self._lock:
            return getattr(self._axis(axis), attr)
    return read


def locked_all_axes_reader(attr: str) -> Callable[[Any], tuple]:
    """Method ``() -> tuple(<attr> of every axis)`` under ``self._lock``."""
    def read(self: Any) -> tuple:
        with self._lock:
            return tuple(getattr(a, attr) for a in self._axes)
    return read
