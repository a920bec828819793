"""Simulated gyro serial line: KVH Format A or HRG frames, byte for byte, over TCP or a pty.

The simulator does no physics.  It asks a ``GyroSource`` (the gyro physics model, or a small
deterministic source in tests) for one ``GyroSample`` per frame instant and encodes it with
``bench.devices.kvh``.  Frame k is produced at bench time ``t0 + k / data_rate_hz`` exactly,
whatever the clock: with an accelerated clock many frames become due per wall second and are
written in batches; with a ``SteppedClock`` every frame up to ``clock.now()`` is written.  For
each frame the source gets ``advance_to(t)`` then ``sample(t)`` with the same, non-decreasing t.

On a lockstep clock (``bench.clock.LockstepClock``) the thread produces nothing by itself: the
clock calls ``serve(t)`` at each bench instant, which accepts a waiting client, writes every frame
due up to ``t`` and reports ``{"peer": client address, "bytes": bytes written on this connection,
"closed": address of the last client connection it closed}`` so the driver can wait for exactly
those bytes, and for the end of a connection the simulator closed (a dropped line), before the
instant is over.  A closed connection is shut down first, so its end (EOF) is on the line at once,
even while the command-reading thread still selects on the socket (a plain close would only end it
once that thread let go of it, a wall-clock moment).

Budget: frames per *wall* second = data_rate_hz x clock speed.  The encoder makes ~100k frames/s
on one core, so keep that product well below (e.g. 1 Hz at speed 3600).  If the simulator
falls more than ``max_backlog_frames`` behind, it skips the excess: the device's sequence
counter still advances (the driver sees a sequence gap, as on a real overrun line) and
``overrun_frames`` counts them.

Transports: ``transport="tcp"`` listens on 127.0.0.1 (ephemeral port by default); ``url`` is
``socket://127.0.0.1:N`` for ``serial.serial_for_url``.  One client at a time; a new client
replaces the old.  ``transport="pty"`` opens a pty pair; ``pty_path`` (``/dev/pts/N``) is what
the driver opens with pyserial (baud is not enforced on a pty).

ASCII command interface on the same line (reference section 3.1; reply format is this bench's
convention, modelled on drivers that wait for the echoed setting, the real reply text is [?]):
commands end with CR, LF or CRLF, are case-insensitive, and are answered with CR LF lines:

==============  ==========================  =============================================
command         effect                      reply
==============  ==========================  =============================================
``=CONFIG,1``   binary output stops         ``CONFIG,1``
``=CONFIG,0``   binary output resumes       ``CONFIG,0``
``?CONFIG``     -                           ``CONFIG,<0|1>``
``=DR,n``       data rate n Hz (config      ``DR,n``; n must be one of 1, 5, 10, 25, 50,
                mode only)                  100, 250, 500, 750, 1000, 3600, 5000
``?DR``         -                           ``DR,n``
other           -                           ``ERROR,<reason>``
==============  ==========================  =============================================

Fault injection (``sim.faults``, a ``GyroFaults``):

- ``corrupt_rate``: fraction of frame bytes flipped on the line (XOR with a random non-zero
  byte; deterministic from ``seed``).  Replies to commands are not corrupted.
- ``drop_link(duration_s=None)``: TCP: the client connection and the listener are closed
  (the driver sees EOF, then "connection refused"); the listener comes back after
  ``duration_s`` wall seconds or on ``restore_link()``.  pty: bytes simply stop (an unplugged
  cable; no EOF exists on a pty).  Frames produced meanwhile are lost, as on a real line.
- ``paused``: the gyro stops producing frames (no sequence advance); clearing it resumes.
- ``clear_status_bits``: bit mask cleared from the status byte of every produced frame
  (e.g. 0x01 = gyro X invalid).  A sample with ``valid=False`` clears all validity bits.

``sent_log`` (read it with ``sent_frames()``, count it with ``sent_count()``) keeps the last
``sent_log_limit`` produced frames, each a plain tuple (a campaign keeps a hundred thousand per gyro:
tuples of numbers and bytes are not watched by the garbage collector, objects are, at every full
collection), given out as ``SentFrame`` (bench time,
sequence, the exact bytes built, whether they were written to a client, whether the line
corrupted them): tests compare what the driver accepted against it.
"""
from __future__ import annotations

