"""Gyro binary frame codecs: KVH 1750/1775 "Format A" and the bench's HRG frequency frame.

Sources (see ../shared/reference/device-protocols.md section 3.1): KVH 1775 IMU Technical Manual
56-0298 Rev B tables 5-1/5-2/5-8/5-9 and the 1775 user manual "CRC Format".

KVH Format A (36 bytes, every multi-byte field big-endian)
----------------------------------------------------------
==== === ============================================================================
off  len field
==== === ============================================================================
0    4   header ``FE 81 FF 55`` (0xFE first)
4    12  gyro X, Y, Z, float32 (deg/s or rad/s as configured on the device)
16   12  accel X, Y, Z, float32 (g)
28   1   status: b0..b2 gyro X/Y/Z valid, b4..b6 accel X/Y/Z valid, b3 = b7 = 0;
         all valid = 0x77
29   1   sequence 0..127, then wraps to 0
30   2   temperature, int16.  Scale depends on firmware / ``=TEMPUNITS``: current firmware
         sends 1/100 degC (``temp_scale=0.01``, the default here); older firmware sends whole
         degrees (``temp_scale=1.0``).  The frame is self-describing in nothing: the scale
         is a decoder parameter.  Example: the verified real frame in the reference carries
         0x0014 and is a whole-degree frame (20 degC), not 0.20 degC.
32   4   CRC-32/MPEG-2 over bytes 0..31 (header included)
==== === ============================================================================

CRC-32/MPEG-2: width 32, poly 0x04C11DB7, init 0xFFFFFFFF, no reflection, xorout 0; check value
of ``b"123456789"`` is 0x0376E6E7.

HRG frame (defined by this bench, 60 bytes)
-------------------------------------------
Three-axis hemispherical resonator gyros can use each resonator's resonance frequency as a
thermometer (seed paper 002: ~0.45..0.49 Hz/degC near 4.7..4.9 kHz, frequencies published to
0.001 Hz, temperature solved to better than 0.1 degC).  The frame must carry those frequencies.

==== === ============================================================================
off  len field
==== === ============================================================================
0    4   header ``FE 81 FF 5A`` (0x5A: not used by KVH Format A/B/C = 0x55/0x56/0x57 nor by
         the BIT reply ``FE 81 00 AA/AB``)
4    12  gyro X, Y, Z, float32 (as Format A)
16   12  accel X, Y, Z, float32 g (as Format A)
28   24  resonance frequency X, Y, Z, **float64** Hz
52   1   status: as Format A plus b3 = resonance frequencies valid; all valid = 0x7F
53   1   sequence 0..127
54   2   temperature int16 (internal sensor, same ``temp_scale`` convention as Format A)
56   4   CRC-32/MPEG-2 over bytes 0..55
==== === ============================================================================

Why float64 for the frequencies: float32 has a 24-bit significand, so between 4096 and 8192 Hz
its step is 2**-11 = 0.000488 Hz (numpy.spacing(float32(4900)) measured).  At ~0.47 Hz/degC
that is a ~1 mK step: enough for one reading, but the compensation models in seed 002 use the
temperature *rate* too, and differencing consecutive 1 kHz frames with a 0.5 mHz quantisation
step gives ~1 K/s of pure quantisation noise in dT/dt; 100-s smoothing of a quantised signal
also needs dither to resolve below one step.  float64 (step 9.1e-13 Hz at 4900 Hz) removes
the frame from the error budget for 12 extra bytes: 60 B x 10 bit x 1000 Hz = 600 kbaud, within
921600 baud (at 5000 Hz only the 4147200-baud setting can carry it, as for Format A).

Speed notes (measured by ``python -m tests.perf.frames``): the pure-Python table-driven CRC
(``crc32_mpeg2_table``) costs ~4 us per 32 bytes, which alone would cap the decoder below the
256 000 frames/s target.  ``crc32_mpeg2`` instead uses zlib's C CRC-32 (same polynomial,
reflected) on bit-reversed bytes: reflecting every input byte and the final register turns
the reflected algorithm into the non-reflected one (init 0xFFFFFFFF is its own reflection,
zlib's xorout 0xFFFFFFFF is undone).  The decoder checks a whole frame including its CRC with
one call: for a non-reflected CRC with xorout 0 the register after the appended big-endian CRC
is 0, i.e. ``zlib.crc32(bitreversed(frame)) == 0xFFFFFFFF``.  Both implementations are tested
against each other and against the check value.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

from bench.errors import ProtocolError
from bench.interfaces import GyroFrame, LinkStats

# ----------------------------------------------------------------------------------------- CRC

_POLY = 0x04C11DB7


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        reg = byte << 24
        for _ in range(8):
            reg = ((reg << 1) ^ _POLY) if reg & 0x80000000 else (reg << 1)
        table.append(reg & 0xFFFFFFFF)
    return tuple(table)


CRC_TABLE = _make_table()
_BITREV = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def crc32_mpeg2_table(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/MPEG-2, byte-wise table-driven (MSB first).  Reference implementation."""
    reg = 0xFFFFFFFF
    table = CRC_TABLE
    for b in bytes(data):
        reg = ((reg << 8) & 0xFFFFFFFF) ^ table[(reg >> 24) ^ b]
    return reg


