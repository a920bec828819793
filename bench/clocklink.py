"""Lockstep bench time across processes: the simulated bench in one process (``bench sim up``), the run
engine in another (``bench run --sim-endpoints FILE``, ``bench worker`` / ``bench serve --config FILE``).

The simulator process owns the physics, the device transports and a ``LockstepClock`` on which its
simulators are registered (``serve``).  It never moves that clock by itself: it listens on a TCP
*clock endpoint* (``ClockLinkServer``, listed as ``clock`` in the endpoints file) and the process that
runs the engine drives it.  That process has its own ``LockstepClock`` (``attach``), paced at its own
``--speed``, holding at its own hold points, with one proxy participant per simulator of the other
process: when its clock moves to bench time t, the first proxy asks the simulator process to advance
to t and every proxy hands its simulator's report (e.g. the gyro line's peer and byte count) to the
local receivers (the gyro link reads exactly those bytes) before ``sleep`` returns.  So the scheduling
stays in ``LockstepClock``; this module only carries its "serve" step over a socket.

Protocol: ASCII lines ending in LF, one request then one reply, times as Python ``repr`` of a float
(they round-trip exactly).  One driving connection at a time.

===================  =========================================================================
request              reply
===================  =========================================================================
``NOW``              ``AT <t>``: the simulator's current bench time
``NAMES``            ``NAMES <json list>``: its participants, in serving order
``ADVANCE <t>``      ``AT <t> <json object>`` once every participant has served every instant up
                     to t (w1 files written, gyro frames up to t written on the line); the object
                     holds each participant's report by name.  t equal to the current time serves
                     that instant again (a driver that connected since); t earlier is refused
(connection refused  ``ERR busy: ...`` then the connection closes: another process drives it
by a second driver)
anything else        ``ERR <reason>``
===================  =========================================================================

The driving side raises ``LinkDown`` when the simulator process is gone (connection refused, closed,
reset) and ``DeviceTimeout`` when it does not answer within ``reply_timeout_s`` wall seconds; once
broken, every later instant fails at once with the same message.
"""
from __future__ import annotations

import json
import logging
import socket
import threading
from typing import Any

from bench.clock import LockstepClock
from bench.errors import DeviceTimeout, LinkDown, ProtocolError

log = logging.getLogger(__name__)

LINK_KIND = "lockstep_link"           # the endpoints file's clock description for a linked clock
REPLY_TIMEOUT_S = 300.0               # wall seconds: a safety net, a busy host only makes replies late
_MAX_LINE = 1 << 20


def _parse_address(address: str) -> tuple[str, int]:
    host, sep, port = str(address).rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"clock endpoint address must be host:port, got {address!r}")
    return host, int(port)


def _closed_by_peer(sock: socket.socket) -> bool:
    """True when the other end closed ``sock`` (or it failed); peeks, so no request is consumed."""
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


