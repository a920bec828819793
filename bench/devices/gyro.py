"""Gyro serial link: reads KVH Format A / HRG frames off a serial line in a background thread.

Transport is pyserial's ``serial_for_url`` (reference section 5.2): a device path
(``/dev/ttyUSB1``, a pty ``/dev/pts/N``) or ``socket://host:port`` for the simulator.  Frames
are decoded by ``bench.devices.kvh.FrameDecoder`` (resync, CRC, sequence and status counting)
and timestamped with the bench clock when taken off the line: the last frame of each read
chunk gets ``clock.now()``, earlier frames of the same chunk are back-dated by the nominal
frame period ``1 / data_rate_hz`` (they left the device one period apart).

On a lockstep clock (the simulated bench, ``bench.clock.LockstepClock``) the link registers as a
receiver: at each new bench instant it waits until it has read every byte the simulator reports
having written for that instant (same connection), then decodes them all at once, the last frame
stamped with the instant and earlier ones back-dated by the frame period, so the stamps do not
depend on how the host happened to chunk the bytes.

The control loop calls ``drain()``, which never blocks.  Frames wait in a bounded but large
queue (``queue_limit``); if the consumer falls that far behind, the oldest frames are dropped
and counted in ``queue_overflows``.

Link loss (a read/open exception, EOF on a socket) is recorded: the gap starts at the bench
time of detection; the thread retries every ``config.reconnect_s`` wall seconds; on success
``(gap_from, gap_to)`` is appended to ``stats.link_gaps`` and ``stats.reconnects`` is
incremented.  On a lockstep clock the loss is the bench instant at which the simulator reports having closed the
connection (the receiver waits for its end, as it waits for an instant's bytes); the receiver retries
at the first bench instant ``config.reconnect_s`` bench seconds after the loss or the last attempt,
and the gap ends at the bench instant the line opened again: the recorded gap does not depend on the
pace or the load.  The decoder is reset (partial bytes and sequence forgotten) so frames lost in
the gap are not miscounted mod 128.  A line that merely goes silent (an unplugged RS-422
cable, a pty) raises nothing and is not a link gap; the sequence check reports the lost frames
if fewer than 128.

ASCII configuration on the same line (KVH ``=CONFIG,1`` / ``=DR,n`` / ``?DR`` / ``=CONFIG,0``):
``configure_data_rate(hz)`` and ``query_data_rate()`` enter config mode, act, and leave it.
Reply convention: the device echoes the setting (``CONFIG,1``, ``DR,100``) or ``ERROR,...``
(see ``bench.sim.gyro``).  The reply bytes also reach the frame decoder, which counts them as
skipped bytes (they are not frames).
"""
from __future__ import annotations

import collections
import re
import threading
import time
from collections.abc import Callable

import serial

from bench.clock import Clock
from bench.config import GyroConfig
from bench.devices.kvh import ALLOWED_DATA_RATES, FrameDecoder
from bench.background import BackgroundLoop
from bench.errors import DeviceTimeout, LinkDown, ProtocolError
from bench.interfaces import GyroFrame, LinkStats

_ERROR_REPLY = re.compile(rb"ERROR,([^\r\n]*)\r\n")


