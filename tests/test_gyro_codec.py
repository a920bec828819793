"""KVH Format A / HRG codecs and the streaming decoder (no I/O)."""
from __future__ import annotations

import math
import random
import struct

import numpy as np
import pytest

from bench.devices import kvh
from bench.devices.kvh import FrameDecoder, crc32_mpeg2, crc32_mpeg2_table, decode_format_a, encode_format_a
from bench.errors import ProtocolError

VERIFIED_FRAME = bytes.fromhex("FE81FF55 BC646C1E 3C3FF981 3B3C1E78 BC065FB7 BB2FBD79 3F7E9800 77 47 0014 168D8B1D")


# --- an independent Format A decoder: bit-serial CRC, hand-made struct format, own header search
def _crc_bitwise(data: bytes) -> int:
    reg = 0xFFFFFFFF
    for byte in data:
        for bit in range(7, -1, -1):
            feedback = ((reg >> 31) & 1) ^ ((byte >> bit) & 1)
            reg = (reg << 1) & 0xFFFFFFFF
            if feedback:
                reg ^= 0x04C11DB7
    return reg


def independent_decode(stream: bytes, temp_scale: float = 0.01) -> list[tuple]:
    out, i = [], 0
    while i + 36 <= len(stream):
        if stream[i:i + 4] == b"\xfe\x81\xff\x55" and _crc_bitwise(stream[i:i + 32]) == int.from_bytes(stream[i + 32:i + 36], "big"):
            f = struct.unpack(">ffffffBBh", stream[i + 4:i + 32])
            out.append((f[7], f[0:3], f[3:6], f[6], f[8] * temp_scale, stream[i:i + 36]))
            i += 36
        else:
            i += 1
    return out


def as_tuple(frame) -> tuple:
    return (frame.sequence, frame.gyro, frame.accel, frame.status, frame.temperature_c, frame.raw)


def make_frames(n: int, seed: int = 1, start_seq: int = 0) -> list[bytes]:
    rng = random.Random(seed)
    return [encode_format_a((rng.uniform(-300, 300), rng.uniform(-1, 1), rng.gauss(0, 1e-3)),
                            (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(0.9, 1.1)),
                            sequence=(start_seq + k) % 128, temperature_c=rng.uniform(-45, 70))
            for k in range(n)]


def test_crc_check_values_and_implementations_agree():
    assert crc32_mpeg2(b"123456789") == 0x0376E6E7
    assert crc32_mpeg2_table(b"123456789") == 0x0376E6E7
    assert _crc_bitwise(b"123456789") == 0x0376E6E7
    rng = random.Random(7)
    for length in (0, 1, 3, 4, 31, 32, 55, 200):
        data = bytes(rng.randrange(256) for _ in range(length))
        assert crc32_mpeg2(data) == crc32_mpeg2_table(data) == _crc_bitwise(data)


def test_verified_real_frame():
    assert crc32_mpeg2(VERIFIED_FRAME[:32]) == 0x168D8B1D
    frame = decode_format_a(VERIFIED_FRAME, temp_scale=1.0)
    assert frame.gyro == pytest.approx((-0.01394, 0.01172, 0.00287), abs=5e-6)
    assert frame.accel == pytest.approx((-0.0082, -0.0027, 0.9945), abs=5e-5)
    assert frame.status == 0x77 and frame.sequence == 71
    assert frame.temperature_c == 20.0
    assert frame.raw == VERIFIED_FRAME and frame.freq_hz is None
    # the same counts read with the current-firmware scale would be 0.20 C
    assert decode_format_a(VERIFIED_FRAME).temperature_c == pytest.approx(0.20)


def test_encode_reproduces_verified_frame():
    f = decode_format_a(VERIFIED_FRAME, temp_scale=1.0)
    assert encode_format_a(f.gyro, f.accel, sequence=71, temperature_c=20.0, temp_scale=1.0) == VERIFIED_FRAME


def test_round_trip_format_a_and_hrg():
    raw = encode_format_a((1.5, -2.25, 0.125), (0.0, -0.5, 1.0), sequence=127, temperature_c=-40.27, status=0x75)
    f = decode_format_a(raw, host_time=12.5)
    assert (f.gyro, f.accel, f.sequence, f.status, f.host_time) == ((1.5, -2.25, 0.125), (0.0, -0.5, 1.0), 127, 0x75, 12.5)
    assert f.temperature_c == pytest.approx(-40.27)
    freqs = (4878.848123456789, 4871.747000000001, 4684.152)
    raw = kvh.encode_hrg((0.5, 0.25, -1.0), (0.0, 0.0, 1.0), freqs, sequence=3, temperature_c=25.75)
    assert len(raw) == 60 and raw[:4] == b"\xfe\x81\xff\x5a"
    h = kvh.decode_hrg(raw)
    assert h.freq_hz == freqs                      # float64: bit exact
    assert (h.gyro, h.sequence, h.status, h.temperature_c) == ((0.5, 0.25, -1.0), 3, 0x7F, 25.75)


