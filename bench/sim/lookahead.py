"""The lockstep bench's gyro physics, integrated in blocks ahead of the clock and used only while
nothing has changed.

On a lockstep clock every bench instant (every 2 s) asks the physics for its frames (one or two) and
the probes' temperatures.  Integrated one instant at a time, numpy's per-call overhead is most of a
run's CPU.  ``Lookahead`` integrates a block of grid steps at once, up to ``MAX_AHEAD_S`` bench
seconds past the instant, on *copies* of the chamber, turntable and supply models advanced one grid
step at a time (their exact state at every grid time, no interpolation), and serves each instant's
frames and probe temperatures from that block.

Causality: a block is used for the next instant only if the real device models, which the simulators'
front-ends read and command, are at that moment exactly in the state they were left in at the last
served instant (their pickled state, random generators of measurement noise aside): the unit's own
supply compared here, the shared chamber and table by the bench's ``DeviceTrack`` (its ``epoch``).
Any difference (a set point, a move, the supply switched, an injected fault: anything a command or a
test changed) drops the rest of the block: the physics is put back to the last served instant
(``GyroPhysics.checkpoint`` / ``rollback`` and the block's own inputs up to there) and integrates on
from the models' state at that instant, commands included.  So a command acts at the bench instant it
was given, as before; which blocks are computed depends only on bench-time events, so the same
scenario and seed give the same data at any speed and load.

Block mode needs the instants and the frames on the physics grid (the lockstep default: 1 Hz frames,
a 1 s grid, instants on whole bench seconds).  Otherwise (an instant or a frame between grid points)
the physics is driven instant by instant, as ``GyroPhysics.sample_many`` does, on the same exact
device states.

Device states at the times the physics asks for: the chamber and table are one pair of models on a
bench with several gyros.  One ``DeviceTrack`` per bench advances them to each instant once (whichever
unit is served first) and keeps their state at the instant before, so every unit integrates from the
same state along the same inputs, served first or last, and a unit's served bytes are those of a bench
of its own; the states along a list of times are computed on one pair of copies and reused by every
unit that asks for the same times from the same state.  The supply is static between commands
(``PsuModel``), so its columns are its state when asked.

Block length: ``MIN_AHEAD_S`` after a block had to be dropped, doubling (to ``MAX_AHEAD_S``) each time
a block is used to its end, so a stretch of commands (a table move) costs little extra work.
"""
from __future__ import annotations

import contextlib
import io
import math
import pickle
import random
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from bench.sim.physics import GyroPhysics, GyroSample, Outputs, SampleRows

if TYPE_CHECKING:   # pragma: no cover
    from bench.sim.bench import SimulatedBench, _RowInputs

_LOCKS = (type(threading.Lock()), type(threading.RLock()))
_NOISE = (random.Random, np.random.Generator)      # measurement noise of reads: not the physics' inputs
_SKIP_TYPES = frozenset(_LOCKS + _NOISE)
_SCALARS = frozenset((int, float, bool, str, bytes, type(None)))
MAX_BLOCK_STEPS = 100_000      # a longer jump (an outage passing) goes the physics' own chunked way


def fingerprint(models: Sequence[Any]) -> bytes | tuple:
    """The models' state: an equal fingerprint, the same future physics inputs.  Models whose fields are
    all plain scalars (a supply, checked at every instant by every unit) give a tuple of (name, type, value);
    others their state pickled without a memo, so equal values give equal bytes whether or not the model
    shares one object between fields."""
    flat = _flat_state(models)
    if flat is not None:
        return flat
    state: list[Any] = []
    for m in models:
        d = vars(m)
        state.append(tuple(d))
        state.append([v for v in d.values() if type(v) not in _SKIP_TYPES])
    buf = io.BytesIO()
    p = pickle.Pickler(buf, protocol=5)
    p.fast = True            # no memo (the states hold no cycles)
    p.dump(state)
    return buf.getvalue()


def _flat_state(models: Sequence[Any]) -> tuple | None:
    """(name, type, value) of every field of ``models`` when all are plain scalars (else None)."""
    out: list[tuple] = []
    for m in models:
        for k, v in vars(m).items():
            tv = type(v)
            if tv in _SCALARS:
                out.append((k, tv, v))
            elif tv not in _SKIP_TYPES:
                return None
        out.append(None)            # the end of one model's fields
    return tuple(out)


def freeze(model: Any) -> bytes:
    """A device model's whole state as bytes (its locks aside), to be ``thaw``-ed into a copy."""
    return pickle.dumps({k: v for k, v in vars(model).items() if not isinstance(v, _LOCKS)}, protocol=5)