import collections
import contextlib
import errno
import logging
import math
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from bench.clock import Clock
from bench.devices import kvh
from bench.sim.audit import CommandLog, link_name

ALLOWED_DATA_RATES = kvh.ALLOWED_DATA_RATES
_RAD_PER_DEG = math.pi / 180.0
from bench.sim.physics import GyroSample  # noqa: E402  (the one sample type; re-exported)

log = logging.getLogger(__name__)


class GyroSource(Protocol):
    def advance_to(self, t: float) -> None: ...
    def sample(self, t: float) -> GyroSample: ...


@dataclass(frozen=True)
class SentFrame:
    bench_time: float
    sequence: int
    frame: bytes          # exactly as built, before any line corruption
    delivered: bool       # written to a connected client / the pty
    corrupted: bool       # at least one of its bytes was flipped on the line


class GyroFaults:
    """Public fault-injection controls (see module docstring)."""

    def __init__(self, seed: int = 12345) -> None:
        self.corrupt_rate = 0.0
        self.paused = False
        self.clear_status_bits = 0
        self.rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._down_until: float | None = None       # wall time; inf = until restore_link
        self._drop_requested = False

    def drop_link(self, duration_s: float | None = None) -> None:
        with self._lock:
            self._drop_requested = True
            self._down_until = math.inf if duration_s is None else time.monotonic() + duration_s

    def restore_link(self) -> None:
        with self._lock:
            self._down_until = None

    def link_down(self) -> bool:
        with self._lock:
            if self._down_until is not None and time.monotonic() >= self._down_until:
                self._down_until = None
            return self._down_until is not None

    def take_drop_request(self) -> bool:
        with self._lock:
            requested, self._drop_requested = self._drop_requested, False
            return requested