class GyroSerialLink(BackgroundLoop):
    """``GyroLink`` over a pyserial URL.  ``start()`` raises ``LinkDown`` if the port cannot be opened."""

    thread_name = "gyro-link"

    def __init__(self, config: GyroConfig, clock: Clock, *, temp_scale: float | None = None,
                 queue_limit: int = 2_000_000, read_timeout_s: float = 0.01, lockstep_name: str = "gyro") -> None:
        super().__init__()
        # lockstep: the name its simulator serves under (one per gyro line on a multi-gyro bench)
        self.lockstep_name = lockstep_name
        self.config = config
        self.clock = clock
        self.stats = LinkStats()
        self.decoder = FrameDecoder(config.frame, temp_scale=config.temp_scale if temp_scale is None else temp_scale, stats=self.stats)
        self.queue_limit = queue_limit
        self.queue_overflows = 0
        self.read_timeout_s = read_timeout_s
        self._rate_hz = float(config.data_rate_hz)
        self._queue: collections.deque[GyroFrame] = collections.deque()
        self._queue_lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._port_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._reply_buf = bytearray()
        self._reply_lock = threading.Lock()
        self._capturing_replies = False
        self.last_error: str | None = None
        self._lockstep = bool(getattr(clock, "lockstep", False))
        self._rx_cond = threading.Condition()
        self._rx_pending = bytearray()       # lockstep: bytes read but not yet decoded
        self._rx_bytes = 0                   # bytes read on the current connection
        self._local_addr: tuple | None = None
        self._served = False                 # lockstep: the simulator reported serving this connection
        self.receive_timeouts = 0            # lockstep instants whose bytes did not all arrive in time
        self.receive_wait_s = 10.0           # wall seconds to wait for an instant's bytes
        self._gap_from: float | None = None  # lockstep: bench time the receiver lost the line
        self._next_attempt = 0.0             # lockstep: bench time of the next reconnect attempt
        self._guard: Callable[[], None] | None = None

    # ------------------------------------------------------------------ lifecycle
    def _before_start(self) -> None:
        self._port = self._open()
        if self._lockstep:
            self.clock.receive(f"{self.lockstep_name}_link", self._receive_instant)
            self.clock.serve_now()

    def stop(self) -> None:
        if self._lockstep:
            self.clock.forget(f"{self.lockstep_name}_link")
        super().stop()

    def _after_stop(self) -> None:
        self._close_port()

    @property
    def connected(self) -> bool:
        return self._port is not None

    @property
    def data_rate_hz(self) -> float:
        return self._rate_hz

    def drain(self, max_frames: int | None = None) -> list[GyroFrame]:
        """All queued frames (or the oldest ``max_frames``), oldest first.  Never blocks."""
        with self._queue_lock:
            if max_frames is None or max_frames >= len(self._queue):
                out = list(self._queue)
                self._queue.clear()
            else:
                popleft = self._queue.popleft
                out = [popleft() for _ in range(max(0, max_frames))]
        return out

    def pending(self) -> int:
        return len(self._queue)

    # ------------------------------------------------------------------ port handling
    def _open(self) -> serial.SerialBase:
        try:
            port = serial.serial_for_url(self.config.url, baudrate=self.config.baudrate,
                                         timeout=self.read_timeout_s, write_timeout=2.0)
            sock = getattr(port, "_socket", None)
            with self._rx_cond:
                self._rx_bytes = 0
                self._rx_pending.clear()
                self._local_addr = tuple(sock.getsockname()[:2]) if sock is not None else None
                self._served = False
            return port
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkDown(f"gyro serial link {self.config.url!r}: cannot open: {exc}") from None

    def _close_port(self) -> None:
        with self._port_lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def _run(self) -> None:
        while not self._stop.is_set():
            port = self._port
            if port is None and self._lockstep:      # the receiver reconnects, by bench time
                self._stop.wait(0.05)
                continue
            if port is None:
                self._reconnect_loop(self._gap_from if self._gap_from is not None else self.clock.now())
                self._gap_from = None
                continue
            if self._lockstep:              # the receiver reads, in the thread that moves the clock
                self._stop.wait(0.05)
                continue
            try:
                data = port.read(65536)
            except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                # AttributeError/TypeError: pyserial's socket handler after a concurrent close
                if self._stop.is_set():
                    return
                self.last_error = f"{type(exc).__name__}: {exc}"
                gap_from = self.clock.now()       # before close: pyserial's socket close sleeps 0.3 s
                self._close_port()
                self._reconnect_loop(gap_from)
                continue
            if data:
                self._on_bytes(data)

    def _reconnect_loop(self, gap_from: float) -> None:
        while not self._stop.wait(self.config.reconnect_s):
            if self._try_reconnect(gap_from, self.clock.now()):
                return

    def _on_bytes(self, data: bytes) -> None:
        if self._capturing_replies:
            with self._reply_lock:
                self._reply_buf += data
                if len(self._reply_buf) > 1 << 20:
                    del self._reply_buf[:-4096]
        if self._lockstep:
            with self._rx_cond:
                self._rx_pending += data
                self._rx_bytes += len(data)
                self._rx_cond.notify_all()
            return
        self._enqueue(self.decoder.feed(data, self.clock.now(), 1.0 / self._rate_hz))

    def _receive_instant(self, t: float, reports: dict) -> None:
        """Lockstep receiver: read every byte the simulator wrote up to bench time ``t`` (they are
        already in the socket buffer: the simulator served the instant first), then decode them."""
        if self._port is None:
            self._reconnect_at(t)
        sent = reports.get(self.lockstep_name) or {}
        port = self._port
        if (port is not None and sent.get("peer") is not None and tuple(sent["peer"]) == self._local_addr):
            self._served = True
            deadline = time.monotonic() + self.receive_wait_s
            while self._rx_bytes < sent["bytes"]:
                try:
                    data = _read_waiting(port, sent["bytes"] - self._rx_bytes)
                except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                    self.last_error = f"{type(exc).__name__}: {exc}"
                    self._lost(t)
                    break
                if data:
                    self._on_bytes(data)
                elif time.monotonic() > deadline:
                    self.receive_timeouts += 1
                    self.last_error = (f"bench instant {t:.3f}: {sent['bytes'] - self._rx_bytes} bytes "
                                       f"not received within {self.receive_wait_s:g} s")
                    break
        elif (port is not None and self._served and sent.get("closed") is not None
              and tuple(sent["closed"]) == self._local_addr):       # served, then closed: a dropped line
            self._await_end(port, t)
        with self._rx_cond:
            data, self._rx_pending = bytes(self._rx_pending), bytearray()
        if data:
            self._enqueue(self.decoder.feed(data, t, 1.0 / self._rate_hz))

    def _lost(self, t: float) -> None:
        """Lockstep: the line was lost at bench time ``t``; the receiver reconnects (``_reconnect_at``)."""
        self._gap_from = t
        self._next_attempt = t + self.config.reconnect_s
        self._close_port()

    def _reconnect_at(self, t: float) -> None:
        """Lockstep: a reconnect attempt when one is due at bench instant ``t``; on success the gap
        ``(loss, t)`` is recorded (the simulator writes to the new connection from its next instant)."""
        if t < self._next_attempt or self._stop.is_set():
            return
        self._next_attempt = t + self.config.reconnect_s
        if self._try_reconnect(self._gap_from if self._gap_from is not None else t, t):
            self._gap_from = None

    def _try_reconnect(self, gap_from: float, t: float) -> bool:
        """One reconnect attempt at time ``t``; on success the new port is used and the gap
        ``(gap_from, t)`` recorded."""
        try:
            port = self._open()
        except LinkDown as exc:
            self.last_error = str(exc)
            return False
        with self._port_lock:
            self._port = port
        self.decoder.reset()
        self.stats.link_gaps.append((gap_from, t))
        self.stats.reconnects += 1
        return True

    def _await_end(self, port: serial.SerialBase, t: float) -> None:
        """Lockstep: the simulator closed our connection (a dropped line) by bench instant ``t``: read
        the bytes still on it up to its end (EOF), then the line is lost at ``t``, as a real receiver
        sees a dropped line; waits at most ``receive_wait_s`` wall seconds for that end (then the line is
        taken as lost all the same: the simulator said so)."""
        deadline = time.monotonic() + self.receive_wait_s
        while True:
            try:
                data = port.read(65536)
            except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                self._lost(t)
                return
            if data:
                self._on_bytes(data)
            elif time.monotonic() > deadline:
                self.receive_timeouts += 1
                self.last_error = (f"bench instant {t:.3f}: the end of the connection the simulator closed "
                                   f"did not arrive within {self.receive_wait_s:g} s")
                self._lost(t)
                return

    def _read_now(self) -> None:
        """Lockstep: take whatever bytes are waiting (command replies), without blocking."""
        port = self._port
        if port is None:
            return
        try:
            port.timeout = 0
            data = port.read(65536)
        except (serial.SerialException, OSError, AttributeError, TypeError):
            return
        finally:
            port.timeout = self.read_timeout_s
        if data:
            self._on_bytes(data)

    def _enqueue(self, frames: list[GyroFrame]) -> None:
        if not frames:
            return
        with self._queue_lock:
            self._queue.extend(frames)
            excess = len(self._queue) - self.queue_limit
            if excess > 0:
                self.queue_overflows += excess
                popleft = self._queue.popleft
                for _ in range(excess):
                    popleft()

    # ------------------------------------------------------------------ ASCII configuration
    def guard_requests(self, guard: Callable[[], None] | None) -> None:
        """Call ``guard`` before every ASCII command sent to the gyro (it raises to keep one off)."""
        self._guard = guard

    def _command(self, text: str, expect: re.Pattern[bytes], timeout_s: float) -> re.Match[bytes]:
        port = self._port
        if port is None:
            raise LinkDown(f"gyro serial link {self.config.url!r}: not connected, cannot send {text!r}")
        if self._guard is not None:
            self._guard()
        with self._reply_lock:
            self._reply_buf.clear()
        self._capturing_replies = True
        try:
            with self._write_lock:
                try:
                    port.write((text + "\r\n").encode("ascii"))
                except (serial.SerialException, OSError) as exc:
                    raise LinkDown(f"gyro serial link {self.config.url!r}: write of {text!r} failed: {exc}") from None
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                if self._lockstep:
                    self._read_now()
                with self._reply_lock:
                    buf = bytes(self._reply_buf)
                match = expect.search(buf)
                if match:
                    return match
                error = _ERROR_REPLY.search(buf)
                if error:
                    raise ProtocolError(f"gyro at {self.config.url!r} refused {text!r}: "
                                        f"ERROR,{error.group(1).decode('ascii', 'replace')}")
                time.sleep(0.002)
        finally:
            self._capturing_replies = False
        raise DeviceTimeout(f"gyro at {self.config.url!r}: no reply to {text!r} within {timeout_s} s")

    def _in_config_mode(self, action, timeout_s: float):
        self._command("=CONFIG,1", re.compile(rb"CONFIG,1\r\n"), timeout_s)
        try:
            return action()
        finally:
            self._command("=CONFIG,0", re.compile(rb"CONFIG,0\r\n"), timeout_s)

    def configure_data_rate(self, hz: int, timeout_s: float = 2.0) -> int:
        """Set the device data rate (``=DR,hz`` inside ``=CONFIG,1`` ... ``=CONFIG,0``)."""
        if hz not in ALLOWED_DATA_RATES:
            raise ValueError(f"gyro data rate {hz} Hz is not one of {ALLOWED_DATA_RATES}")
        hz = int(hz)

        def set_rate() -> int:
            self._command(f"=DR,{hz}", re.compile(rb"DR,%d\r\n" % hz), timeout_s)
            self._rate_hz = float(hz)
            return hz

        return self._in_config_mode(set_rate, timeout_s)

    def query_data_rate(self, timeout_s: float = 2.0) -> int:
        """Ask the device for its data rate (``?DR`` inside config mode)."""

        def ask() -> int:
            match = self._command("?DR", re.compile(rb"DR,(\d+)\r\n"), timeout_s)
            return int(match.group(1))

        rate = self._in_config_mode(ask, timeout_s)
        self._rate_hz = float(rate)
        return rate


def _read_waiting(port: serial.SerialBase, size: int) -> bytes:
    """Lockstep: up to ``size`` bytes of the line, for bytes the simulator has already written.  On a TCP
    line (pyserial's ``socket://``, a non-blocking socket) the socket is read at once when they are there:
    pyserial's ``read`` asks ``select`` first, a system call per gyro per bench instant; bytes not there yet
    (and any other port) go through ``port.read``, which waits for them."""
    sock = getattr(port, "_socket", None)
    if sock is None:
        return port.read(size)
    try:
        data = sock.recv(size)
    except (BlockingIOError, InterruptedError):
        return port.read(size)
    if not data:
        raise serial.SerialException("socket disconnected")
    return data
