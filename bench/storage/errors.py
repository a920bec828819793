"""Typed storage errors (subclasses of ``bench.errors.BenchError``)."""
from __future__ import annotations

from bench.errors import BenchError, DataFormatError


class StorageError(BenchError):
    """The runs database refused or could not do something."""


class StorageUnavailable(StorageError):
    """The database could not be reached (yet); buffered data is kept and retried."""


class BufferFull(StorageError):
    """The frame writer's in-memory buffer reached its bound while the database is unavailable."""


class WriterFenced(StorageError):
    """Another writer has taken over this run's frames; this writer must stop."""


class UnknownRun(StorageError):
    """No run with that id."""


class InvalidTransition(StorageError):
    """A run status change that the state machine does not allow."""


class UnknownFrameKind(DataFormatError):
    """Stored frames of a kind this version cannot decode."""