class GyroStreamSimulator:
    def __init__(self, source: GyroSource, clock: Clock, data_rate_hz: float = 1000.0,
                 frame: Literal["kvh_a", "hrg"] = "kvh_a", *, transport: Literal["tcp", "pty"] = "tcp",
                 host: str = "127.0.0.1", port: int = 0, temp_scale: float = 0.01,
                 output_units: Literal["deg/s", "rad/s"] = "deg/s", sent_log_limit: int = 200_000,
                 max_backlog_frames: int = 200_000, seed: int = 12345) -> None:
        if data_rate_hz not in ALLOWED_DATA_RATES:
            raise ValueError(f"gyro data rate {data_rate_hz} Hz not in the allowed set {ALLOWED_DATA_RATES}")
        if transport not in ("tcp", "pty"):
            raise ValueError(f"gyro simulator transport must be 'tcp' or 'pty', got {transport!r}")
        if output_units not in ("deg/s", "rad/s"):
            raise ValueError(f"gyro output units must be 'deg/s' or 'rad/s', got {output_units!r}")
        self.source = source
        self.clock = clock
        self.spec = kvh.spec_for(frame)
        self.transport = transport
        self.temp_scale = temp_scale
        self.output_units = output_units
        self.faults = GyroFaults(seed)
        # (bench_time, sequence, frame, delivered, corrupted): the fields of a SentFrame
        self.sent_log: collections.deque[tuple[float, int, bytes, bool, bool]] = collections.deque(maxlen=sent_log_limit)
        self.overrun_frames = 0
        self.received = CommandLog("gyro")        # every ASCII command, by the sender's link
        self.max_backlog_frames = max_backlog_frames
        self._host, self._port = host, port
        self._rate = int(data_rate_hz)
        self._config_mode = False
        self._sequence = 0
        self._next_index = 0
        self._base_t = 0.0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lockstep = bool(getattr(clock, "lockstep", False))
        # free-running, this loop also paces the frames (2 ms); in lockstep the clock's serve() writes
        # them and the loop only answers commands (select wakes at once when one arrives)
        self._poll_s = 0.05 if self._lockstep else 0.002
        self._client_bytes = 0           # bytes written on the current client connection
        self._client_peer: tuple | None = None
        self._closed_peer: tuple | None = None   # the last client connection closed (its address)
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._pty_master: int | None = None
        self._pty_slave: int | None = None
        self._cmd_buf = b""
        self.error: Exception | None = None      # set if the simulator thread died (e.g. the source raised)
        self.url: str | None = None
        self.address: tuple[str, int] | None = None
        self.pty_path: str | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            return
        if self.transport == "tcp":
            self._open_listener()
            self.url = f"socket://{self.address[0]}:{self.address[1]}"
        else:
            master, slave = os.openpty()
            tty.setraw(slave)            # no echo: our frames must not come back as "commands"
            os.set_blocking(master, False)
            self._pty_master, self._pty_slave = master, slave
            self.pty_path = os.ttyname(slave)
            self.url = self.pty_path
        self._restart_timebase(self.clock.now())
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="gyro-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join(timeout=5)
        self._thread = None
        self._close_client()
        self._close_listener()
        for fd in (self._pty_master, self._pty_slave):
            if fd is not None:
                os.close(fd)
        self._pty_master = self._pty_slave = None

    def __enter__(self) -> "GyroStreamSimulator":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def sent_frames(self) -> list[SentFrame]:
        """Snapshot of ``sent_log``, consistent with what is on the line: a batch is written and
        logged under one lock, so a frame the driver already holds is always in the snapshot."""
        with self._lock:
            return [SentFrame(*entry) for entry in self.sent_log]

    def sent_count(self) -> int:
        """``len(sent_frames())`` without the snapshot (a poll while a long log grows: the snapshot is
        O(frames) and holds the lock the sending thread needs)."""
        with self._lock:
            return len(self.sent_log)

    @property
    def data_rate_hz(self) -> int:
        return self._rate

    @property
    def config_mode(self) -> bool:
        return self._config_mode

    @property
    def client_connected(self) -> bool:
        return self._client is not None

    # ------------------------------------------------------------------ sockets
    def _open_listener(self) -> None:
        lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lst.bind((self._host, self._port))
        lst.listen(1)
        lst.setblocking(False)
        self._listener = lst
        self.address = lst.getsockname()[:2]
        self._port = self.address[1]              # come back on the same port after a drop

    def _close_listener(self) -> None:
        if self._listener is not None:
            # shutdown stops listening now (a reconnect is refused from this instant on); close alone
            # would wait for the command-reading thread's select to let go of the socket
            with contextlib.suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)
            self._listener.close()
            self._listener = None

    def _close_client(self, client: socket.socket | None = None) -> None:
        """Close the client connection (only if it is still ``client``, when given): the lockstep
        thread (a drop) and the command-reading thread (the client went away) both may."""
        with self._lock:
            conn = self._client
            if conn is None or (client is not None and conn is not client):
                return
            self._client = None
            self._closed_peer, self._client_peer = self._client_peer, None
            self._cmd_buf = b""
            # shutdown ends the connection now; close alone would wait for the reading thread's select
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()

    # ------------------------------------------------------------------ main loop
    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:  # noqa: BLE001 - a dead simulator must say why
            self.error = exc
            log.exception("gyro stream simulator stopped")
            self._close_client()
            self._close_listener()

    def _loop(self) -> None:
        while not self._stop.is_set():
            if not self._lockstep:
                self._service_link()               # lockstep: serve() does it, at its bench instant
            readers = [s for s in (self._listener, self._client) if s is not None]
            if self._pty_master is not None:
                readers.append(self._pty_master)
            if readers:
                try:
                    ready, _, _ = select.select(readers, [], [], self._poll_s)
                except (ValueError, OSError):
                    # serve() (the lockstep thread) closed one of them meanwhile: look again
                    if any(not isinstance(r, int) and r.fileno() < 0 for r in readers):
                        continue
                    raise
            else:
                time.sleep(0.002)
                ready = []
            for r in ready:
                if r is self._listener:
                    self._accept()
                elif r is self._client:
                    self._read_commands_socket()
                elif r == self._pty_master:
                    self._read_commands_pty()
            if not self._lockstep:
                self._produce_due_frames()

    def serve(self, t: float) -> dict:
        """Lockstep: put every frame due up to bench time ``t`` on the line (see module docstring)."""
        if self.error is not None:
            raise RuntimeError(f"gyro simulator stopped: {self.error}") from self.error
        self._service_link()                       # a drop or a restore takes effect at this instant
        with self._lock:
            if self._client is None and self._listener is not None:
                ready, _, _ = select.select([self._listener], [], [], 0)
                if ready:
                    self._accept()
            self._produce_due_frames_locked(t)
            return {"peer": self._client_peer, "bytes": self._client_bytes, "closed": self._closed_peer}

    def _service_link(self) -> None:
        if self.faults.take_drop_request():
            self._close_client()
            if self.transport == "tcp":
                self._close_listener()
        if self.transport == "tcp" and self._listener is None and not self.faults.link_down():
            try:
                self._open_listener()
            except OSError:
                pass                               # port busy: try again next loop

    def _accept(self) -> None:
        with self._lock:
            self._accept_locked()

    def _accept_locked(self) -> None:
        if self._listener is None:
            return
        try:
            conn, peer = self._listener.accept()
        except (BlockingIOError, OSError):
            return
        self._close_client()
        self._client_peer = tuple(peer[:2])
        self._client_bytes = 0
        conn.setblocking(True)
        conn.settimeout(2.0)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = conn

    def _read_commands_socket(self) -> None:
        client = self._client
        if client is None:
            return
        try:
            data = client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._close_client(client)
            return
        self._handle_command_bytes(data)

    def _read_commands_pty(self) -> None:
        try:
            data = os.read(self._pty_master, 4096)
        except OSError:
            return
        self._handle_command_bytes(data)

    # ------------------------------------------------------------------ ASCII commands
    def _handle_command_bytes(self, data: bytes) -> None:
        self._cmd_buf += data.replace(b"\r", b"\n")
        if len(self._cmd_buf) > 4096:                  # no terminator in sight: line noise
            self._cmd_buf = self._cmd_buf[-256:]
        while b"\n" in self._cmd_buf:
            line, self._cmd_buf = self._cmd_buf.split(b"\n", 1)
            text = line.decode("ascii", "replace").strip().upper()
            if text:
                self.received.record(link_name(self._client_peer) if self.transport == "tcp" else "pty", text)
                self._write_reply(self.execute_command(text))

    def execute_command(self, text: str) -> str:
        """Apply one ASCII command and return the reply text (without CR LF)."""
        now = self.clock.now()
        with self._lock:
            if text in ("=CONFIG,1", "=CONFIG,0"):
                entering = text.endswith("1")
                if entering and not self._config_mode:
                    self._produce_due_frames_locked(now)
                self._config_mode = entering
                if not entering:
                    self._restart_timebase(now)
                return f"CONFIG,{int(entering)}"
            if text == "?CONFIG":
                return f"CONFIG,{int(self._config_mode)}"
            if text == "?DR":
                return f"DR,{self._rate}"
            if text.startswith("=DR,"):
                if not self._config_mode:
                    return "ERROR,NOT IN CONFIG MODE"
                arg = text[4:]
                if not arg.isdigit() or int(arg) not in ALLOWED_DATA_RATES:
                    return f"ERROR,DR {arg} NOT ALLOWED"
                self._rate = int(arg)
                return f"DR,{self._rate}"
            return f"ERROR,UNKNOWN COMMAND {text}"

    def _write_reply(self, reply: str) -> None:
        with self._lock:
            self._write_bytes((reply + "\r\n").encode("ascii"))

    def _write_bytes(self, data: bytes) -> bool:
        if self.transport == "pty":
            if self._pty_master is None or self.faults.link_down():
                return False
            try:
                written = os.write(self._pty_master, data)
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EIO):
                    raise
                return False                      # nobody reading: bytes go into the void
            return written == len(data)
        if self._client is None:
            return False
        try:
            self._client.sendall(data)
        except OSError:
            self._close_client()
            return False
        self._client_bytes += len(data)
        return True

    # ------------------------------------------------------------------ frames
    def _restart_timebase(self, now: float) -> None:
        self._base_t = now
        self._next_index = 1

    def _frame_time(self, index: int) -> float:
        return self._base_t + index / self._rate

    def _produce_due_frames(self) -> None:
        now = self.clock.now()
        with self._lock:
            self._produce_due_frames_locked(now)

    def _produce_due_frames_locked(self, now: float) -> None:
        if self._config_mode or self.faults.paused:
            self._restart_timebase(now)
            return
        due = math.floor((now - self._base_t + 1e-6) * self._rate) - self._next_index + 1
        if due <= 0:
            return
        if due > self.max_backlog_frames:
            skipped = due - self.max_backlog_frames
            self.overrun_frames += skipped
            self._sequence = (self._sequence + skipped) % 128
            self._next_index += skipped
            due = self.max_backlog_frames
        times = [self._frame_time(self._next_index + k) for k in range(due)]
        self._next_index += due
        many = getattr(self.source, "sample_many", None)
        if many is not None:        # vectorised physics: same values, a fraction of the cost per frame
            samples = many(times)
        else:
            samples = []
            for t in times:
                self.source.advance_to(t)
                samples.append(self.source.sample(t))
        frames = [self._build_frame(t, s) for t, s in zip(times, samples)]
        self._send_frames(times, frames)

    def _build_frame(self, t: float, s: GyroSample) -> tuple[int, bytes]:
        if len(s.rate_dps) != 3 or len(s.accel_g) != 3:
            raise ValueError(f"gyro source {type(self.source).__name__} returned a sample without 3 rates and "
                             f"3 accelerations at t={t}: {s!r}")
        seq = self._sequence
        self._sequence = (seq + 1) % 128
        spec = self.spec
        status = spec.all_valid if s.valid else 0
        status &= ~self.faults.clear_status_bits & 0xFF
        rate = s.rate_dps
        if self.output_units == "rad/s":
            rate = (rate[0] * _RAD_PER_DEG, rate[1] * _RAD_PER_DEG, rate[2] * _RAD_PER_DEG)
        if spec.has_freq:
            freq = s.freq_hz
            if freq is None:
                freq = (math.nan, math.nan, math.nan)
                status &= ~kvh.STATUS_FREQ_VALID
            data = kvh.encode_hrg(rate, s.accel_g, freq, sequence=seq, temperature_c=s.temperature_c,
                                  status=status, temp_scale=self.temp_scale)
        else:
            data = kvh.encode_format_a(rate, s.accel_g, sequence=seq, temperature_c=s.temperature_c,
                                       status=status, temp_scale=self.temp_scale)
        return seq, data

    def _send_frames(self, times: list[float], frames: list[tuple[int, bytes]]) -> None:
        line = b"".join(f for _, f in frames)
        corrupted_frames: set[int] = set()
        rate = self.faults.corrupt_rate
        if rate > 0:
            buf = np.frombuffer(bytearray(line), dtype=np.uint8).copy()
            rng = self.faults.rng
            flip = np.flatnonzero(rng.random(buf.size) < rate)
            if flip.size:
                buf[flip] ^= rng.integers(1, 256, flip.size, dtype=np.uint8)
                corrupted_frames = set((flip // self.spec.length).tolist())
                line = buf.tobytes()
        link_up = not self.faults.link_down()
        delivered = link_up and self._write_bytes(line)
        for k, (t, (seq, data)) in enumerate(zip(times, frames)):
            self.sent_log.append((t, seq, data, delivered, k in corrupted_frames))
