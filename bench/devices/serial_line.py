"""ASCII request/reply over a pyserial URL, with timeouts, reconnect and typed errors.

Shared by the turntable (Acutrol ACL) and power-supply (SCPI) drivers.  The port is opened with
``serial.serial_for_url`` (pyserial 3.5), so the same code reaches a serial device (``/dev/ttyS0``,
9600 8N1 for the Acutrol TM-9411 RS-232 bridge) or a TCP endpoint (``socket://host:port``).

Error policy (all wall-time, see bench/clock.py):

- opening fails -> ``LinkDown`` naming the URL;
- the link breaks during a transaction (pyserial ``SerialException``/``OSError``, e.g. "socket
  disconnected") -> the port is closed, reopened once and the request repeated when the caller
  allows it (``retry=True``, idempotent requests); otherwise / if that fails -> ``LinkDown``;
- no complete reply within ``timeout_s`` -> ``DeviceTimeout``; the port is then closed so that a
  late reply cannot be mistaken for the answer to the next request (a line protocol has no
  transaction ids); the next call reopens it and counts a reconnect;
- undecodable bytes -> ``ProtocolError``.

Before every request pending input is discarded (``reset_input_buffer``).
"""
from __future__ import annotations

import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable, TypeVar

import serial
from serial.urlhandler import protocol_socket

from bench.errors import DeviceTimeout, LinkDown, ProtocolError

T = TypeVar("T")


@dataclass
class LineStats:
    requests: int = 0
    timeouts: int = 0
    reconnects: int = 0
    link_errors: int = 0


class _LinkBroken(Exception):
    """Internal: the transport failed mid-transaction (maps to a retry or LinkDown)."""


