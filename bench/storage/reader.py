"""Reading stored frames back: raw bit-exact, decoded arrays, per-frame records, and 1-s means.

``iter_frame_blocks`` streams numpy blocks (one per group of chunks), ``read_frames`` concatenates
them, ``iter_frames`` yields one ``StoredFrame`` per frame (convenient, slower), and
``second_means`` reads the ``frame_seconds`` sums written at ingest (16 s packed per row), so its
cost depends on the duration of the run, not on the number of frames.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from sqlalchemy import select

from bench.interfaces import GyroFrame
from bench.storage import codec
from bench.storage.db import Database
from bench.storage.models import SECONDS_PER_BLOCK, SUM_FIELDS, FrameChunk, FrameSecond


@dataclass
class FrameArrays:
    """``n`` consecutive stored frames of one kind, decoded (gyro in the device's output unit)."""

    kind: str
    index: np.ndarray          # (n,) int64, per-run frame index
    time: np.ndarray           # (n,) float64 host bench time (1 us resolution)
    raw: np.ndarray            # (n, frame_size) uint8, exactly as received
    gyro: np.ndarray           # (n, 3)
    accel: np.ndarray          # (n, 3) g
    status: np.ndarray         # (n,) uint8
    sequence: np.ndarray       # (n,) int64
    temperature_c: np.ndarray  # (n,) float64, NaN where the device gave none
    freq_hz: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.index.size)

    def raw_bytes(self, i: int) -> bytes:
        return self.raw[i].tobytes()

    def select(self, mask: np.ndarray) -> "FrameArrays":
        return FrameArrays(self.kind, self.index[mask], self.time[mask], self.raw[mask], self.gyro[mask],
                           self.accel[mask], self.status[mask], self.sequence[mask], self.temperature_c[mask],
                           None if self.freq_hz is None else self.freq_hz[mask])

    @staticmethod
    def concat(blocks: list["FrameArrays"]) -> "FrameArrays":
        kinds = {b.kind for b in blocks}
        if len(kinds) > 1:
            raise codec.UnknownFrameKind(f"cannot concatenate frames of different kinds {sorted(kinds)}")
        freq = None if any(b.freq_hz is None for b in blocks) else np.concatenate([b.freq_hz for b in blocks])
        return FrameArrays(blocks[0].kind, *(np.concatenate([getattr(b, f) for b in blocks]) for f in
                                             ("index", "time", "raw", "gyro", "accel", "status", "sequence",
                                              "temperature_c")), freq_hz=freq)


@dataclass(frozen=True)
class StoredFrame:
    index: int
    frame: GyroFrame


def _block_from_chunks(rows) -> FrameArrays:
    kind, size = rows[0].frame_kind, rows[0].frame_size
    raw = np.frombuffer(b"".join(r.raw for r in rows), dtype=np.uint8).reshape(-1, size)
    decoded = codec.decode_frames(kind, raw, size)
    index = np.concatenate([np.arange(r.first_index, r.first_index + r.count, dtype=np.int64) for r in rows])
    times = np.concatenate([codec.unpack_times(r.t_first, r.dt_us) for r in rows])
    temps = np.concatenate([codec.unpack_temps(r.temp_centi) for r in rows])
    return FrameArrays(kind, index, times, raw, decoded.gyro, decoded.accel, decoded.status, decoded.sequence,
                       temps, decoded.freq_hz)


def iter_frame_blocks(db: Database, run_id: int, *, t_from: float | None = None, t_to: float | None = None,
                      first_index: int | None = None, last_index: int | None = None,
                      chunks_per_block: int = 200) -> Iterator[FrameArrays]:
    """Stored frames of a run in index order, as decoded blocks, optionally limited to host time
    ``[t_from, t_to]`` and/or indexes ``[first_index, last_index]``.  Raises ``UnknownFrameKind`` for
    frames whose layout is not registered."""
    c = FrameChunk
    stmt = select(c.first_index, c.count, c.t_first, c.t_last, c.frame_kind, c.frame_size, c.raw, c.dt_us,
                  c.temp_centi).where(c.run_id == run_id)
    if t_from is not None:
        stmt = stmt.where(c.t_last >= t_from)
    if t_to is not None:
        stmt = stmt.where(c.t_first <= t_to)
    if first_index is not None:
        stmt = stmt.where(c.first_index + c.count > first_index)
    if last_index is not None:
        stmt = stmt.where(c.first_index <= last_index)
    stmt = stmt.order_by(c.first_index)
    with db.engine.connect() as conn:
        result = conn.execution_options(yield_per=chunks_per_block).execute(stmt)
        for part in result.partitions():
            groups: list[list] = []
            for row in part:          # chunks of one kind and size decode together
                if groups and (groups[-1][0].frame_kind, groups[-1][0].frame_size) == (row.frame_kind,
                                                                                        row.frame_size):
                    groups[-1].append(row)
                else:
                    groups.append([row])
            for group in groups:
                block = _block_from_chunks(group)
                mask = np.ones(len(block), dtype=bool)
                if t_from is not None:
                    mask &= block.time >= t_from
                if t_to is not None:
                    mask &= block.time <= t_to
                if first_index is not None:
                    mask &= block.index >= first_index
                if last_index is not None:
                    mask &= block.index <= last_index
                if not mask.all():
                    block = block.select(mask)
                if len(block):
                    yield block