def test_encoder_and_decoder_refuse_bad_input():
    with pytest.raises(ValueError, match="sequence"):
        encode_format_a((0, 0, 0), (0, 0, 0), sequence=128, temperature_c=20)
    with pytest.raises(ValueError, match="int16"):
        encode_format_a((0, 0, 0), (0, 0, 0), sequence=0, temperature_c=400.0)
    with pytest.raises(ValueError, match="unknown gyro frame kind"):
        FrameDecoder("kvh_b")
    with pytest.raises(ProtocolError, match="36 bytes"):
        decode_format_a(VERIFIED_FRAME[:-1])
    with pytest.raises(ProtocolError, match="header"):
        decode_format_a(b"\x00" + VERIFIED_FRAME[1:])
    bad = bytearray(VERIFIED_FRAME)
    bad[10] ^= 0x01
    with pytest.raises(ProtocolError, match="CRC mismatch"):
        decode_format_a(bytes(bad))


def test_decoder_agrees_with_independent_decoder_on_noisy_stream():
    frames = make_frames(400, seed=3)
    rng = np.random.default_rng(5)
    stream = bytearray(b"".join(frames))
    flip = np.flatnonzero(rng.random(len(stream)) < 0.01)
    for i in flip:
        stream[i] ^= int(rng.integers(1, 256))
    stream = bytes(stream)
    dec = FrameDecoder()
    got = []
    for k in range(0, len(stream), 100):
        got += dec.feed(stream[k:k + 100])
    expected = independent_decode(stream)
    assert [as_tuple(f) for f in got] == expected
    intact = [f for k, f in enumerate(frames) if not any(k * 36 <= i < k * 36 + 36 for i in flip)]
    assert [f.raw for f in got] == intact
    assert dec.stats.bad_crc > 0
    # losses before the first / after the last kept frame have no neighbour to reveal them
    span = frames.index(intact[-1]) - frames.index(intact[0]) + 1
    assert dec.stats.frames + dec.stats.missing_frames == span


@pytest.mark.parametrize("seed", range(8))
def test_property_garbage_and_random_chunking(seed):
    rng = random.Random(seed)
    frames = make_frames(300, seed=seed)
    pieces, garbage_total = [], 0
    for f in frames:
        if rng.random() < 0.3:
            junk = bytearray(rng.randrange(256) for _ in range(rng.randrange(1, 60)))
            if rng.random() < 0.3:            # adversarial: a header inside the junk
                at = rng.randrange(len(junk) + 1)
                junk[at:at] = kvh.KVH_A.header
            if rng.random() < 0.3:            # a truncated frame (lost bytes on the line)
                junk += rng.choice(frames)[:rng.randrange(1, 36)]
            pieces.append(bytes(junk))
            garbage_total += len(junk)
        pieces.append(f)
    stream = b"".join(pieces)
    dec = FrameDecoder()
    got, pos = [], 0
    while pos < len(stream):
        step = rng.choice((1, 2, 3, 5, 35, 36, 37, 100, 1000))
        got += dec.feed(stream[pos:pos + step])
        pos += step
    assert [f.raw for f in got] == frames
    assert dec.stats.skipped_bytes == garbage_total
    assert dec.stats.missing_frames == 0 and dec.stats.sequence_gaps == 0


def test_frame_after_truncated_frame_is_kept():
    a, b, c = make_frames(3)
    stream = a + b[:20] + c                  # b lost 16 bytes: its CRC window swallows c's start
    dec = FrameDecoder()
    got = dec.feed(stream)
    assert [f.raw for f in got] == [a, c]
    assert dec.stats.bad_crc == 1 and dec.stats.skipped_bytes == 20
    assert dec.stats.sequence_gaps == 1 and dec.stats.missing_frames == 1


def test_sequence_wrap_gaps_and_status_counting():
    frames = make_frames(200, start_seq=120)
    keep = [f for k, f in enumerate(frames) if k not in (5, 6, 7, 150)]   # seq 125..127 and one more lost
    invalid = kvh.encode_format_a((0, 0, 0), (0, 0, 1), sequence=(120 + 200) % 128, temperature_c=0, status=0x70)
    dec = FrameDecoder()
    got = dec.feed(b"".join(keep) + invalid)
    assert len(got) == 197
    assert dec.stats.sequence_gaps == 2 and dec.stats.missing_frames == 4
    assert dec.stats.invalid_status == 1


def test_timestamps_back_dated_by_period_and_monotonic():
    frames = make_frames(10)
    dec = FrameDecoder()
    first = dec.feed(b"".join(frames[:4]), host_time=100.0, frame_period_s=0.01)
    assert [f.host_time for f in first] == pytest.approx([99.97, 99.98, 99.99, 100.0])
    second = dec.feed(b"".join(frames[4:]), host_time=100.02, frame_period_s=0.01)
    times = [f.host_time for f in first + second]
    assert times == sorted(times) and times[-1] == 100.02 and second[0].host_time >= 100.0


def test_hrg_stream_decoder_and_temp_scale():
    freqs = [(4900.0 + k * 1e-4, 4890.0 - k * 1e-4, 4700.5) for k in range(50)]
    raws = [kvh.encode_hrg((0.1, 0.2, 0.3), (0, 0, 1), f, sequence=k, temperature_c=21, temp_scale=1.0)
            for k, f in enumerate(freqs)]
    dec = FrameDecoder("hrg", temp_scale=1.0)
    got = dec.feed(b"junk" + b"".join(raws))
    assert [f.freq_hz for f in got] == freqs
    assert all(f.temperature_c == 21.0 for f in got) and dec.stats.invalid_status == 0
    assert math.isclose(got[1].freq_hz[0] - got[0].freq_hz[0], 1e-4, rel_tol=1e-6)
