"""The whole simulated bench in one process: every device model wired to the others through physics,
every protocol server on a real loopback transport, one shared clock.

    bench = SimulatedBench(speed=3600, scenario="default")
    bench.start()
    bench.endpoints      # {"chamber_modbus_tcp": "127.0.0.1:PORT", "turntable": "socket://...", ...}
    bench.config         # a BenchConfig whose drivers talk to the simulators unchanged
    bench.stop()

Wiring: the chamber air drives the gyro's thermal network; the turntable's angles give the gyro's
orientation (Earth rate, gravity) and its axis rates the input rate; the power supply's output
switches the gyro on (self-heating, warm-up) and off; the DS18B20 tree reads the gyro's probe nodes.
"""
from __future__ import annotations

import base64
import contextlib
import json
import os
import pickle
import shutil
import tempfile
import threading
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from bench.clock import AcceleratedClock, Clock, LockstepClock, SteppedClock
from bench.config import (BenchConfig, ChamberConfig, GyroConfig, ProbeConfig, PsuConfig, TurntableConfig)
from bench.devices.orientation import check_geometry, rotation_about
from bench.sim.audit import Received
from bench.sim.chamber import ChamberSimulator
from bench.sim.chamber_physics import ChamberModel
from bench.sim.gyro import GyroStreamSimulator
from bench.sim.lookahead import DeviceTrack, Lookahead
from bench.sim.physics import GyroPhysics, InputBatch, PhysicsInputs
from bench.sim.psu import PsuModel, PsuSimulator
from bench.sim.scenario import Scenario
from bench.sim.turntable import TableModel, TurntableSimulator
from bench.sim.w1 import W1TreeSimulator

# gyro data rate (Hz, bench time) per clock speed: keeps the frame rate on the wire a few thousand/s
_RATES = (1000, 500, 250, 100, 50, 25, 10, 5, 1)


# on a lockstep clock the frame rate costs host time, not accuracy: the simulated default is
# decimated to 1 Hz (the physics integrates on its own grid; each frame is a 1-s sample)
LOCKSTEP_DATA_RATE_HZ = 1
# wall seconds a driver waits for a simulator's reply on the lockstep bench (see bench_config)
LOCKSTEP_REPLY_TIMEOUT_S = 30.0
# a snapshot goes into every run checkpoint (every two bench minutes): zlib's fastest level packs its
# ~15 kB of state within 3 % of the default level's size in a quarter of the time
SNAPSHOT_ZLIB_LEVEL = 1
# a seeded simulated bench starts at this bench instant (2026-01-01T00:00:00Z), so the same scenario
# and seed give the same bench times, not only the same values
SEEDED_EPOCH_S = 1_767_225_600.0


def lockstep_clock(pace: float | None, seed: int | None = None) -> LockstepClock:
    """The simulated bench's clock: paced at ``pace`` x wall at most (None: as fast as the host can),
    starting at ``SEEDED_EPOCH_S`` when seeded, else at the current whole wall second."""
    import time

    return LockstepClock(SEEDED_EPOCH_S if seed is not None else float(int(time.time())), pace)


def default_data_rate(speed: float) -> int:
    for rate in _RATES:
        if rate * speed <= 5000:
            return rate
    return 1


def probe_serials(names: list[str]) -> dict[str, str]:
    """Stable 12-hex-digit DS18B20 serials for the scenario's probe names."""
    return {name: f"0000{0xA1B2C300 + i:08x}" for i, name in enumerate(names)}


