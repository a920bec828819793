"""Threaded TCP server for ASCII request/reply instruments, with fault injection.

Used by the turntable (Acutrol ACL) and power-supply (SCPI) simulators.  A driver reaches it with
the pyserial URL ``socket://127.0.0.1:<port>`` (pyserial 3.5 ``socket://`` handler: raw TCP seen
as a serial port), the same way a real instrument behind a serial-to-TCP bridge (e.g. the MOXA
NPort of Acutronic TM-9411) is reached.

Protocol-specific work lives in subclasses:

- ``new_session()`` returns per-connection parser state (SCPI/ACL keep a "current path" per link);
- ``handle_line(session, line)`` gets one request line (terminator and a trailing ``\\r`` removed)
  and returns the complete reply bytes to send (framing included) or ``None`` for no reply.

``received`` (``bench.sim.audit.CommandLog``) logs every request line with the sender's link.

Fault injection: ``server.faults`` (a ``LineFaults``), changeable at any time from any thread.

- ``delay_s``: wall seconds to wait before each reply is sent (a slow or stuck instrument).
- ``drop_next_replies(n)``: the next ``n`` replies are computed (the command still acts) but never sent.
- ``corrupt_rate``: probability (0..1) that a reply gets one bit flipped in one payload byte
  (the reply terminator, if any, is left intact so framing is kept; seeded by ``seed``).
- ``drop_link(refuse_s=0.0)``: close every client connection now; with ``refuse_s > 0`` the
  listening socket is also closed for that many wall seconds, so reconnects are *refused*, then
  it listens again on the same port.  ``restore_link()`` listens again at once (before the call
  returns: a simulator that drops a link by bench time restores it at a bench instant).
"""
from __future__ import annotations

import random
import socket
import threading
import time
from typing import Any

from bench.sim.audit import CommandLog, link_name


class LineFaults:
    """Fault switches of one line server (see module docstring).  Thread-safe."""

    def __init__(self, seed: int = 12345) -> None:
        self._lock = threading.Lock()
        self.delay_s = 0.0
        self.corrupt_rate = 0.0
        self._drop_replies = 0
        self._rng = random.Random(seed)
        self._server: LineServer | None = None
        self.replies_dropped = 0
        self.replies_corrupted = 0

    def drop_next_replies(self, n: int) -> None:
        if n < 0:
            raise ValueError(f"drop_next_replies needs n >= 0, got {n}")
        with self._lock:
            self._drop_replies = int(n)

    def drop_link(self, refuse_s: float = 0.0) -> None:
        if self._server is None:
            raise RuntimeError("drop_link: the line server is not attached/started")
        self._server._drop_all_clients(refuse_s)

    def restore_link(self) -> None:
        """Listen again now (ends a ``drop_link`` refusal early, e.g. ``refuse_s=math.inf``)."""
        if self._server is None:
            raise RuntimeError("restore_link: the line server is not attached/started")
        self._server._listen_again()

    def clear(self) -> None:
        """Back to a healthy link (no delay, no drops, no corruption)."""
        with self._lock:
            self.delay_s = 0.0
            self.corrupt_rate = 0.0
            self._drop_replies = 0

    # used by the server ---------------------------------------------------------------------
    def _take_drop(self) -> bool:
        with self._lock:
            if self._drop_replies > 0:
                self._drop_replies -= 1
                self.replies_dropped += 1
                return True
            return False

    def _maybe_corrupt(self, reply: bytes, terminator: bytes) -> bytes:
        with self._lock:
            if self.corrupt_rate <= 0 or self._rng.random() >= self.corrupt_rate:
                return reply
            body_len = len(reply) - (len(terminator) if terminator and reply.endswith(terminator) else 0)
            if body_len <= 0:
                return reply
            pos = self._rng.randrange(body_len)
            bit = 1 << self._rng.randrange(8)
            self.replies_corrupted += 1
        data = bytearray(reply)
        data[pos] ^= bit
        return bytes(data)


