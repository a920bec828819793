"""Frame decoder throughput on one core: ``python -m tests.perf.frames``.

Target: >= 100 x the 921600-baud line rate of KVH Format A, i.e. 921600 / (36 bytes x 10 bits)
= 2560 frames/s -> >= 256 000 frames/s, for clean streams and with 1 % of bytes corrupted.
Rates count line frames (every frame sent, intact or corrupt) per CPU second of this process
(time.process_time, single thread: robust when other jobs share the machine).  The
60-byte HRG frame's own 921600-baud line rate is 1536 frames/s; its target is 100 x that.
Also prints the CRC implementations' cost (the reason the decoder uses zlib on bit-reversed
bytes, see bench/devices/kvh.py).
"""
from __future__ import annotations

import argparse
import random
import time

import numpy as np

from bench.devices import kvh

LINE_RATE_A = 921600 / (36 * 10)        # 2560 frames/s
TARGET_RATIO = 100.0


def build_stream(kind: str, n: int, corrupt_rate: float, seed: int = 1) -> bytes:
    rng = random.Random(seed)
    frames = []
    for k in range(n):
        gyro = (rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 1))
        accel = (rng.gauss(0, 0.01), rng.gauss(0, 0.01), 1.0)
        if kind == "hrg":
            frames.append(kvh.encode_hrg(gyro, accel, (4900 + k * 1e-6, 4890.0, 4700.0), sequence=k % 128,
                                         temperature_c=25.0))
        else:
            frames.append(kvh.encode_format_a(gyro, accel, sequence=k % 128, temperature_c=25.0))
    data = np.frombuffer(b"".join(frames), dtype=np.uint8).copy()
    if corrupt_rate > 0:
        nprng = np.random.default_rng(seed)
        flip = np.flatnonzero(nprng.random(data.size) < corrupt_rate)
        data[flip] ^= nprng.integers(1, 256, flip.size, dtype=np.uint8)
    return data.tobytes()


def decode_rate(kind: str, stream: bytes, chunk: int, repeats: int) -> tuple[float, kvh.FrameDecoder]:
    """Best line frames per second (frames sent on the line, good or corrupt, per CPU second)."""
    line_frames = len(stream) / kvh.spec_for(kind).length
    best = 0.0
    decoder = None
    for _ in range(repeats):
        decoder = kvh.FrameDecoder(kind)
        start = time.process_time()
        for pos in range(0, len(stream), chunk):
            decoder.feed(stream[pos:pos + chunk], 0.0, 0.001)
        elapsed = time.process_time() - start
        best = max(best, line_frames / elapsed)
    return best, decoder


def crc_cost_us(fn, data: bytes, repeats: int = 20000) -> float:
    start = time.process_time()
    for _ in range(repeats):
        fn(data)
    return (time.process_time() - start) / repeats * 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    payload = bytes(range(32))
    print(f"CRC-32/MPEG-2 over 32 bytes: table-driven pure Python {crc_cost_us(kvh.crc32_mpeg2_table, payload):.2f} us,"
          f" zlib on bit-reversed bytes {crc_cost_us(kvh.crc32_mpeg2, payload):.2f} us")
    ok = True
    for kind in ("kvh_a", "hrg"):
        for corrupt in (0.0, 0.01):
            stream = build_stream(kind, args.frames, corrupt)
            rate, dec = decode_rate(kind, stream, args.chunk, args.repeats)
            line = 921600 / (kvh.spec_for(kind).length * 10)     # this frame's 921600-baud line rate
            ratio = rate / line
            flag = "OK" if ratio >= TARGET_RATIO else "BELOW TARGET"
            print(f"{kind:6s} corruption {corrupt:4.0%}: {rate:10,.0f} line frames/s = {rate / LINE_RATE_A:6.1f} x 2560/s"
                  f" | {ratio:6.1f} x its own line rate {line:,.0f}/s | accepted {dec.stats.frames:,}"
                  f" bad_crc {dec.stats.bad_crc:,} [{flag}]")
            ok &= ratio >= TARGET_RATIO
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