def _reflect32(value: int) -> int:
    return int.from_bytes(value.to_bytes(4, "little").translate(_BITREV), "big")


def crc32_mpeg2(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/MPEG-2 computed with zlib's C CRC-32 on bit-reversed bytes (see module docstring)."""
    return _reflect32(zlib.crc32(bytes(data).translate(_BITREV)) ^ 0xFFFFFFFF)


def crc_residue_ok(frame: bytes | bytearray | memoryview) -> bool:
    """True when ``frame`` (payload followed by its big-endian CRC-32/MPEG-2) is intact."""
    return zlib.crc32(bytes(frame).translate(_BITREV)) == 0xFFFFFFFF


# ------------------------------------------------------------------------------- frame layouts

ALLOWED_DATA_RATES = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000, 3600, 5000)   # ``=DR,n`` values, Hz
STATUS_ALL_VALID_A = 0x77
STATUS_ALL_VALID_HRG = 0x7F
STATUS_FREQ_VALID = 0x08


@dataclass(frozen=True)
class FrameSpec:
    kind: str
    header: bytes
    length: int
    body: struct.Struct          # fields after the header, before the CRC
    all_valid: int
    has_freq: bool


KVH_A = FrameSpec("kvh_a", b"\xFE\x81\xFF\x55", 36, struct.Struct(">6fBBh"), STATUS_ALL_VALID_A, False)
HRG = FrameSpec("hrg", b"\xFE\x81\xFF\x5A", 60, struct.Struct(">6f3dBBh"), STATUS_ALL_VALID_HRG, True)
SPECS = {"kvh_a": KVH_A, "hrg": HRG}
_CRC = struct.Struct(">I")


def spec_for(kind: str) -> FrameSpec:
    try:
        return SPECS[kind]
    except KeyError:
        raise ValueError(f"unknown gyro frame kind {kind!r}; expected one of {sorted(SPECS)}") from None


def _temp_counts(temperature_c: float, temp_scale: float) -> int:
    if not temp_scale > 0:
        raise ValueError(f"temp_scale must be > 0, got {temp_scale}")
    if not math.isfinite(temperature_c):
        raise ValueError(f"gyro frame temperature must be finite, got {temperature_c}")
    counts = round(temperature_c / temp_scale)
    if not -32768 <= counts <= 32767:
        raise ValueError(f"temperature {temperature_c} degC does not fit an int16 at scale {temp_scale}")
    return counts


def _check_common(sequence: int, status: int) -> None:
    if not 0 <= sequence <= 127:
        raise ValueError(f"gyro frame sequence must be 0..127, got {sequence}")
    if not 0 <= status <= 255:
        raise ValueError(f"gyro frame status must be one byte, got {status}")


def _finish(spec: FrameSpec, fields: tuple) -> bytes:
    payload = spec.header + spec.body.pack(*fields)
    return payload + _CRC.pack(crc32_mpeg2(payload))


def encode_format_a(gyro: tuple[float, float, float], accel: tuple[float, float, float], *,
                    sequence: int, temperature_c: float, status: int = STATUS_ALL_VALID_A,
                    temp_scale: float = 0.01) -> bytes:
    """Build one 36-byte KVH Format A frame (CRC included)."""
    _check_common(sequence, status)
    return _finish(KVH_A, (*gyro, *accel, status, sequence, _temp_counts(temperature_c, temp_scale)))