def thaw(frozen: bytes, like: Any) -> Any:
    """An independent model of ``like``'s type in the ``freeze``-d state (locks of its own)."""
    copy = object.__new__(type(like))
    vars(copy).update(pickle.loads(frozen))
    for k, v in vars(like).items():
        if isinstance(v, _LOCKS):
            vars(copy)[k] = threading.RLock() if isinstance(v, _LOCKS[1]) else threading.Lock()
    return copy


def clone(model: Any) -> Any:
    """An independent copy of a device model (own lock, state deep-copied)."""
    return thaw(freeze(model), model)


class DeviceTrack:
    """The chamber and table of one bench along bench time, for every gyro on it.

    The real models are brought to each bench instant once, by ``instant`` (the first unit served at
    that instant calls it; the others find them there), and the state they had at the instant before,
    with the commands given during it, is kept: a unit integrates from there along the same inputs
    whether it is served first or last.  ``epoch`` counts the instants at which the models were found
    changed since the previous one (a set point, a move, a fault): a unit's block ahead is still right
    while the epoch is the one it was built in.  ``states`` gives the air, angles and rates along grid
    times from the state at a unit's last served instant, on copies (the real models stay where they
    are), through the states kept for each instant since (a unit that skipped instants, its line in
    config mode, integrates on what the chamber did meanwhile); the units of one bench ask for the
    same times from the same instant, so the last answer is kept and reused."""

    def __init__(self, chamber: Any, table: Any, t0: float) -> None:
        self.chamber, self.table = chamber, table
        self._lock = threading.RLock()
        self._units: list["Lookahead"] = []
        self.computed = 0                  # tracks integrated (not reused), for the benchmarks
        self.reused = 0
        self.epoch = 0
        self.reset(t0)

    def join(self, unit: "Lookahead") -> None:
        """``unit`` integrates on this track: states are kept back to its last served instant."""
        with self._lock:
            self._units.append(unit)

    def reset(self, t: float) -> None:
        """The models were put in the state of bench instant ``t`` (a restored snapshot)."""
        with self._lock:
            self._t = float(t)
            self._fp = fingerprint((self.chamber, self.table))
            # instant -> (fingerprint, chamber frozen, table frozen): their state before the next instant
            self._kept: dict[float, tuple[bytes, bytes, bytes]] = {}
            self._key: tuple | None = None
            self._states: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
            self.epoch += 1

    def instant(self, t: float) -> int:
        """The real models at bench instant ``t`` (advanced there once; an instant already reached is
        left alone); returns the epoch."""
        with self._lock:
            if t <= self._t:
                return self.epoch
            models = (self.chamber, self.table)
            before = fingerprint(models)
            if before != self._fp:
                self.epoch += 1
            self._kept[self._t] = (before, freeze(self.chamber), freeze(self.table))
            behind = min((u._t for u in self._units), default=self._t)
            for old in [k for k in self._kept if k < behind]:
                del self._kept[old]
            for m in models:
                m.advance_to(t)
            self._t = float(t)
            self._fp = fingerprint(models)
            return self.epoch

    def states(self, since: float, times: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(air (n,), angles (n, axes), rates (n, axes)) at ``times`` (increasing, after ``since``
        or at it), as the models went from their state at instant ``since``: between two kept
        instants from the state at the first, past the last one on from there."""
        with self._lock:
            if since >= self._t:       # the live models (no unit moved past this instant yet)
                bases = [(since, (fingerprint((self.chamber, self.table)), None, None))]
            else:
                bases = [(k, v) for k, v in self._kept.items() if k >= since]
                if not bases or bases[0][0] != since:
                    raise RuntimeError(f"device track: no chamber and table state kept for bench instant {since!r} "
                                       f"(kept: {sorted(self._kept)[:1]}..{sorted(self._kept)[-1:]})")
            # equal fingerprints of the states the track starts from, equal states along it
            key = (since, tuple(times), tuple((k, v[0]) for k, v in bases))
            if key == self._key and self._states is not None:
                self.reused += 1
                return self._states

            def start(base: tuple[bytes, bytes | None, bytes | None]) -> tuple[Any, Any]:
                if base[1] is None:
                    return clone(self.chamber), clone(self.table)
                return thaw(base[1], self.chamber), thaw(base[2], self.table)

            i = 0
            c, tb = start(bases[0][1])
            air, ang, rates = [], [], []
            for g in key[1]:
                while i + 1 < len(bases) and g > bases[i + 1][0]:
                    i += 1
                    c, tb = start(bases[i][1])
                c.advance_to(g)
                tb.advance_to(g)
                air.append(c.air_c)
                ang.append(tb.angles())
                rates.append(tb.rates())
            self._key = key
            self._states = (np.array(air, dtype=float), np.array(ang, dtype=float).reshape(len(air), -1),
                            np.array(rates, dtype=float).reshape(len(air), -1))
            self.computed += 1
            return self._states


@dataclass
class _Block:
    checkpoint: tuple                  # the physics at t0
    t0: float                          # block start (an instant already served)
    index: dict[float, int]            # grid time -> row of ``out``
    out: Outputs
    end: float                         # its last grid time
    samples: SampleRows                # the gyro sample of each row of ``out``


class Lookahead:
    """A ``GyroSource`` / probe source over ``GyroPhysics`` for the lockstep bench (module docstring)."""

    MIN_AHEAD_S = 4.0
    MAX_AHEAD_S = 512.0

    def __init__(self, bench: "SimulatedBench", physics: GyroPhysics, inputs: "_RowInputs") -> None:
        self.bench = bench
        self.physics = physics
        self.inputs = inputs
        self.clock = bench.clock
        self._lock = threading.RLock()
        self._t = physics.clock_start          # the instant served last: the physics' public present
        self._block: _Block | None = None
        self._fp: bytes | None = None          # the supply's state when it was last advanced
        self._epoch = -1                       # the chamber and table's (``DeviceTrack.epoch``) then
        self._ahead = self.MIN_AHEAD_S
        self.stats = {"blocks": 0, "dropped": 0, "direct": 0}
        bench.device_track.join(self)

    # ---- GyroSource / ProbeSource ------------------------------------------------------------
    def advance_to(self, t: float) -> None:
        with self._lock:
            self._at(float(t), None)

    def sample(self, t: float) -> GyroSample:
        return self.sample_many([t])[0]

    def sample_many(self, times: Sequence[float]) -> list[GyroSample]:
        times = [float(x) for x in times]
        if not times:
            return []
        if any(b < a for a, b in zip(times, times[1:])):
            raise ValueError("sample_many needs non-decreasing times")
        with self._lock:
            return self._at(max(self.clock.now(), times[-1], self._t), times)

    def probe_temperatures(self) -> dict[str, float]:
        with self._lock:
            blk = self._block
            if blk is None:
                return self.physics.probe_temperatures()
            row = blk.index[self._t]
            return {p: float(v[row]) for p, v in blk.out.probes_c.items()}

    def node_temperatures(self) -> dict[str, float]:
        with self._lock:
            blk = self._block
            if blk is None:
                return self.physics.node_temperatures()
            temps = blk.out.trajectory.temps[blk.index[self._t]]
            return {n: float(temps[i]) for n, i in self.physics._node_idx.items()}

    # ---- continuity ---------------------------------------------------------------------------
    def settle(self) -> None:
        """Put the physics back at the last served instant (the block ahead is dropped)."""
        with self._lock:
            self._settle()

    @contextlib.contextmanager
    def at_instant(self) -> Iterator[None]:
        """The physics at the last served instant while the block is open (a snapshot of the bench),
        then back where it was, block and all: a checkpoint every two bench minutes would otherwise
        drop the block each time and integrate again from the shortest look-ahead.  The state reached
        at the instant becomes the block's start (an instant already served, the same steps on the same
        inputs), so the next settle integrates again only from there, not from the block's start: with
        blocks of up to ``MAX_AHEAD_S`` and a checkpoint every two minutes, every unit re-integrated on
        average half a block at each checkpoint."""
        with self._lock:
            blk, ph = self._block, self.physics
            if blk is None or ph._state.t <= self._t:
                yield
                return
            ahead = ph.checkpoint()
            self._settle()
            here = ph.checkpoint()
            try:
                yield
            finally:
                ph.rollback(ahead)
                self._block = _Block(here, self._t, blk.index, blk.out, blk.end, blk.samples)

    def reset(self, t: float) -> None:
        """After the physics was restored from a snapshot taken at bench time ``t``."""
        with self._lock:
            self._block = None
            self._fp = None
            self._t = float(t)
            self._ahead = self.MIN_AHEAD_S
            # the probes may be read at the restored instant before the clock moves
            self.inputs.rows = {self._t: _row(self.bench, list(self._models()), self._t)}

    # ---- internals ----------------------------------------------------------------------------
    def _models(self) -> tuple[Any, Any, Any]:
        b = self.bench
        return b.chamber_model, b.table_model, b.psu_model

    def _unchanged(self, t: float) -> bool:
        """Nothing but time moved the device models since the last served instant (their states at
        instant ``t``, before they are advanced to it, are those the block ahead was computed from)."""
        if self._fp is None:
            return False
        epoch = self.bench.device_track.instant(t)
        return epoch == self._epoch and fingerprint((self.bench.psu_model,)) == self._fp

    def _on_grid(self, t: float) -> bool:
        """``t`` is exactly one of the grid times the physics integrates to from its committed state."""
        ph = self.physics
        return ph._state.t + ph.h * round((t - ph._state.t) / ph.h) == t

    def _at(self, t: float, frames: list[float] | None) -> list[GyroSample]:
        blk = self._block
        if blk is not None and t >= self._t:
            if t in blk.index and (t == self._t or self._unchanged(t)):
                rows = [blk.index.get(x) for x in frames] if frames else []
                if None not in rows:
                    self._serve_real(t)
                    samples = blk.samples
                    return [samples[k] for k in rows]
            if t not in blk.index and blk.end < t:
                # used as far as it reaches (to its end, or to a grid time between two instants when the
                # engine ticked on odd seconds meanwhile): nothing had to be dropped
                self._ahead = min(self.MAX_AHEAD_S, 2 * self._ahead)
            else:
                self.stats["dropped"] += 1
                self._ahead = self.MIN_AHEAD_S
        if t <= self._t and frames is None:
            return []
        self._settle()
        ph = self.physics
        n_to_t = round((t - ph._state.t) / ph.h)
        if (frames is None or all(self._on_grid(x) and x > self._t for x in frames)) and self._on_grid(t) \
                and ph._state.t == self._t and 0 < n_to_t <= MAX_BLOCK_STEPS:
            return self._build(t, n_to_t, frames)
        return self._direct(t, frames)

    def _serve_real(self, t: float, keep_fingerprint: bool = True) -> None:
        """The real device models follow the clock (front-ends and tests read them at the instant):
        the shared chamber and table through the bench's track (once per instant, whichever unit
        comes first), the unit's own supply here; their state is kept for a block ahead to be
        checked against (none on the direct path)."""
        if t == self._t and self._fp is not None:
            return
        self._epoch = self.bench.device_track.instant(t)
        psu = self.bench.psu_model
        psu.advance_to(t)
        self._t = t
        self._fp = fingerprint((psu,)) if keep_fingerprint else None

    def _settle(self) -> None:
        blk, ph = self._block, self.physics
        self._block = None
        if blk is None or ph._state.t <= self._t:
            return
        ph.rollback(blk.checkpoint)
        k = round((self._t - blk.t0) / ph.h)
        if k > 0:
            ph.run_grid(k)                   # the same steps on the same recorded inputs

    def _build(self, t: float, n_to_t: int, frames: list[float] | None) -> list[GyroSample]:
        ph = self.physics
        t0 = ph._state.t
        n = n_to_t + round(self._ahead / ph.h)
        times = t0 + ph.h * np.arange(1, n + 1)          # the grid times GyroPhysics integrates to
        self.inputs.rows = self._rows(times.tolist())
        cp = ph.checkpoint()
        out = ph.run_grid(n)
        grid = times.tolist()
        self._block = _Block(cp, t0, {g: i for i, g in enumerate(grid)}, out, grid[-1], SampleRows(out))
        self.stats["blocks"] += 1
        self._serve_real(t)
        samples = self._block.samples
        return [samples[self._block.index[x]] for x in frames] if frames else []

    def _direct(self, t: float, frames: list[float] | None) -> list[GyroSample]:
        """One instant on the physics' own path (instants or frames off the grid)."""
        ph = self.physics
        self.stats["direct"] += 1
        self.bench.device_track.instant(self._t)
        self.bench.psu_model.advance_to(self._t)
        base = ph._state.t
        grid = [base + ph.h * k for k in range(1, int(math.floor((t - base) / ph.h + 1e-9)) + 1)]
        wanted = sorted(set(grid) | set(frames or ()) | {t})
        self.inputs.rows = self._rows([g for g in wanted if g > self._t or g == t])
        samples = ph.sample_many(frames) if frames else []
        ph.advance_to(t)
        self._serve_real(t, keep_fingerprint=False)
        return samples

    def _rows(self, times: list[float]) -> dict[float, np.ndarray]:
        """``device_inputs_row`` at each of ``times`` (increasing), the models advanced through them
        on copies from their state at the last served instant: the chamber and table from the
        bench's shared track."""
        b = self.bench
        air, angles, rates = b.device_track.states(self._t, times)
        g = b.geometry
        outer, inner = g.outer_axis_number - 1, g.inner_axis_number - 1
        psu = b.psu_model                  # static between commands: its state now is its state then
        on = bool(psu.output_on)
        since = psu.on_since if on else None
        n = len(times)
        table = np.column_stack((np.array(times, dtype=float), air, angles[:, outer], angles[:, inner],
                                 rates[:, outer], rates[:, inner], np.full(n, float(on)),
                                 np.full(n, np.nan if since is None else float(since))))
        return dict(zip(times, table))


def _row(bench: "SimulatedBench", models: list[Any], t: float) -> np.ndarray:
    from bench.sim.bench import device_inputs_row

    return device_inputs_row(bench, models[0], models[1], models[2], t)