class SimulatedBench:
    def __init__(self, *, speed: float = 3600.0, scenario: str | Scenario = "default",
                 clock: Clock | None = None, data_rate_hz: int | None = None, w1_root: str | None = None,
                 bench_name: str = "sim1", latitude_deg: float | None = None,
                 initial_air_c: float = 23.0, seed: int | None = None) -> None:
        self.clock = clock or AcceleratedClock(speed)
        self.scenario = scenario if isinstance(scenario, Scenario) else _load_scenario(scenario)
        if latitude_deg is not None:
            self.scenario = self.scenario.with_changes(latitude_deg=latitude_deg)
        if seed is not None:
            self.scenario = self.scenario.with_changes(seed=int(seed))
        self.seed = self.scenario.seed
        self.lockstep = isinstance(self.clock, LockstepClock)
        speed_eff = 1e6 if isinstance(self.clock, SteppedClock) else self.clock.speed
        self.data_rate_hz = data_rate_hz or (LOCKSTEP_DATA_RATE_HZ if self.lockstep else default_data_rate(speed_eff))
        self.bench_name = bench_name
        self._own_w1 = w1_root is None
        # a memory file system when there is one (sysfs is memory too, and a disk journal makes every
        # rewrite cost milliseconds), unless the user names a temporary directory with $TMPDIR
        shm = ("/dev/shm" if not os.environ.get("TMPDIR") and Path("/dev/shm").is_dir()
               and os.access("/dev/shm", os.W_OK) else None)
        self.w1_root = Path(w1_root or tempfile.mkdtemp(prefix="bench-w1-", dir=shm))
        base = BenchConfig()
        self.geometry = base.turntable.geometry
        self._outer_axis, self._inner_axis, self._mounting = check_geometry(self.geometry)   # validated once
        t0 = self.clock.now()
        self.chamber_model = ChamberModel(air_c=initial_air_c, setpoint_c=initial_air_c)
        self.chamber_model.advance_to(t0)
        self.table_model = TableModel(axes=2)
        self.table_model.advance_to(t0)
        self.psu_model = PsuModel()
        self.psu_model.advance_to(t0)
        self._lock = threading.RLock()
        # the chamber and table states along the physics' times, shared by every gyro of the bench
        self.device_track = DeviceTrack(self.chamber_model, self.table_model, t0)
        if self.lockstep:
            # integrated in blocks ahead of the clock, on exact device states (bench.sim.lookahead)
            inputs = _RowInputs(self)
            inputs.rows[t0] = device_inputs_row(self, self.chamber_model, self.table_model, self.psu_model, t0)
            self.physics = GyroPhysics(self.scenario, t0, inputs, output_period_s=1.0 / self.data_rate_hz)
            self.lookahead: Lookahead | None = Lookahead(self, self.physics, inputs)
            source = self.lookahead
        else:
            self.physics = GyroPhysics(self.scenario, t0, _BenchInputs(self), output_period_s=1.0 / self.data_rate_hz)
            self.lookahead = None
            source = self.physics
        self.probe_names = list(self.scenario.probes)
        self.serials = probe_serials(self.probe_names)
        self.chamber = ChamberSimulator(self.chamber_model, self.clock)
        self.turntable = TurntableSimulator(self.table_model, self.clock)
        self.psu = PsuSimulator(self.psu_model, self.clock)
        frame = "hrg" if self.scenario.gyro_type == "hrg" else "kvh_a"
        self.gyro = GyroStreamSimulator(source, self.clock, self.data_rate_hz, frame)
        # refresh the w1 files often in wall time: at x3600 a 20 ms refresh would make every reading
        # up to 72 bench seconds old (a real read triggers a fresh conversion)
        self.w1 = W1TreeSimulator(source, self.clock, self.w1_root, self.serials, min_wall_interval_s=0.005)
        self.started = False
        # the endpoints file's clock when another process drives this bench's lockstep clock
        # (``bench.clocklink.ClockLinkServer.to_json``); None: this clock's own description
        self.clock_endpoint: dict[str, Any] | None = None

    # ---------------------------------------------------------------- physics inputs
    def _air_c(self, t: float) -> float:
        self.chamber_model.advance_to(t)
        return self.chamber_model.air_c

    def _angles(self, t: float) -> tuple[float, float]:
        self.table_model.advance_to(t)
        a = self.table_model.angles()
        return a[self.geometry.outer_axis_number - 1], a[self.geometry.inner_axis_number - 1]

    def _body_to_level(self, t: float) -> np.ndarray:
        outer_deg, inner_deg = self._angles(t)
        return (rotation_about(self._outer_axis, outer_deg) @ rotation_about(self._inner_axis, inner_deg)
                @ self._mounting)

    def _table_rate_body(self, t: float) -> np.ndarray:
        outer_deg, _ = self._angles(t)
        r = self.table_model.rates()
        w_outer = r[self.geometry.outer_axis_number - 1]
        w_inner = r[self.geometry.inner_axis_number - 1]
        inner_axis = rotation_about(self._outer_axis, outer_deg) @ self._inner_axis
        omega_level = w_outer * self._outer_axis + w_inner * inner_axis
        return self._body_to_level(t).T @ omega_level

    def _powered(self, t: float) -> bool:
        self.psu_model.advance_to(t)
        return bool(self.psu_model.output_on)

    def _power_on_time(self, t: float) -> float | None:
        self.psu_model.advance_to(t)
        return self.psu_model.on_since if self.psu_model.output_on else None

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> "SimulatedBench":
        if self.started:
            return self
        self.chamber.start()
        for server in (self.turntable, self.psu, self.gyro, self.w1):
            server.start()
        if self.lockstep:
            # the gyro first: its frames since the last instant are sampled on the way to the new
            # instant (the physics cannot rewind); the probes then read the state at the instant
            self.clock.serve("gyro", self.gyro.serve)
            self.clock.serve("w1", self.w1.serve)
        self.started = True
        return self

    def stop(self) -> None:
        if self.lockstep:
            self.clock.forget("w1")
            self.clock.forget("gyro")
        for server in (self.w1, self.gyro, self.psu, self.turntable, self.chamber):
            try:
                server.stop()
            except Exception:   # noqa: BLE001 - stopping must reach every server
                pass
        self.started = False
        if self._own_w1:
            shutil.rmtree(self.w1_root, ignore_errors=True)

    def __enter__(self) -> "SimulatedBench":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # ---------------------------------------------------------------- continuity
    def snapshot(self) -> dict[str, Any]:
        """The bench's physical state at the current bench instant (chamber air and controller, table,
        supply, the gyro's thermal network and noise processes, the probes' last conversions, the gyro
        line's frame counter), for a run checkpoint.  ``restore`` puts it back."""
        with self._lock, (self.lookahead.at_instant() if self.lookahead is not None else contextlib.nullcontext()):
            parts = {name: _fields(name, obj) for name, obj in self._state_objects().items()}   # at the instant
            return {"version": SNAPSHOT_VERSION, "t": self.clock.now(), "scenario": self.scenario.name,
                    "seed": self.seed,
                    "state": base64.b64encode(zlib.compress(pickle.dumps(parts, protocol=5),
                                                            SNAPSHOT_ZLIB_LEVEL)).decode("ascii")}

    def restore(self, snap: dict[str, Any]) -> float:
        """Put back a ``snapshot`` (taken by this program on a bench of the same scenario); returns its
        bench time.  The caller then moves the clock on (``LockstepClock.jump_to``)."""
        if snap.get("version") != SNAPSHOT_VERSION:
            raise ValueError(f"simulated bench snapshot version {snap.get('version')!r} is not {SNAPSHOT_VERSION}")
        parts = pickle.loads(zlib.decompress(base64.b64decode(snap["state"])))
        with self._lock:
            for name, obj in self._state_objects().items():
                if name not in parts:
                    raise ValueError(f"simulated bench snapshot has no {name!r} state")
                vars(obj).update(parts[name])
            self.device_track.reset(float(snap["t"]))
            if self.lookahead is not None:
                self.lookahead.reset(float(snap["t"]))
        return float(snap["t"])

    def _state_objects(self) -> dict[str, Any]:
        objects = {"chamber": self.chamber_model, "table": self.table_model, "psu": self.psu_model,
                   "physics": self.physics, "inputs": self.physics.inputs, "w1": self.w1, "gyro": self.gyro}
        if self.lookahead is not None:
            del objects["inputs"]      # recorded again from the device models after a restore
        return objects

    # ---------------------------------------------------------------- addresses
    @property
    def endpoints(self) -> dict[str, Any]:
        return {
            "chamber_modbus_tcp": self.chamber.tcp_address,
            "chamber_modbus_rtu": self.chamber.rtu_url,
            "turntable": self.turntable.url,
            "gyro": self.gyro.url,
            "psu": self.psu.url,
            "w1_root": str(self.w1_root),
            "probes": dict(self.serials),
            "gyro_frame": "hrg" if self.scenario.gyro_type == "hrg" else "kvh_a",
            "gyro_data_rate_hz": self.data_rate_hz,
            "clock": self.clock_endpoint or self.clock.to_json(),
            "seed": self.seed,
        }

    def bench_config(self, *, chamber_transport: str = "modbus_tcp") -> BenchConfig:
        """A bench config whose drivers talk to these simulators; with real hardware only the
        addresses differ."""
        e = self.endpoints
        chamber_addr = e["chamber_modbus_tcp"] if chamber_transport == "modbus_tcp" else e["chamber_modbus_rtu"]
        # in lockstep bench time a reply that is late in wall time only means the host is busy (the
        # simulators answer at the same bench instant whatever the delay): wall timeouts are generous,
        # so load slows the run instead of changing what it records
        reply_s = LOCKSTEP_REPLY_TIMEOUT_S if self.lockstep else None
        return BenchConfig(
            name=self.bench_name,
            latitude_deg=self.scenario.latitude_deg,
            chamber=ChamberConfig(transport=chamber_transport, address=chamber_addr, inter_frame_delay_s=0.0,
                                  baudrate=115200, timeout_s=reply_s or 2.0),
            turntable=TurntableConfig(url=e["turntable"], geometry=self.geometry,
                                      **({"timeout_s": reply_s} if reply_s else {})),
            gyro=GyroConfig(url=e["gyro"], frame=e["gyro_frame"], data_rate_hz=self.data_rate_hz,
                            channels=tuple(self.scenario.channels),
                            channel_probes=self.scenario.channel_probe_map()),
            probes=ProbeConfig(w1_root=e["w1_root"], probes=dict(self.serials)),
            psu=PsuConfig(url=e["psu"], **({"timeout_s": reply_s} if reply_s else {})),
        )

    @property
    def config(self) -> BenchConfig:
        return self.bench_config()

    def received(self) -> list[Received]:
        """Every request the chamber, turntable, power supply and gyro received, in order of arrival
        (``bench.sim.audit``: the bench side's record of which link commanded what, when)."""
        logs = (self.chamber.received, self.turntable.received, self.psu.received, self.gyro.received)
        return sorted((e for log in logs for e in log.entries()), key=lambda e: e.mono)

    def write_endpoints(self, path: str | Path) -> None:
        doc = dict(self.endpoints)
        doc["bench_config"] = json.loads(self.config.model_dump_json())
        tmp = Path(str(path) + ".tmp")
        tmp.write_text(json.dumps(doc, indent=2))
        tmp.replace(path)