def encode_hrg(gyro: tuple[float, float, float], accel: tuple[float, float, float],
               freq_hz: tuple[float, float, float], *, sequence: int, temperature_c: float,
               status: int = STATUS_ALL_VALID_HRG, temp_scale: float = 0.01) -> bytes:
    """Build one 60-byte HRG frame (layout in the module docstring)."""
    _check_common(sequence, status)
    if len(freq_hz) != 3:
        raise ValueError(f"HRG frame needs 3 resonance frequencies, got {len(freq_hz)}")
    return _finish(HRG, (*gyro, *accel, *freq_hz, status, sequence,
                         _temp_counts(temperature_c, temp_scale)))


def _decode(spec: FrameSpec, frame: bytes, temp_scale: float, host_time: float) -> GyroFrame:
    frame = bytes(frame)
    if len(frame) != spec.length:
        raise ProtocolError(f"{spec.kind} frame must be {spec.length} bytes, got {len(frame)}")
    if frame[:4] != spec.header:
        raise ProtocolError(f"{spec.kind} frame header is {frame[:4].hex(' ')}, expected {spec.header.hex(' ')}")
    if not crc_residue_ok(frame):
        got = _CRC.unpack_from(frame, spec.length - 4)[0]
        raise ProtocolError(f"{spec.kind} frame CRC mismatch: frame carries 0x{got:08X}, "
                            f"computed 0x{crc32_mpeg2(frame[:-4]):08X}")
    return _to_frame(spec, spec.body.unpack_from(frame, 4), temp_scale, host_time, frame)


def _to_frame(spec: FrameSpec, v: tuple, temp_scale: float, host_time: float, raw: bytes) -> GyroFrame:
    if spec.has_freq:
        return GyroFrame(host_time, v[10], (v[0], v[1], v[2]), (v[3], v[4], v[5]), v[9],
                         v[11] * temp_scale, raw, (v[6], v[7], v[8]))
    return GyroFrame(host_time, v[7], (v[0], v[1], v[2]), (v[3], v[4], v[5]), v[6], v[8] * temp_scale, raw)


def decode_format_a(frame: bytes, temp_scale: float = 0.01, host_time: float = 0.0) -> GyroFrame:
    """Decode one complete 36-byte Format A frame; ProtocolError on length, header or CRC.

    ``temp_scale`` is degC per count of the int16 temperature: 0.01 for current firmware
    (1/100 degC), 1.0 for older whole-degree firmware such as the verified reference frame.
    """
    return _decode(KVH_A, frame, temp_scale, host_time)


def decode_hrg(frame: bytes, temp_scale: float = 0.01, host_time: float = 0.0) -> GyroFrame:
    """Decode one complete 60-byte HRG frame; ProtocolError on length, header or CRC."""
    return _decode(HRG, frame, temp_scale, host_time)


# ---------------------------------------------------------------------------- stream decoder

_FIELDS = ("host_time", "sequence", "gyro", "accel", "status", "temperature_c", "raw", "freq_hz")


def _frame_builder():
    """Fast GyroFrame construction for the decoder's hot loop.

    ``GyroFrame`` is a frozen dataclass: its ``__init__`` goes through ``object.__setattr__`` once
    per field (~2 us per frame measured, more than CRC + unpack together).  Filling the instance
    ``__dict__`` directly gives an equal object in ~0.7 us.  The shortcut is verified here against
    the real constructor; if ``GyroFrame`` ever changes shape (slots, new fields) the real
    constructor is used instead.
    """
    new = object.__new__

    def fast(host_time, sequence, gyro, accel, status, temperature_c, raw, freq_hz):
        frame = new(GyroFrame)
        frame.__dict__.update(host_time=host_time, sequence=sequence, gyro=gyro, accel=accel, status=status,
                              temperature_c=temperature_c, raw=raw, freq_hz=freq_hz)
        return frame

    sample = (1.0, 5, (0.1, 0.2, 0.3), (0.0, 0.0, 1.0), 0x77, 21.5, b"raw", None)
    try:
        if fast(*sample) == GyroFrame(*sample) and tuple(GyroFrame.__dataclass_fields__) == _FIELDS:
            return fast
    except (AttributeError, TypeError):
        pass
    return GyroFrame


_make_frame = _frame_builder()

