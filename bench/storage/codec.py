"""Vectorised decoding of stored raw frames, keyed by frame kind, and chunk array packing.

Only the KVH "Format A" layout is built in (device-protocols.md 3.1, KVH 1775 manual Tables 5-1/5-2):
36 bytes, big-endian: header u32 (FE 81 FF 55), gyro x/y/z f32, accel x/y/z f32 (g), status u8,
sequence u8 (0..127), temperature i16 (unit is a device setting), CRC-32/MPEG-2 u32 over bytes 0..31.
Other kinds (the HRG frame is defined by the device driver) can be added with
``register_frame_layout``; decoding an unregistered kind raises ``UnknownFrameKind``.

The CRC is not re-checked here: stored frames were validated by the link when received, and the
raw bytes are kept exactly as received.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from bench.storage.errors import UnknownFrameKind

KVH_A_DTYPE = np.dtype([("header", ">u4"), ("gyro", ">f4", (3,)), ("accel", ">f4", (3,)), ("status", "u1"),
                        ("sequence", "u1"), ("temp_raw", ">i2"), ("crc", ">u4")])
assert KVH_A_DTYPE.itemsize == 36

DT_US_DTYPE = np.dtype("<i4")        # host time offset from the chunk's t_first, microseconds
TEMP_DTYPE = np.dtype("<i2")         # decoded temperature, 1/100 degC
TEMP_MISSING = -32768
MAX_CHUNK_SPAN_S = 2000.0            # int32 microseconds reach +-2147 s


@dataclass(frozen=True)
class DecodedFrames:
    """Decoded fields of ``n`` frames as arrays (wire units: gyro as output by the device, accel in g)."""

    gyro: np.ndarray                  # (n, 3) float64
    accel: np.ndarray                 # (n, 3) float64
    status: np.ndarray                # (n,) uint8
    sequence: np.ndarray              # (n,) int64
    freq_hz: np.ndarray | None = None  # (n, 3) float64 for resonator gyros, else None


@dataclass(frozen=True)
class FrameLayout:
    kind: str
    size: int                          # bytes per frame
    decode: Callable[[np.ndarray], DecodedFrames]   # (n, size) uint8 -> decoded


def _decode_kvh_a(raw: np.ndarray) -> DecodedFrames:
    rec = np.ascontiguousarray(raw).view(KVH_A_DTYPE).reshape(-1)
    return DecodedFrames(gyro=rec["gyro"].astype(np.float64), accel=rec["accel"].astype(np.float64),
                         status=rec["status"].copy(), sequence=rec["sequence"].astype(np.int64))


_LAYOUTS: dict[str, FrameLayout] = {"kvh_a": FrameLayout("kvh_a", KVH_A_DTYPE.itemsize, _decode_kvh_a)}


def register_frame_layout(layout: FrameLayout) -> None:
    """Make stored frames of ``layout.kind`` decodable (e.g. the HRG frame, from its driver)."""
    existing = _LAYOUTS.get(layout.kind)
    if existing is not None and existing.size != layout.size:
        raise ValueError(f"frame kind {layout.kind!r} is already registered with {existing.size} bytes per frame")
    _LAYOUTS[layout.kind] = layout


def frame_layout(kind: str, size: int | None = None) -> FrameLayout:
    try:
        layout = _LAYOUTS[kind]
    except KeyError:
        raise UnknownFrameKind(f"stored frames of kind {kind!r} cannot be decoded: no layout registered "
                               f"(known: {', '.join(sorted(_LAYOUTS))})") from None
    if size is not None and size != layout.size:
        raise UnknownFrameKind(f"stored frames of kind {kind!r} are {size} bytes, the {kind} layout has "
                               f"{layout.size}")
    return layout


def known_frame_size(kind: str) -> int | None:
    layout = _LAYOUTS.get(kind)
    return layout.size if layout else None


def decode_frames(kind: str, raw: bytes | np.ndarray, size: int | None = None) -> DecodedFrames:
    """Decode concatenated raw frames of one kind."""
    layout = frame_layout(kind, size)
    buf = np.frombuffer(raw, dtype=np.uint8) if isinstance(raw, (bytes, bytearray, memoryview)) else raw
    if buf.size % layout.size:
        raise UnknownFrameKind(f"{buf.size} bytes of {kind!r} frames is not a multiple of {layout.size}")
    return layout.decode(buf.reshape(-1, layout.size))


def pack_times(times: np.ndarray) -> tuple[float, bytes]:
    """(t_first, int32 LE microsecond offsets) for host times spanning < MAX_CHUNK_SPAN_S."""
    t0 = float(times[0])
    offsets = np.rint((times - t0) * 1e6)
    if offsets.size and np.abs(offsets).max() > np.iinfo(np.int32).max:
        raise ValueError("host times of one chunk span more than the int32 microsecond range")
    return t0, offsets.astype(DT_US_DTYPE).tobytes()


def unpack_times(t_first: float, dt_us: bytes) -> np.ndarray:
    return t_first + np.frombuffer(dt_us, dtype=DT_US_DTYPE).astype(np.float64) * 1e-6


def pack_temps(celsius: np.ndarray) -> bytes:
    centi = np.rint(np.where(np.isfinite(celsius), celsius, 0.0) * 100.0)
    centi = np.clip(centi, -32767, 32767)
    centi[~np.isfinite(celsius)] = TEMP_MISSING
    return centi.astype(TEMP_DTYPE).tobytes()


def unpack_temps(temp_centi: bytes) -> np.ndarray:
    centi = np.frombuffer(temp_centi, dtype=TEMP_DTYPE)
    out = centi.astype(np.float64) / 100.0
    out[centi == TEMP_MISSING] = np.nan
    return out