SNAPSHOT_VERSION = 1
# a snapshot keeps each object's plain state, not its wiring (locks, threads, sockets, the clock,
# other devices, callbacks) nor caches; for the servers only the fields named here
_WIRING = (type(threading.Lock()), type(threading.RLock()), threading.Event, threading.Thread,
           threading.Condition)
_SKIP = ("_cache", "inputs", "clock", "bench", "source", "faults", "sent_log")
_SERVER_STATE = {
    "w1": ("_retained", "last_update_t", "updates"),
    "gyro": ("_sequence", "_next_index", "_base_t", "_rate", "_config_mode", "overrun_frames"),
}


def _fields(name: str, obj: Any) -> dict[str, Any]:
    name = name.split(":")[0]          # "gyro:g2": the second gyro of a multi-gyro bench
    if name in _SERVER_STATE:
        return {key: getattr(obj, key) for key in _SERVER_STATE[name]}
    return {key: value for key, value in vars(obj).items()
            if key not in _SKIP and not isinstance(value, _WIRING) and not callable(value)}


class _BenchInputs(PhysicsInputs):
    """The physics' view of the other devices, evaluated for a whole batch of times at once.

    Each device model is advanced once per batch (to the batch's last time) and its state recorded;
    values at earlier times in the batch are interpolated from that short history (chamber air and
    table angles are smooth; the power switch is placed at the PSU's own switch-on time).  Calling
    every model once per gyro sample instead costs more than the gyro physics itself at x3600.
    """

    HISTORY = 512           # states kept (each batch interpolates within its own short span)

    def __init__(self, bench: "SimulatedBench") -> None:
        super().__init__(bench._air_c, bench._body_to_level, bench._table_rate_body, bench._powered,
                         bench._power_on_time)
        self.bench = bench
        self._n = 0
        # columns: t, air, outer, inner, w_outer, w_inner, on, on_since (nan when off)
        self._hist = np.empty((self.HISTORY, 8))
        self._still: tuple[bytes, np.ndarray, np.ndarray] | None = None   # pose of a table at rest

    def _record(self, t: float) -> None:
        if self._n and t <= self._hist[self._n - 1, 0]:
            return
        if self._n == self.HISTORY:
            keep = self.HISTORY // 2
            self._hist[:keep] = self._hist[self._n - keep:self._n]
            self._n = keep
        self._hist[self._n] = device_inputs_row(self.bench, self.bench.chamber_model, self.bench.table_model,
                                                self.bench.psu_model, t)
        self._n += 1

    def batch(self, times: np.ndarray) -> InputBatch:
        times = np.asarray(times, dtype=float)
        self._record(float(times[-1]))
        h = self._hist[:self._n]
        # the span that matters: from the last state at or before the batch's first time
        first = max(0, int(np.searchsorted(h[:, 0], times[0], side="right")) - 1)
        return self._from_history(times, h[first:])

    def _from_history(self, times: np.ndarray, h: np.ndarray) -> InputBatch:
        """Inputs at ``times`` from device states ``h`` (rows of ``device_inputs_row``, increasing
        in time): interpolated between rows; a time that is a row's own time gets that row."""
        hist_t = h[:, 0]
        air = np.interp(times, hist_t, h[:, 1])
        table = h[:, 2:6]
        if (table == table[0]).all():      # table standing still over the span (the usual case)
            key = table[0].tobytes()
            if self._still is None or self._still[0] != key:
                self._still = (key, *self._table_pose(times[-1:], h[:1]))
            body = np.repeat(self._still[1], times.size, axis=0)
            table_rate_body = np.repeat(self._still[2], times.size, axis=0)
        else:
            body, table_rate_body = self._table_pose(times, h)
        # power: the state recorded at or after each time; switched on from the PSU's switch-on time
        k = np.clip(np.searchsorted(hist_t, times, side="left"), 0, len(hist_t) - 1)
        power = h[k, 6] > 0.5
        since = h[k, 7]
        powered = power & ~(times < since)
        return InputBatch(air_c=air, body_to_level=body, table_rate_body_dps=table_rate_body,
                          powered=powered, power_on_time=np.where(powered, since, np.nan))

    def _table_pose(self, times: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body-to-level matrices (n, 3, 3) and table rates on body axes (n, 3) at ``times``,
        interpolated in the history rows ``h`` (angles unwrapped)."""
        hist_t = h[:, 0]
        ang = np.unwrap(np.radians(h[:, 2:4]), axis=0)
        outer = np.degrees(np.interp(times, hist_t, ang[:, 0]))
        inner = np.degrees(np.interp(times, hist_t, ang[:, 1]))
        w_outer = np.interp(times, hist_t, h[:, 4])
        w_inner = np.interp(times, hist_t, h[:, 5])
        b = self.bench
        r_outer = _rotations(b._outer_axis, outer)
        r_inner = _rotations(b._inner_axis, inner)
        body = r_outer @ r_inner @ b._mounting
        inner_axis_level = r_outer @ b._inner_axis
        omega_level = w_outer[:, None] * b._outer_axis + w_inner[:, None] * inner_axis_level
        return body, np.einsum("nji,nj->ni", body, omega_level)


class _RowInputs(_BenchInputs):
    """The lockstep bench's physics inputs: device states recorded exactly at each time the physics
    asks for (by ``bench.sim.lookahead.Lookahead``, on copies of the device models), no interpolation."""

    def __init__(self, bench: "SimulatedBench") -> None:
        super().__init__(bench)
        self.rows: dict[float, np.ndarray] = {}

    def batch(self, times: np.ndarray) -> InputBatch:
        times = np.asarray(times, dtype=float)
        try:
            h = np.array([self.rows[float(t)] for t in times])
        except KeyError as exc:
            raise RuntimeError(f"lockstep physics inputs: no device state recorded for bench time {exc.args[0]!r}") from None
        if times.size > 1 and np.any(np.diff(times) <= 0):       # interpolation needs increasing rows
            h = np.unique(h, axis=0)
        return self._from_history(times, h)


def device_inputs_row(bench: "SimulatedBench", chamber: ChamberModel, table: TableModel, psu: PsuModel,
                      t: float) -> np.ndarray:
    """What the gyro physics takes from the other devices at bench time ``t`` (each model advanced to
    ``t``): t, chamber air, outer and inner table angles and rates, supply output on, its switch-on time."""
    chamber.advance_to(t)
    table.advance_to(t)
    psu.advance_to(t)
    g = bench.geometry
    a = table.angles()
    r = table.rates()
    on = bool(psu.output_on)
    since = psu.on_since if on else None
    return np.array((t, chamber.air_c, a[g.outer_axis_number - 1], a[g.inner_axis_number - 1],
                     r[g.outer_axis_number - 1], r[g.inner_axis_number - 1], float(on),
                     np.nan if since is None else float(since)))


def _rotations(axis: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    """Rodrigues rotation matrices (n, 3, 3) about one unit axis, for many angles."""
    a = np.radians(angles_deg)[:, None, None]
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def _load_scenario(name_or_path: str) -> Scenario:
    path = Path(name_or_path)
    if path.suffix == ".json" or path.exists():
        return Scenario.load(path)
    return Scenario.builtin(name_or_path)
