"""Replay timing: when each recorded sample is due again (ROS-free).

A log is replayed with its original timing (``rate`` 1), faster or slower by a rate factor, or
as fast as possible (``rate`` 0). Sample k of a log with stamps t_k is due ``(t_k - t_0) / rate``
seconds after the replay started; :class:`ReplaySchedule` answers how many samples are due at
a given moment and how long to wait for the next one, and :func:`paced_batches` turns that into
the index ranges a publisher sends, sleeping in between. Republished messages keep their
recorded stamps, so what the live pipeline computes from them lines up with the log.
:func:`log_problem_values` says, in diagnostics key/values, what a damaged log lost before the
replay started (those samples cannot be replayed).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import ArrayLike

from mmd_ros.logs.reader import LogProblem

__all__ = ['ReplaySchedule', 'log_problem_values', 'paced_batches']


class ReplaySchedule:
    """Due times of a log's samples.

    stamps_ns : array_like, shape (N,) — recorded stamps, non-decreasing [ns]
    rate : float — playback speed factor (1: original timing, 2: twice as fast); 0 or inf: as
        fast as possible
    """

    def __init__(self, stamps_ns: ArrayLike, rate: float = 1.0) -> None:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        if stamps.ndim != 1:
            raise ValueError('stamps_ns must be one-dimensional')
        if not (rate >= 0) or math.isnan(rate):
            raise ValueError(f'rate must be >= 0 (0: as fast as possible), got {rate}')
        self.stamps_ns = stamps
        self.rate = float(rate)
        self.fast = rate == 0 or math.isinf(rate)
        t0 = int(stamps[0]) if stamps.size else 0
        # due offsets [s] from the start of the replay; clamped so that they never go back
        rel = np.maximum.accumulate((stamps - t0).astype(np.float64)) * 1e-9 if stamps.size else np.zeros(0)
        self.offsets_s = rel / self.rate if not self.fast else np.zeros_like(rel)

    @property
    def n(self) -> int:
        return int(self.stamps_ns.size)

    @property
    def duration_s(self) -> float:
        """Time the whole replay takes [s] (0 as fast as possible)."""
        return float(self.offsets_s[-1]) if self.n else 0.0

    def due(self, elapsed_s: float) -> int:
        """How many samples are due ``elapsed_s`` after the start."""
        return int(np.searchsorted(self.offsets_s, elapsed_s, side='right'))

    def wait_s(self, k: int, elapsed_s: float) -> float:
        """Seconds from ``elapsed_s`` until sample ``k`` is due (0 if it already is)."""
        if k >= self.n:
            return 0.0
        return max(0.0, float(self.offsets_s[k]) - elapsed_s)


def paced_batches(schedule: ReplaySchedule, *, max_batch: int = 64,
                  stop: threading.Event | None = None,
                  clock: Callable[[], float] = time.monotonic,
                  sleep: Callable[[float], object] = time.sleep) -> Iterator[tuple[int, int]]:
    """Index ranges [a, b) of samples as they fall due, at most ``max_batch`` at a time.

    Blocks (sleeps) until the next sample is due; stops early when ``stop`` is set.
    """
    start = clock()
    k = 0
    while k < schedule.n:
        if stop is not None and stop.is_set():
            return
        elapsed = clock() - start
        due = schedule.due(elapsed) if not schedule.fast else schedule.n
        if due <= k:
            wait = schedule.wait_s(k, elapsed)
            if stop is not None:
                stop.wait(min(wait, 0.1))
            else:
                sleep(min(wait, 0.1))
            continue
        b = min(due, k + max_batch)
        yield k, b
        k = b


def _seconds(value: float | None) -> str:
    return '?' if value is None else f'{value:.3f}'


def log_problem_values(problem: LogProblem | None, topic: str = '/mmd/raw_counts') -> dict[str, str]:
    """What reading the log lost, as diagnostics key/values (empty for a whole log): the kind,
    the stretches skipped, the ``topic`` messages lost (``unknown`` when no index survived),
    their time spans and the full message."""
    if problem is None:
        return {}
    lost = problem.lost_messages
    spans = [s.as_dict(problem.t0_ns) for s in problem.skipped]
    return {
        'log_problem': problem.kind,
        'log_clean_end': str(problem.clean_end).lower(),
        'log_skipped_parts': str(len(spans)),
        'log_lost_samples': 'unknown' if lost is None else str(lost.get(topic, 0)),
        'log_lost_spans_s': '; '.join(f'{_seconds(s["start_s"])}..'
                                      f'{"end" if s["at_end"] else _seconds(s["end_s"])}' for s in spans),
        'log_problem_detail': problem.message,
    }
