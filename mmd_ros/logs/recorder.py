"""Recording live messages into MCAP logs: periodic flushes, rotation, a full disk (ROS-free).

:class:`Recorder` writes serialised messages (the CDR bytes exactly as they were published)
through :class:`~mmd_ros.logs.writer.LogWriter`:

- **flushed in chunks**: every ``flush_period_s`` the open chunk is closed and fsynced, so after
  a SIGKILL or a power cut everything up to the last flush reads back
  (:class:`~mmd_ros.logs.reader.LogReader` reads a log cut short up to the damage);
- **closed cleanly** by :meth:`Recorder.close` (summary section, indexes): a complete MCAP file;
- **never over an earlier file**: when ``path`` (or a rotation part's name) is taken — a
  recording restarted after a crash with the same ``output`` — the recorder writes
  ``<stem>.1.mcap`` (``.2``, ...) instead (:func:`unused_path`);
- **rotated** by size (``max_bytes``) or time (``max_duration_s``): the first file is ``path``,
  the next ones ``<stem>_1.mcap``, ``<stem>_2.mcap``, ... next to it. Every file starts with the
  latched messages seen so far (device description, calibration, model), so each one is a
  self-contained log;
- **a full disk** (ENOSPC, EDQUOT, EFBIG) or any other write error stops the recording: the
  recorder goes to state ``error`` with a message saying what happened, writes nothing more
  and keeps what was flushed before.

:class:`QueuedRecorder` puts a queue and a thread in front of it, so that the threads that
produce messages (a 1 kHz reader, executor callbacks) never wait for compression or fsync.
"""

from __future__ import annotations

import collections
import errno
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.logs.errors import LogError
from mmd_ros.logs.writer import LogWriter

__all__ = ['QueuedRecorder', 'Recorder', 'RecorderStatus', 'part_path', 'unused_path']

_log = logging.getLogger(__name__)

#: errno values that mean the disk (or the quota, or the file size limit) is full.
DISK_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


def part_path(path: Path, index: int) -> Path:
    """File of rotation part ``index``: ``path`` itself for 0, else ``<stem>_<index><suffix>``."""
    if index == 0:
        return path
    return path.with_name(f'{path.stem}_{index}{path.suffix or ".mcap"}')


def unused_path(path: Path) -> Path:
    """``path``, or when a file is there already (an earlier recording: a raw log is never
    written over), the first of ``<stem>.1<suffix>``, ``<stem>.2<suffix>``, ... that is not."""
    k = 0
    target = path
    while target.exists() or target.is_symlink():
        k += 1
        target = path.with_name(f'{path.stem}.{k}{path.suffix or ".mcap"}')
    return target


@dataclass(frozen=True)
class RecorderStatus:
    """A snapshot for diagnostics.

    state : 'recording', 'closed' or 'error'
    path : the file being written (the last one when closed)
    files : every file written so far, in order
    messages : messages written; dropped : messages not written (after an error, or a full queue)
    bytes_on_disk : size of all files at their last flush [bytes]
    last_flush_age_s : time since the last flush [s], NaN before the first
    error : what went wrong, or ''
    """

    state: str
    path: str
    files: tuple[str, ...]
    messages: int
    dropped: int
    bytes_on_disk: int
    flushes: int
    last_flush_age_s: float
    error: str = ''


