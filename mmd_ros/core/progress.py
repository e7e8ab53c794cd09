"""Progress on long jobs: a one-line bar on stderr when it is a terminal, sparse lines otherwise."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ['Progress', 'heading']


class Progress:
    """Report ``done`` of ``total`` units of work under ``label``; quiet when ``enabled`` is False."""

    def __init__(self, label: str, total: float, *, enabled: bool = True,
                 stream: TextIO | None = None, interval_s: float = 0.5) -> None:
        self.label = label
        self.total = max(float(total), 1e-12)
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.interval_s = interval_s if self.stream.isatty() else max(interval_s, 5.0)
        self._start = time.monotonic()
        self._last = -1e9

    def update(self, done: float) -> None:
        now = time.monotonic()
        if not self.enabled or now - self._last < self.interval_s:
            return
        self._last = now
        frac = min(max(done / self.total, 0.0), 1.0)
        elapsed = now - self._start
        eta = elapsed * (1 - frac) / frac if frac > 0 else float('nan')
        line = f'{self.label}: {100 * frac:5.1f} %  elapsed {elapsed:6.1f} s  left {eta:6.1f} s'
        if self.stream.isatty():
            self.stream.write('\r' + line)
        else:
            self.stream.write(line + '\n')
        self.stream.flush()

    def close(self) -> None:
        """Say the work is done (once: a second call says nothing)."""
        if self.enabled:
            self.enabled = False
            elapsed = time.monotonic() - self._start
            end = '\r' if self.stream.isatty() else ''
            self.stream.write(f'{end}{self.label}: done in {elapsed:.1f} s{" " * 20}\n')
            self.stream.flush()


def heading(text: str) -> None:
    """A section heading in console reports (demo, analysis)."""
    print(f'\n== {text} ' + '=' * max(0, 74 - len(text)))
