"""The recorder stage: parameters, file naming and diagnostics around :class:`QueuedRecorder`.

Used by ``recorder_node`` (fed by raw subscriptions) and ``pose_node`` (fed by its outlets).
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from mmd_ros.logs.recorder import QueuedRecorder, Recorder
from mmd_ros.nodes.calibration_stage import ros_home
from mmd_ros.nodes.diagnostics import ERROR, OK, WARN, Report
from mmd_ros.nodes.params import Param

__all__ = ['RECORDER_PARAMS', 'RecorderConfig', 'RecorderStage', 'raw_writer']

RECORDER_PARAMS = [
    Param('output', '', 'MCAP file to record into; "" makes mmd_<UTC date>_<time>.mcap in '
          'output_dir'),
    Param('output_dir', str(ros_home() / 'mmd' / 'logs'), 'folder of the recordings when output '
          'is ""'),
    Param('max_size_mb', 0.0, 'start a new file (<name>_1.mcap, ...) at this size [MB]; 0 never',
          low=0.1, high=1e7, allow_zero=True),
    Param('max_duration_s', 0.0, 'start a new file after this long [s]; 0 never', low=1.0,
          high=1e8, allow_zero=True),
    Param('flush_period_s', 1.0, 'close the open chunk and fsync this often: after a crash the '
          'log reads back up to the last flush [s]', low=0.05, high=60.0),
    Param('compression', 'zstd', 'chunk compression', choices=('zstd', 'lz4', 'none')),
]


def raw_writer(queue: QueuedRecorder, clock: Any, topic: str, type_name: str, log_qos: str,
               stamped: bool, counter: Callable[[], None] | None = None) -> Callable[[bytes], None]:
    """A raw subscription's callback that records the CDR bytes as received: log time is the
    message's ``header.stamp`` (right after the 4-byte encapsulation), else the receive time."""
    put = queue.put_message

    def write(payload: bytes) -> None:
        if counter is not None:
            counter()
        if stamped and len(payload) >= 12:
            sec, nsec = struct.unpack_from('<iI', payload, 4)
            stamp = sec * 1_000_000_000 + nsec
        else:
            stamp = clock.now().nanoseconds
        put(topic, type_name, stamp, payload, log_qos)
    return write


@dataclass(frozen=True)
class RecorderConfig:
    output: str
    output_dir: str
    max_size_mb: float
    max_duration_s: float
    flush_period_s: float
    compression: str

    @classmethod
    def from_values(cls, v: dict[str, Any]) -> RecorderConfig:
        return cls(**{k: v[k] for k in cls.__dataclass_fields__})

    def path(self) -> Path:
        if self.output:
            return Path(self.output).expanduser()
        name = time.strftime('mmd_%Y%m%d_%H%M%S.mcap', time.gmtime())
        return Path(self.output_dir).expanduser() / name


class RecorderStage:
    """A queued recorder with its diagnostics."""

    def __init__(self, cfg: RecorderConfig, node_name: str, logger: Any) -> None:
        self.cfg = cfg
        self.log = logger
        path = cfg.path()
        recorder = Recorder(path, max_bytes=int(cfg.max_size_mb * 1e6),
                            max_duration_s=cfg.max_duration_s, flush_period_s=cfg.flush_period_s,
                            compression=cfg.compression,
                            metadata={'recorded_by': node_name,
                                      'started_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())})
        self.queue = QueuedRecorder(recorder)
        self._reported_error = False
        if recorder.state == 'error':
            logger.error(f'recorder: {recorder.error}')
        elif recorder.path != path:
            logger.warn(f'{path} exists (an earlier recording): it is not written over; '
                        f'recording into {recorder.path}')
        else:
            logger.info(f'recording into {path}')

    @property
    def path(self) -> Path:
        return self.queue.recorder.path

    def close(self) -> None:
        st = self.queue.close()
        if st.state == 'closed':
            self.log.info(f'recording closed: {", ".join(st.files)} ({st.messages} messages, '
                          f'{st.bytes_on_disk / 1e6:.1f} MB)')

    def report(self) -> Report:
        st = self.queue.status()
        r = Report('recorder', OK, f'recording into {st.path}')
        if st.state == 'error':
            r.worse(ERROR, st.error)
            if not self._reported_error:
                self.log.error(f'recorder: {st.error}')
                self._reported_error = True
        elif st.state == 'closed':
            r.message = f'closed: {st.path}'
        elif math.isfinite(st.last_flush_age_s) and st.last_flush_age_s > 5 * self.cfg.flush_period_s + 2:
            r.worse(WARN, f'no flush for {st.last_flush_age_s:.1f} s: the disk is slow')
        if st.dropped:
            r.worse(WARN, f'{st.dropped} message(s) not recorded')
        r.values.update({
            'state': st.state,
            'file': st.path,
            'files': len(st.files),
            'messages': st.messages,
            'dropped': st.dropped,
            'queued': self.queue.queued,
            'size_mb': round(st.bytes_on_disk / 1e6, 3),
            'flushes': st.flushes,
            'last_flush_age_s': round(st.last_flush_age_s, 2) if math.isfinite(st.last_flush_age_s) else math.nan,
        })
        return r