class Recorder:
    """An MCAP recording, possibly split into several files. Not thread-safe (see
    :class:`QueuedRecorder`).

    path : the first file [.mcap]; its folder is created
    max_bytes : start a new file once this size is reached (0: never) [bytes]
    max_duration_s : start a new file after this long (0: never) [s]
    flush_period_s : close the open chunk and fsync this often [s]
    compression : 'zstd', 'lz4' or 'none'
    metadata : written as the MCAP metadata record ``mmd_recording`` of every file
    clock : monotonic clock [s]
    """

    def __init__(self, path: str | Path, *, max_bytes: int = 0, max_duration_s: float = 0.0,
                 flush_period_s: float = 1.0, compression: str = 'zstd', chunk_size: int = 1 << 22,
                 metadata: dict[str, str] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 writer_factory: Callable[..., LogWriter] = LogWriter) -> None:
        if max_bytes < 0 or max_duration_s < 0 or not flush_period_s > 0:
            raise LogError('max_bytes and max_duration_s must be >= 0 and flush_period_s > 0')
        self.base = Path(path)
        self.max_bytes = int(max_bytes)
        self.max_duration_s = float(max_duration_s)
        self.flush_period_s = float(flush_period_s)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.metadata = dict(metadata or {})
        self._clock = clock
        self._factory = writer_factory
        self._latched: dict[str, tuple[str, int, bytes, str]] = {}
        self._writer: LogWriter | None = None
        self.files: list[Path] = []
        self.state = 'recording'
        self.error = ''
        self.messages = 0
        self.dropped = 0
        self.flushes = 0
        self._closed_bytes = 0
        self._current_bytes = 0
        self._part_messages = 0
        self._opened_at = 0.0
        self._last_flush = float('nan')
        self._open_next()

    # -- files ---------------------------------------------------------------------------------
    @property
    def path(self) -> Path:
        """The file being written (or the last one)."""
        return self.files[-1] if self.files else self.base

    def _guard(self, what: str, fn: Callable[[], Any]) -> bool:
        """Run a write operation; on an OS error stop recording. True when it succeeded."""
        try:
            fn()
            return True
        except (OSError, LogError) as exc:
            self._fail(what, exc)
            return False

    def _fail(self, what: str, exc: BaseException) -> None:
        code = getattr(exc, 'errno', None)
        if code is None and isinstance(exc.__cause__, OSError):
            code = exc.__cause__.errno
        if code in DISK_FULL:
            why = (f'the disk is full ({errno.errorcode.get(code, code)}) while {what} {self.path}: '
                   'recording stopped; the log keeps everything up to its last flush; free some '
                   'space and start a new recording')
        else:
            why = (f'{exc.__class__.__name__} while {what} {self.path}: {exc}; recording stopped; '
                   'the log keeps everything up to its last flush')
        self.state = 'error'
        self.error = why
        _log.error('%s', why)
        writer, self._writer = self._writer, None
        if writer is not None:
            try:  # let go of the file; its summary cannot be written on a failing disk
                writer.close()
            except (OSError, LogError):
                pass

    def _open_next(self) -> None:
        target = unused_path(part_path(self.base, len(self.files)))

        def open_file() -> None:
            self._writer = self._factory(target, chunk_size=self.chunk_size,
                                         compression=self.compression)
        self.files.append(target)
        if not self._guard('creating', open_file):
            return
        self._opened_at = self._clock()
        self._current_bytes = 0
        self._part_messages = 0
        meta = dict(self.metadata)
        meta['part'] = str(len(self.files) - 1)
        if len(self.files) > 1:
            meta['previous_file'] = self.files[-2].name
        writer = self._writer
        assert writer is not None
        ok = self._guard('writing', lambda: writer.write_metadata('mmd_recording', meta))
        for topic, (msg_type, stamp, payload, qos) in list(self._latched.items()):
            if not ok:
                break
            ok = self._guard('writing', lambda t=topic, m=msg_type, s=stamp, p=payload, q=qos:
                             writer.write_raw(t, m, s, p, q))

    # -- messages ------------------------------------------------------------------------------
    def write(self, topic: str, msg_type: str, stamp_ns: int, payload: bytes,
              qos: str = 'reliable') -> bool:
        """One serialised message (``qos`` 'latched' keeps it for the start of every file).
        Returns False when it was not written (the recorder is closed or failed)."""
        if qos == 'latched':
            self._latched[topic] = (msg_type, int(stamp_ns), bytes(payload), qos)
        writer = self._writer
        if writer is None or self.state != 'recording':
            self.dropped += 1
            return False
        if self._guard('writing', lambda: writer.write_raw(topic, msg_type, int(stamp_ns),
                                                           bytes(payload), qos)):
            self.messages += 1
            self._part_messages += 1
            return True
        self.dropped += 1
        return False

    def write_rows(self, streams: list[tuple[str, str, NDArray[np.uint8]]],
                   stamps_ns: NDArray[np.int64], qos: str = 'reliable') -> bool:
        """N samples of several fixed-layout topics at once (see ``LogWriter.write_rows``)."""
        n = len(stamps_ns) * len(streams)
        writer = self._writer
        if writer is None or self.state != 'recording':
            self.dropped += n
            return False
        if self._guard('writing', lambda: writer.write_rows(streams, stamps_ns, qos)):
            self.messages += n
            self._part_messages += n
            return True
        self.dropped += n
        return False

    def poll(self) -> None:
        """Flush when the flush period has passed, then rotate when a limit is reached."""
        if self._writer is None or self.state != 'recording':
            return
        now = self._clock()
        last = self._last_flush
        if not last == last or now - last >= self.flush_period_s:  # NaN: never flushed
            self.flush()
        if self._writer is None:
            return
        if (self.max_bytes and self._current_bytes >= self.max_bytes) or \
                (self.max_duration_s and now - self._opened_at >= self.max_duration_s):
            self.rotate()

    def flush(self) -> None:
        """Close the open chunk and fsync: after a crash the log reads back up to here."""
        writer = self._writer
        if writer is None or self.state != 'recording':
            return
        if self._guard('flushing', writer.flush):
            self.flushes += 1
            self._last_flush = self._clock()
            try:
                self._current_bytes = self.path.stat().st_size
            except OSError:
                pass

    def rotate(self) -> None:
        """Close the current file cleanly and continue in the next one."""
        writer = self._writer
        if writer is None or self.state != 'recording':
            return
        if not self._guard('closing', writer.close):
            return
        self._closed_bytes += self._size(self.path)
        self._writer = None
        self._open_next()

    def close(self) -> None:
        """Close the current file cleanly (a complete, indexed MCAP file). Safe to call twice.
        A rotation part that received no message after the latched ones (the limit was
        reached by the last messages before the close) is removed: it holds nothing recorded."""
        writer, self._writer = self._writer, None
        if writer is not None and self.state == 'recording':
            if self._guard('closing', writer.close):
                self.state = 'closed'
                if len(self.files) > 1 and self._part_messages == 0:
                    empty = self.files.pop()
                    empty.unlink(missing_ok=True)
        elif self.state == 'recording':
            self.state = 'closed'

    @staticmethod
    def _size(path: Path) -> int:
        try:
            return path.stat().st_size
        except OSError:
            return 0

    def status(self) -> RecorderStatus:
        current = self._current_bytes if self._writer is not None else self._size(self.path)
        last = self._last_flush
        age = self._clock() - last if last == last else float('nan')
        return RecorderStatus(self.state, str(self.path), tuple(str(f) for f in self.files),
                              self.messages, self.dropped, self._closed_bytes + current,
                              self.flushes, age, self.error)