# ---------------------------------------------------------------------------------------- server side
class ClockLinkServer:
    """Serves ``clock`` (the simulator process's ``LockstepClock``) on a TCP clock endpoint (module
    docstring).  ``start()`` listens (port 0: any free port); ``address`` is ``host:port``."""

    def __init__(self, clock: LockstepClock, host: str = "127.0.0.1", port: int = 0) -> None:
        if not getattr(clock, "lockstep", False):
            raise ValueError("a clock endpoint serves a lockstep clock only")
        self.clock = clock
        self._host, self._port = host, port
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._driver: socket.socket | None = None
        self._driver_lock = threading.Lock()
        self._handling = threading.Lock()
        self._stop = threading.Event()
        self.instants_served = 0

    @property
    def address(self) -> str:
        if self._listener is None:
            raise RuntimeError("clock endpoint not started")
        host, port = self._listener.getsockname()[:2]
        return f"{host}:{port}"

    def to_json(self, pace: float | None) -> dict[str, Any]:
        """The endpoints file's ``clock``: where to drive it and the pace a driver uses by default."""
        return {"kind": LINK_KIND, "address": self.address, "pace": pace}

    def start(self) -> "ClockLinkServer":
        lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lst.bind((self._host, self._port))
        lst.listen(4)
        lst.settimeout(0.2)
        self._listener = lst
        self._stop.clear()
        self._thread = threading.Thread(target=self._accept_loop, name="clock-link", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        with self._driver_lock:
            driver, self._driver = self._driver, None
        if driver is not None:
            try:
                driver.shutdown(socket.SHUT_RDWR)      # the driver sees the end now (its reader holds the fd)
            except OSError:
                pass
        for sock in (driver, self._listener):
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass
        self._listener = None

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, peer = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            with self._driver_lock:
                busy = self._driver
                if busy is not None and _closed_by_peer(busy):
                    busy = None                  # its thread has not seen the end yet: it is gone
                if busy is None:
                    self._driver = conn
            if busy is not None:
                try:
                    conn.sendall(f"ERR busy: another process drives this bench's clock "
                                 f"(from {busy.getpeername()[0]}:{busy.getpeername()[1]})\n".encode())
                except OSError:
                    pass
                conn.close()
                continue
            threading.Thread(target=self._drive, args=(conn, peer), name="clock-link-driver", daemon=True).start()

    def _drive(self, conn: socket.socket, peer: tuple) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(None)
        reader = conn.makefile("rb")
        try:
            while not self._stop.is_set():
                line = reader.readline(_MAX_LINE)
                if not line:
                    return                                   # the driver went away; another may come
                with self._handling:         # a driver taking over waits for its predecessor's last instant
                    reply = self.handle(line.decode("ascii", "replace").strip())
                conn.sendall(reply.encode("ascii") + b"\n")
        except OSError as exc:
            log.info("clock link from %s:%s ended: %s", peer[0], peer[1], exc)
        finally:
            reader.close()
            with self._driver_lock:
                if self._driver is conn:
                    self._driver = None
            try:
                conn.close()
            except OSError:
                pass

    def handle(self, request: str) -> str:
        """The reply line to one request line."""
        verb, _, arg = request.partition(" ")
        verb = verb.upper()
        if verb == "NOW" and not arg:
            return f"AT {self.clock.now()!r}"
        if verb == "NAMES" and not arg:
            return "NAMES " + json.dumps(self.clock.participants())
        if verb == "ADVANCE":
            try:
                t = float(arg)
            except ValueError:
                return f"ERR ADVANCE needs a bench time in seconds, got {arg!r}"
            if t != t or t in (float("inf"), float("-inf")):
                return f"ERR ADVANCE needs a finite bench time, got {arg!r}"
            now = self.clock.now()
            if t < now:
                return f"ERR cannot go back: the bench time is {now!r}, asked {t!r}"
            try:
                if t == now and self.clock.instants > 0:
                    self.clock.serve_now()
                else:
                    self.clock.advance_to(t)
            except Exception as exc:  # noqa: BLE001 - the driver must learn why the instant failed
                log.exception("serving bench time %r failed", t)
                return f"ERR serving bench time {t!r}: {type(exc).__name__}: {exc}".replace("\n", " ")
            self.instants_served += 1
            return f"AT {self.clock.now()!r} {json.dumps(self.clock.last_reports, separators=(',', ':'))}"
        return f"ERR unknown request {request[:80]!r} (NOW, NAMES, ADVANCE <t>)"


# ---------------------------------------------------------------------------------------- driving side
class ClockLink:
    """The driving side's connection to a ``ClockLinkServer``; ``reports_for(name, t)`` is what each
    proxy participant calls (the first call for a new instant asks the simulator process to serve it)."""

    def __init__(self, address: str, reply_timeout_s: float = REPLY_TIMEOUT_S) -> None:
        self.address = address
        self.reply_timeout_s = reply_timeout_s
        self._lock = threading.Lock()
        self._broken: str | None = None
        self._t: float | None = None
        self._reports: dict[str, Any] = {}
        self._taken: set[str] = set()
        host, port = _parse_address(address)
        try:
            self._sock = socket.create_connection((host, port), timeout=10.0)
        except OSError as exc:
            raise LinkDown(f"simulated bench clock at {address}: cannot connect ({exc}); is `bench sim up` "
                           f"running?") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(reply_timeout_s)
        self._reader = self._sock.makefile("rb")
        try:
            self.names: list[str] = self._names()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        self._broken = self._broken or f"simulated bench clock at {self.address}: link closed by this process"
        for closable in (self._reader, self._sock):
            try:
                closable.close()
            except OSError:
                pass

    def now(self) -> float:
        verb, rest = self._request("NOW")
        return self._time(verb, rest, "NOW")

    def _names(self) -> list[str]:
        verb, rest = self._request("NAMES")
        try:
            names = json.loads(rest) if verb == "NAMES" else None
        except json.JSONDecodeError:
            names = None
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ProtocolError(f"simulated bench clock at {self.address}: bad reply to NAMES: {verb} {rest[:200]}")
        return names

    def advance(self, t: float) -> dict[str, Any]:
        """Ask the simulator process to serve bench time ``t``; its participants' reports."""
        verb, rest = self._request(f"ADVANCE {float(t)!r}")
        at, _, doc = rest.partition(" ")
        got = self._time(verb, at, "ADVANCE")
        if got != t:
            raise ProtocolError(f"simulated bench clock at {self.address}: asked to serve {t!r}, it is at {got!r}")
        try:
            reports = json.loads(doc)
        except json.JSONDecodeError:
            reports = None
        if not isinstance(reports, dict):
            raise ProtocolError(f"simulated bench clock at {self.address}: bad reports in {rest[:200]!r}")
        return reports

    def reports_for(self, name: str, t: float) -> dict[str, Any] | None:
        """Proxy participant ``name`` at bench time ``t``: one ADVANCE per serving of an instant,
        whichever proxy the local clock calls first (a proxy asking again means a new serving)."""
        with self._lock:
            if self._t != t or name in self._taken:
                self._t, self._taken = None, set()
                self._reports = self.advance(t)
                self._t = t
            self._taken.add(name)
            return self._reports.get(name)

    def _time(self, verb: str, text: str, what: str) -> float:
        try:
            if verb != "AT":
                raise ValueError
            return float(text)
        except ValueError:
            raise ProtocolError(f"simulated bench clock at {self.address}: bad reply to {what}: "
                                f"{verb} {text[:200]}") from None

    def _request(self, line: str) -> tuple[str, str]:
        if self._broken:
            raise LinkDown(self._broken)
        try:
            self._sock.sendall(line.encode("ascii") + b"\n")
            reply = self._reader.readline(_MAX_LINE)
        except socket.timeout:
            self._broken = (f"simulated bench clock at {self.address}: no answer to {line!r} within "
                            f"{self.reply_timeout_s:g} s (is the `bench sim up` process stopped?)")
            raise DeviceTimeout(self._broken) from None
        except OSError as exc:
            self._broken = (f"simulated bench clock at {self.address}: the link broke ({exc}); the `bench sim "
                            f"up` process is gone")
            raise LinkDown(self._broken) from None
        if not reply:
            self._broken = (f"simulated bench clock at {self.address}: the simulator closed the link; the "
                            f"`bench sim up` process is gone")
            raise LinkDown(self._broken)
        verb, _, rest = reply.decode("ascii", "replace").strip().partition(" ")
        if verb == "ERR":
            if rest.startswith("busy"):
                self._broken = f"simulated bench clock at {self.address}: {rest}"
                raise LinkDown(self._broken)
            raise ProtocolError(f"simulated bench clock at {self.address}: {line!r} refused: {rest}")
        return verb, rest


def attach(address: str, pace: float | None, *, hold_file: str | None = None,
           reply_timeout_s: float = REPLY_TIMEOUT_S) -> LockstepClock:
    """A ``LockstepClock`` of this process that drives the simulated bench's clock at ``address``: it
    starts at the simulator's bench time, is paced at ``pace`` (None: as fast as the host can) and
    holds at ``hold_file``'s instants; every simulator of the other process is a participant here."""
    link = ClockLink(address, reply_timeout_s)
    clock = LockstepClock(link.now(), pace, hold_file=hold_file)
    clock.link = link                     # type: ignore[attr-defined]  # kept alive with the clock
    for name in link.names:
        clock.serve(name, lambda t, _name=name: link.reports_for(_name, t))
    return clock


def clock_from_link_json(data: dict[str, Any]) -> LockstepClock:
    """``attach`` from the endpoints file's clock description (``ClockLinkServer.to_json``)."""
    try:
        address = str(data["address"])
    except KeyError:
        raise ValueError(f"linked clock description without an address: {data!r}") from None
    pace = data.get("pace")
    if pace is not None and not float(pace) > 0:
        raise ValueError(f"linked clock pace must be > 0 or null, got {pace!r}")
    return attach(address, None if pace is None else float(pace), hold_file=data.get("hold_file"))