class LineServer:
    """Base class: listens on ``host:port`` (port 0 = ephemeral), one thread per client.

    ``request_terminator`` ends request lines (a ``\\r`` before it is stripped, so both ``\\n`` and
    ``\\r\\n`` senders work).  ``reply_terminator`` is only used to keep it intact when corrupting.
    """

    name = "line"

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, request_terminator: bytes = b"\n",
                 reply_terminator: bytes = b"\n", max_line: int = 4096, seed: int = 12345) -> None:
        if not request_terminator:
            raise ValueError("request_terminator must not be empty")
        self.host = host
        self._port = port
        self.request_terminator = request_terminator
        self.reply_terminator = reply_terminator
        self.max_line = max_line
        self.faults = LineFaults(seed)
        self.faults._server = self
        self._lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._clients: set[socket.socket] = set()
        self._threads: list[threading.Thread] = []
        self._accept_thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._refuse_until = 0.0
        self._started = False
        self.connections_accepted = 0
        self.received = CommandLog(self.name)       # every request line, by the sender's link

    # subclass API ------------------------------------------------------------------------------
    def new_session(self) -> Any:
        return None

    def handle_line(self, session: Any, line: bytes) -> bytes | None:  # pragma: no cover - abstract
        raise NotImplementedError

    # lifecycle -------------------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        if not self._started:
            raise RuntimeError(f"{self.name} server: address is known only after start()")
        return (self.host, self._port)

    @property
    def url(self) -> str:
        host, port = self.address
        return f"socket://{host}:{port}"

    def start(self) -> "LineServer":
        if self._started:
            return self
        self._stopping.clear()
        self._listener = self._listen()
        self._port = self._listener.getsockname()[1]
        self._started = True
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"{self.name}-accept", daemon=True)
        self._accept_thread.start()
        return self

    def stop(self) -> None:
        if not self._started:
            return
        self._stopping.set()
        with self._lock:
            listener, self._listener = self._listener, None
            clients = list(self._clients)
            self._clients.clear()
        if listener is not None:
            listener.close()
        for conn in clients:
            _close_quietly(conn)
        if self._accept_thread is not None:
            self._accept_thread.join(timeout=5)
        for thread in list(self._threads):
            thread.join(timeout=5)
        self._threads.clear()
        self._started = False

    def __enter__(self) -> "LineServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # internals -------------------------------------------------------------------------------
    def _listen(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.host, self._port))
        sock.listen(8)
        sock.settimeout(0.05)
        return sock

    def _drop_all_clients(self, refuse_s: float) -> None:
        with self._lock:
            clients = list(self._clients)
            self._clients.clear()
            if refuse_s > 0:
                self._refuse_until = time.monotonic() + refuse_s
                listener, self._listener = self._listener, None
            else:
                listener = None
        if listener is not None:
            listener.close()
        for conn in clients:
            _close_quietly(conn)

    def _listen_again(self) -> None:
        with self._lock:
            self._refuse_until = 0.0
            if self._listener is None and self._started and not self._stopping.is_set():
                self._listener = self._listen()

    def _accept_loop(self) -> None:
        while not self._stopping.is_set():
            with self._lock:
                listener = self._listener
                refuse_left = self._refuse_until - time.monotonic()
            if listener is None:
                if refuse_left > 0:
                    self._stopping.wait(min(refuse_left, 0.05))
                    continue
                try:
                    new_listener = self._listen()
                except OSError:
                    self._stopping.wait(0.05)
                    continue
                with self._lock:
                    if self._stopping.is_set():
                        new_listener.close()
                        return
                    self._listener = new_listener
                continue
            try:
                conn, _ = listener.accept()
            except socket.timeout:
                continue
            except OSError:
                continue  # listener closed by drop_link/stop
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.1)
            with self._lock:
                if self._stopping.is_set():
                    _close_quietly(conn)
                    return
                self._clients.add(conn)
                self.connections_accepted += 1
            thread = threading.Thread(target=self._serve_client, args=(conn,), name=f"{self.name}-client",
                                      daemon=True)
            self._threads = [t for t in self._threads if t.is_alive()]
            self._threads.append(thread)
            thread.start()

    def _connected(self, conn: socket.socket) -> bool:
        with self._lock:
            return conn in self._clients

    def _serve_client(self, conn: socket.socket) -> None:
        session = self.new_session()
        buffer = b""
        term = self.request_terminator
        try:
            link = link_name(conn.getpeername())
        except OSError:
            link = "?"
        try:
            while not self._stopping.is_set() and self._connected(conn):
                try:
                    chunk = conn.recv(4096)
                except socket.timeout:
                    continue
                except OSError:
                    return
                if not chunk:
                    return
                buffer += chunk
                while term in buffer:
                    line, buffer = buffer.split(term, 1)
                    if line.endswith(b"\r"):
                        line = line[:-1]
                    self.received.record(link, line.decode("ascii", "replace"))
                    self._answer(conn, session, line)
                if len(buffer) > self.max_line:
                    buffer = b""  # an overlong line is discarded, as an instrument's input buffer would
        finally:
            with self._lock:
                self._clients.discard(conn)
            _close_quietly(conn)

    def _answer(self, conn: socket.socket, session: Any, line: bytes) -> None:
        reply = self.handle_line(session, line)
        if reply is None:
            return
        delay = self.faults.delay_s
        if delay > 0:
            self._stopping.wait(delay)
        if self.faults._take_drop():
            return
        reply = self.faults._maybe_corrupt(reply, self.reply_terminator)
        try:
            conn.sendall(reply)
        except OSError:
            pass  # client went away; the read loop will notice


def _close_quietly(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        conn.close()
    except OSError:
        pass