class QueuedRecorder:
    """A :class:`Recorder` fed through a queue and written by its own thread.

    ``put_message`` / ``put_rows`` only append to a queue (any thread); the writer thread
    writes, flushes every ``flush_period_s`` and rotates. When more than ``max_queue`` items
    wait (the disk cannot keep up), new items are dropped and counted.
    """

    def __init__(self, recorder: Recorder, *, max_queue: int = 200_000) -> None:
        self.recorder = recorder
        self.max_queue = int(max_queue)
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque()
        self._cond = threading.Condition()
        self._stop = False
        self.queue_dropped = 0
        self._thread = threading.Thread(target=self._run, name='mmd-recorder', daemon=True)
        self._thread.start()

    def _put(self, item: tuple[Any, ...]) -> None:
        with self._cond:
            if self._stop:
                return
            if len(self._queue) >= self.max_queue:
                self.queue_dropped += 1
                return
            self._queue.append(item)
            if len(self._queue) == 1:
                self._cond.notify()

    def put_message(self, topic: str, msg_type: str, stamp_ns: int, payload: bytes,
                    qos: str = 'reliable') -> None:
        self._put(('msg', topic, msg_type, stamp_ns, payload, qos))

    def put_rows(self, streams: list[tuple[str, str, NDArray[np.uint8]]],
                 stamps_ns: NDArray[np.int64], qos: str = 'reliable') -> None:
        self._put(('rows', streams, stamps_ns, qos))

    def _run(self) -> None:
        rec = self.recorder
        period = min(0.2, rec.flush_period_s / 2)
        while True:
            with self._cond:
                if not self._queue and not self._stop:
                    self._cond.wait(period)
                items = list(self._queue)
                self._queue.clear()
                stop = self._stop
            for item in items:
                if item[0] == 'msg':
                    rec.write(*item[1:])
                else:
                    rec.write_rows(*item[1:])
            rec.poll()
            if stop:
                return

    def status(self) -> RecorderStatus:
        st = self.recorder.status()
        if self.queue_dropped:
            st = RecorderStatus(st.state, st.path, st.files, st.messages,
                                st.dropped + self.queue_dropped, st.bytes_on_disk, st.flushes,
                                st.last_flush_age_s, st.error)
        return st

    @property
    def queued(self) -> int:
        return len(self._queue)

    def close(self, timeout: float = 10.0) -> RecorderStatus:
        """Write what is queued, close the log cleanly and stop the thread."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout)
        self.recorder.close()
        return self.status()