def read_frames(db: Database, run_id: int, **limits) -> FrameArrays | None:
    """All matching frames as one ``FrameArrays`` (None when there are none); limits as in
    ``iter_frame_blocks``."""
    blocks = list(iter_frame_blocks(db, run_id, **limits))
    return FrameArrays.concat(blocks) if blocks else None


def iter_frames(db: Database, run_id: int, **limits) -> Iterator[StoredFrame]:
    """One ``StoredFrame(index, GyroFrame)`` per stored frame (GyroFrame rebuilt from storage)."""
    for b in iter_frame_blocks(db, run_id, **limits):
        for i in range(len(b)):
            temp = float(b.temperature_c[i])
            yield StoredFrame(int(b.index[i]), GyroFrame(
                host_time=float(b.time[i]), sequence=int(b.sequence[i]), gyro=tuple(b.gyro[i].tolist()),
                accel=tuple(b.accel[i].tolist()), status=int(b.status[i]),
                temperature_c=temp, raw=b.raw[i].tobytes(),
                freq_hz=None if b.freq_hz is None else tuple(b.freq_hz[i].tolist())))


@dataclass
class SecondMeans:
    """Means per bench second ``[second, second+1)`` over valid-status frames (units as on the wire)."""

    second: np.ndarray         # (m,) int64
    n: np.ndarray              # (m,) valid frames in the second
    n_invalid: np.ndarray      # (m,) frames left out (status not all-valid)
    time: np.ndarray           # (m,) mean host time of the valid frames (second + 0.5 if none)
    gyro: np.ndarray           # (m, 3), NaN where n == 0
    accel: np.ndarray          # (m, 3)
    temperature_c: np.ndarray  # (m,) mean device temperature, NaN where none
    freq_hz: np.ndarray | None

    def __len__(self) -> int:
        return int(self.second.size)


def second_means(db: Database, run_id: int, *, t_from: float | None = None,
                 t_to: float | None = None) -> SecondMeans:
    """1-s means of a run from the packed ``frame_seconds`` blocks (no raw frame is decoded).
    Only seconds in which frames were stored appear."""
    fs = FrameSecond
    stmt = select(fs.block, fs.has_freq, fs.sums).where(fs.run_id == run_id)
    lo = None if t_from is None else int(np.floor(t_from))
    hi = None if t_to is None else int(np.floor(t_to))
    if lo is not None:
        stmt = stmt.where(fs.block > lo - SECONDS_PER_BLOCK)
    if hi is not None:
        stmt = stmt.where(fs.block <= hi)
    with db.engine.connect() as conn:
        rows = conn.execute(stmt.order_by(fs.block)).all()
    width = len(SUM_FIELDS)
    if not rows:
        table = np.zeros((0, width))
        seconds = np.zeros(0, dtype=np.int64)
    else:
        table = np.frombuffer(b"".join(r[2] for r in rows), dtype="<f8").reshape(-1, width)
        seconds = (np.repeat(np.array([r[0] for r in rows], dtype=np.int64), SECONDS_PER_BLOCK)
                   + np.tile(np.arange(SECONDS_PER_BLOCK, dtype=np.int64), len(rows)))
    has_freq = any(r[1] for r in rows)
    keep = (table[:, 0] + table[:, 1]) > 0
    if lo is not None:
        keep &= seconds >= lo
    if hi is not None:
        keep &= seconds <= hi
    table, seconds = table[keep], seconds[keep]
    col = {name: table[:, i] for i, name in enumerate(SUM_FIELDS)}
    n = col["n"]
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_n = np.where(n > 0, 1.0 / np.where(n > 0, n, 1.0), np.nan)
        time = seconds + np.where(n > 0, col["sum_dt"] * np.nan_to_num(inv_n), 0.5)
        gyro = np.column_stack([col["sum_gx"], col["sum_gy"], col["sum_gz"]]) * inv_n[:, None]
        accel = np.column_stack([col["sum_ax"], col["sum_ay"], col["sum_az"]]) * inv_n[:, None]
        n_temp = col["n_temp"]
        temp = np.where(n_temp > 0, col["sum_temp"] / np.where(n_temp > 0, n_temp, 1.0), np.nan)
        freq = (np.column_stack([col["sum_fx"], col["sum_fy"], col["sum_fz"]]) * inv_n[:, None]
                if has_freq else None)
    return SecondMeans(seconds, np.rint(n).astype(np.int64), np.rint(col["n_invalid"]).astype(np.int64), time,
                       gyro.reshape(-1, 3), accel.reshape(-1, 3), temp, freq)