class FrameDecoder:
    """Streaming decoder: feed arbitrary byte chunks, get intact frames back.

    - Resynchronises on the 4-byte header after garbage (``bytes.find``, no per-byte loop).
    - A candidate frame with a bad CRC is rejected and the search restarts one byte after its
      header, so an intact frame that starts inside a corrupt/truncated one is still found.
    - ``stats`` (a ``LinkStats``) counts: ``frames`` accepted; ``bad_crc`` rejected candidates;
      ``skipped_bytes`` bytes not belonging to an accepted frame (garbage, the bytes of
      rejected candidates, ASCII replies); ``resyncs`` runs of such bytes between good frames;
      ``sequence_gaps`` / ``missing_frames`` from sequence jumps mod 128 (a loss of 128 or more
      frames is ambiguous and shows as fewer; link gaps are reported separately by the link);
      ``invalid_status`` frames whose status is not the all-valid value (0x77 / 0x7F).
    - ``feed(chunk, host_time, frame_period_s)`` timestamps the frames of one chunk: the last
      gets ``host_time``; earlier ones are back-dated by the nominal period per sequence step (they
      left the device one period apart; a frame lost on the line keeps its period), never earlier
      than the previous frame's time.
    """

    def __init__(self, kind: str = "kvh_a", temp_scale: float = 0.01, stats: LinkStats | None = None) -> None:
        if not temp_scale > 0:
            raise ValueError(f"temp_scale must be > 0, got {temp_scale}")
        self.spec = spec_for(kind)
        self.temp_scale = float(temp_scale)
        self.stats = stats if stats is not None else LinkStats()
        self._tail = b""
        self._in_garbage = False
        self._last_seq: int | None = None
        self._last_time = -math.inf

    def reset(self) -> None:
        """Forget partial bytes and the sequence (call after a reconnect or a rate change)."""
        self._tail = b""
        self._in_garbage = False
        self._last_seq = None

    def _skip(self, count: int) -> None:
        self.stats.skipped_bytes += count
        if not self._in_garbage:
            self._in_garbage = True
            self.stats.resyncs += 1

    def feed(self, chunk: bytes | bytearray | memoryview, host_time: float = 0.0,
             frame_period_s: float = 0.0) -> list[GyroFrame]:
        spec = self.spec
        length = spec.length
        header = spec.header
        buf = self._tail + bytes(chunk)
        n = len(buf)
        starts: list[int] = []
        pos = 0
        if n >= length:
            tview = memoryview(buf.translate(_BITREV))
            crc32 = zlib.crc32
            find = buf.find
            stats = self.stats
            while True:
                i = find(header, pos)
                if i < 0:
                    keep = max(pos, n - 3)          # a header may straddle the chunk boundary
                    if keep > pos:
                        self._skip(keep - pos)
                    pos = keep
                    break
                if i > pos:
                    self._skip(i - pos)
                if i + length > n:
                    pos = i
                    break
                if crc32(tview[i:i + length]) != 0xFFFFFFFF:
                    stats.bad_crc += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                starts.append(i)
                self._in_garbage = False
                pos = i + length
            tview.release()
        self._tail = buf[pos:]
        if not starts:
            return []
        return self._build(buf, starts, host_time, frame_period_s)

    def _build(self, buf: bytes, starts: list[int], host_time: float, period: float) -> list[GyroFrame]:
        spec = self.spec
        length = spec.length
        unpack = spec.body.unpack_from
        scale = self.temp_scale
        all_valid = spec.all_valid
        has_freq = spec.has_freq
        seq_i, status_i, temp_i = (10, 9, 11) if has_freq else (7, 6, 8)
        stats = self.stats
        last_seq = self._last_seq
        count = len(starts)
        values = [unpack(buf, i + 4) for i in starts]
        # the frames left the device one period per sequence step apart (frames lost on the line keep
        # their period): back-date from the last one, which left just before host_time
        steps = [(values[k][seq_i] - values[k - 1][seq_i]) & 0x7F or 128 for k in range(1, count)]
        t = host_time - sum(steps) * period
        if t < self._last_time:
            t = self._last_time
        out: list[GyroFrame] = []
        append = out.append
        make = _make_frame
        for k, i in enumerate(starts):
            v = values[k]
            seq = v[seq_i]
            if last_seq is not None:
                missing = (seq - last_seq - 1) & 0x7F
                if missing:
                    stats.sequence_gaps += 1
                    stats.missing_frames += missing
            last_seq = seq
            status = v[status_i]
            if status != all_valid:
                stats.invalid_status += 1
            ft = t if t < host_time else host_time
            append(make(ft, seq, (v[0], v[1], v[2]), (v[3], v[4], v[5]), status, v[temp_i] * scale,
                             buf[i:i + length], (v[6], v[7], v[8]) if has_freq else None))
            if k + 1 < count:
                t += steps[k] * period
        stats.frames += count
        self._last_seq = last_seq
        self._last_time = out[-1].host_time
        return out
