"""Benchmark of the terminal protocol and driver: decode throughput, and the driver's CPU at 1 kHz.

1. Encoding and decoding of sample frames in batches (``encode_frames`` / ``decode_frames``),
   and the stateful decoder (``FrameStream.feed``: CRC filter, gaps, unwrapping) fed with
   live-sized transfers (8 frames) and with replay-sized blocks (4096 frames).
2. ``TerminalDriver.read_batch`` in a loop against the simulated terminal paced in real time at
   1 kHz, for ``--seconds`` (10 by default): process CPU per second of stream, split into what the
   simulated terminal costs (measured around the backend's bulk reads) and the rest (driver,
   pyusb, decoding).

Prints the figures and, last, one JSON line. Never fails on timing.

    PYTHONPATH=. python bench/bench_driver.py [--seconds 10] [--fpt 8]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mmd_ros.hardware import (  # noqa: E402
    FrameStream, SimTerminal, SimUsbBackend, TerminalDriver, decode_frames, encode_frames,
)


def _rate(fn, n_items: int, min_time: float = 0.5) -> float:
    """Items per second of fn() (best of a few repetitions)."""
    best = float('inf')
    t_end = time.perf_counter() + min_time
    reps = 0
    while reps < 3 or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        reps += 1
    return n_items / best


def bench_codec(n: int = 200_000) -> dict[str, float]:
    rng = np.random.default_rng(0)
    seq = np.arange(n)
    t_ns = seq * 1_000_000
    counts = np.cumsum(rng.integers(-5000, 5000, size=(n, 8)), axis=0) + (1 << 31) - 10_000
    data = encode_frames(seq, t_ns, counts)
    out = {
        'encode_frames_per_s': _rate(lambda: encode_frames(seq, t_ns, counts), n),
        'decode_frames_per_s': _rate(lambda: decode_frames(data), n),
    }

    def feed(block: int) -> None:
        s = FrameStream()
        step = block * 64
        for i in range(0, len(data), step):
            s.feed(data[i:i + step])

    out['stream_feed_4096_frames_per_s'] = _rate(lambda: feed(4096), n)
    n_small = 20_000
    small = data[:n_small * 64]

    def feed_small() -> None:
        s = FrameStream()
        for i in range(0, len(small), 8 * 64):
            s.feed(small[i:i + 8 * 64])

    out['stream_feed_8_frames_per_s'] = _rate(feed_small, n_small)
    out['stream_feed_8_us_per_transfer'] = 8e6 / out['stream_feed_8_frames_per_s']
    return out


class _TimedBackend(SimUsbBackend):
    """Measures the CPU the simulated terminal spends inside bulk reads (thread CPU time)."""

    sim_cpu_s = 0.0

    def bulk_read(self, *args, **kwargs):  # type: ignore[override]
        t0 = time.thread_time()
        try:
            return super().bulk_read(*args, **kwargs)
        finally:
            self.sim_cpu_s += time.thread_time() - t0


def bench_driver(seconds: float, fpt: int) -> dict[str, float]:
    term = SimTerminal(paced=True, power_on_reset=False, frames_per_transfer=fpt)
    backend = _TimedBackend(term)
    frames = transfers = 0
    with TerminalDriver(backend=backend) as drv:
        drv.read_batch()
        backend.sim_cpu_s = 0.0
        c0, t0 = time.process_time(), time.monotonic()
        while time.monotonic() - t0 < seconds:
            b = drv.read_batch()
            frames += b.n
            transfers += 1
        cpu, wall = time.process_time() - c0, time.monotonic() - t0
        stats = drv.stats
    driver_cpu = cpu - backend.sim_cpu_s
    return {
        'seconds': wall,
        'frames': frames,
        'transfers': transfers,
        'frames_per_transfer': fpt,
        'rate_hz': frames / wall,
        'measured_rate_hz': stats.sample_rate_hz,
        'gaps': stats.gaps,
        'cpu_total_percent': 100 * cpu / wall,
        'cpu_sim_percent': 100 * backend.sim_cpu_s / wall,
        'cpu_driver_percent': 100 * driver_cpu / wall,
        'driver_us_per_transfer': 1e6 * driver_cpu / max(transfers, 1),
        'driver_us_per_frame': 1e6 * driver_cpu / max(frames, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='real-time run length [s]')
    ap.add_argument('--fpt', type=int, default=8, help='frames per USB transfer')
    args = ap.parse_args(argv)

    codec = bench_codec()
    print('frame codec (64-byte frames, batches of 200000):')
    print(f"  encode            {codec['encode_frames_per_s'] / 1e6:8.2f} M frames/s")
    print(f"  decode            {codec['decode_frames_per_s'] / 1e6:8.2f} M frames/s")
    print(f"  FrameStream 4096  {codec['stream_feed_4096_frames_per_s'] / 1e6:8.2f} M frames/s (replay)")
    print(f"  FrameStream 8     {codec['stream_feed_8_frames_per_s'] / 1e6:8.3f} M frames/s "
          f"({codec['stream_feed_8_us_per_transfer']:.0f} µs per 8-frame transfer, live)")

    drv = bench_driver(args.seconds, args.fpt)
    print(f"driver at 1 kHz real time, {drv['seconds']:.1f} s, {args.fpt} frames/transfer:")
    print(f"  {drv['frames']} frames in {drv['transfers']} transfers, {drv['rate_hz']:.1f} Hz "
          f"(driver's measured rate {drv['measured_rate_hz']:.1f} Hz), gaps {drv['gaps']}")
    print(f"  CPU: {drv['cpu_total_percent']:.2f} % of a core in all, of which simulated terminal "
          f"{drv['cpu_sim_percent']:.2f} %, driver + pyusb + decoding {drv['cpu_driver_percent']:.2f} % "
          f"({drv['driver_us_per_transfer']:.0f} µs per transfer)")
    print(json.dumps({'bench': 'driver', **{k: round(v, 3) if isinstance(v, float) else v
                                            for k, v in {**codec, **drv}.items()}}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