class SerialLine:
    """One ASCII instrument link.  Thread-safe: one transaction at a time."""

    def __init__(self, url: str, *, baudrate: int = 9600, timeout_s: float = 1.0, name: str = "device",
                 write_terminator: bytes = b"\r\n", read_terminator: bytes = b"\n",
                 encoding: str = "ascii") -> None:
        if timeout_s <= 0:
            raise ValueError(f"{name}: timeout_s must be > 0, got {timeout_s}")
        self.url = url
        self.baudrate = baudrate
        self.timeout_s = float(timeout_s)
        self.name = name
        self.write_terminator = write_terminator
        self.read_terminator = read_terminator
        self.encoding = encoding
        self.stats = LineStats()
        self._port: serial.SerialBase | None = None
        self._opened_once = False
        self._lock = threading.RLock()
        self._carry = b""          # bytes received past the end of the last reply read (this transaction)
        self.request_guard: Callable[[], None] | None = None   # called before each request goes on the wire

    # connection ------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        with self._lock:
            if self.is_open:
                return
            try:
                self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.timeout_s,
                                                   write_timeout=self.timeout_s)
            except (serial.SerialException, OSError, ValueError) as exc:
                self._port = None
                raise LinkDown(f"{self.name}: cannot open {self.url}: {exc}") from None
            if self._opened_once:
                self.stats.reconnects += 1
            self._opened_once = True

    def close(self) -> None:
        with self._lock:
            port, self._port = self._port, None
            if port is not None:
                _close_port(port)

    # transactions ----------------------------------------------------------------------------
    def transact(self, request: str, reader: Callable[["SerialLine"], T], *, retry: bool = True) -> T:
        """Send ``request`` (terminator appended) and return ``reader(self)``.

        ``reader`` uses ``read_line``/``read_exact``; it may be ``lambda line: None`` for requests
        with no reply.
        """
        with self._lock:
            attempts = 2 if retry else 1
            for attempt in range(attempts):
                self.open()
                try:
                    return self._once(request, reader)
                except _LinkBroken as exc:
                    self.stats.link_errors += 1
                    self.close()
                    if attempt + 1 >= attempts:
                        raise LinkDown(f"{self.name} at {self.url}: link lost during {request!r}: {exc}") from None
            raise AssertionError("unreachable")

    def send(self, request: str, *, retry: bool = True) -> None:
        """Write a request that has no reply."""
        self.transact(request, lambda line: None, retry=retry)

    def query_line(self, request: str, *, retry: bool = True) -> str:
        return self.transact(request, lambda line: line.read_line(request), retry=retry)

    def _once(self, request: str, reader: Callable[["SerialLine"], T]) -> T:
        port = self._port
        assert port is not None
        if self.request_guard is not None:
            self.request_guard()             # raises to keep the request off the wire (a lost lease)
        self.stats.requests += 1
        try:
            self._carry = b""
            port.reset_input_buffer()
            port.write(request.encode(self.encoding) + self.write_terminator)
            port.flush()
        except serial.SerialTimeoutException:
            self._timed_out()
            raise DeviceTimeout(f"{self.name} at {self.url}: write of {request!r} timed out "
                                f"after {self.timeout_s} s") from None
        except (serial.SerialException, OSError, UnicodeEncodeError) as exc:
            if isinstance(exc, UnicodeEncodeError):
                raise ValueError(f"{self.name}: request {request!r} is not {self.encoding}") from None
            raise _LinkBroken(str(exc)) from None
        return reader(self)

    # readers (called inside transact) ----------------------------------------------------------
    def read_line(self, request: str = "") -> str:
        """Read up to the read terminator; strip it and a trailing CR; decode."""
        raw = self._read(self._read_through_terminator, request)
        if not raw.endswith(self.read_terminator):
            self._timed_out()
            got = f" (partial {raw!r})" if raw else ""
            raise DeviceTimeout(f"{self.name} at {self.url}: no reply to {request!r} within "
                                f"{self.timeout_s} s{got}")
        text = raw[: -len(self.read_terminator)]
        if text.endswith(b"\r"):
            text = text[:-1]
        return self._decode(text, request)

    def read_exact(self, size: int, request: str = "") -> bytes:
        raw = self._read(lambda port: self._read_size(port, size), request)
        if len(raw) != size:
            self._timed_out()
            raise DeviceTimeout(f"{self.name} at {self.url}: expected {size} bytes in reply to {request!r}, "
                                f"got {len(raw)} within {self.timeout_s} s")
        return raw

    def decode(self, data: bytes, request: str = "") -> str:
        return self._decode(data, request)

    def _read_through_terminator(self, port: serial.SerialBase) -> bytes:
        """The reply up to and including the read terminator (or what came within ``timeout_s``).

        pyserial's ``read_until`` asks the port for one byte per call (a select and a recv per byte
        on ``socket://``); this waits for the first bytes, then takes everything already received
        in one read.  Bytes past the terminator are kept for the next read of this transaction."""
        term = self.read_terminator
        buf = bytearray(self._carry)
        self._carry = b""
        deadline = time.monotonic() + self.timeout_s
        while term not in buf:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            chunk = _read_available(port, left)
            if not chunk:
                break
            buf += chunk
        end = buf.find(term)
        if end < 0:
            return bytes(buf)
        end += len(term)
        self._carry = bytes(buf[end:])
        return bytes(buf[:end])

    def _read_size(self, port: serial.SerialBase, size: int) -> bytes:
        head, self._carry = self._carry[:size], self._carry[size:]
        return head + port.read(size - len(head)) if len(head) < size else head

    def _read(self, op: Callable[[serial.SerialBase], bytes], request: str) -> bytes:
        port = self._port
        if port is None:
            raise _LinkBroken("port closed")
        try:
            return op(port)
        except (serial.SerialException, OSError) as exc:
            raise _LinkBroken(str(exc)) from None

    def _decode(self, data: bytes, request: str) -> str:
        try:
            return data.decode(self.encoding)
        except UnicodeDecodeError:
            raise ProtocolError(f"{self.name} at {self.url}: reply to {request!r} is not {self.encoding} "
                                f"text: {data!r}") from None

    def _timed_out(self) -> None:
        self.stats.timeouts += 1
        self.close()


def _read_available(port: serial.SerialBase, wait_s: float) -> bytes:
    """Wait up to ``wait_s`` (the port's own timeout for a device port) for input, then return every
    byte already received; b"" when nothing came."""
    sock = getattr(port, "_socket", None)
    if isinstance(port, protocol_socket.Serial) and sock is not None:
        ready, _, _ = select.select([sock], [], [], wait_s)
        if not ready:
            return b""
        data = sock.recv(4096)
        if not data:
            raise serial.SerialException("socket disconnected")
        return data
    first = port.read(1)
    if not first:
        return b""
    waiting = port.in_waiting
    return first + port.read(waiting) if waiting else first


def _close_port(port: serial.SerialBase) -> None:
    """Close a port.  pyserial 3.5's ``socket://`` ``close()`` sleeps 0.3 s "for quick reconnects";
    a dead TCP link is closed here directly instead so a timeout/reconnect costs no extra wall time.
    """
    sock = getattr(port, "_socket", None)
    if isinstance(port, protocol_socket.Serial) and sock is not None:
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        sock.close()
        port._socket = None
        port.is_open = False
        return
    try:
        port.close()
    except (serial.SerialException, OSError):
        pass
