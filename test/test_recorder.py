"""Recorder core (flush, rotation, a full disk) and replay timing, ROS-free.

The full disk is real: a child process records with its file size limit (RLIMIT_FSIZE) set low
and SIGXFSZ ignored, so the kernel refuses the write that would cross it with EFBIG, exactly
as a full file system refuses one with ENOSPC.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mmd_ros.logs.cdr import JointStateLayout, encode_string
from mmd_ros.logs.reader import LogReader
from mmd_ros.logs.recorder import QueuedRecorder, Recorder, part_path
from mmd_ros.logs.replay import ReplaySchedule, paced_batches

ROOT = Path(__file__).resolve().parents[1]
NAMES = [f'bar{i}' for i in range(1, 7)] + ['ref1', 'ch8']
T0 = 1_700_000_000_000_000_000


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def rows(n: int, start: int = 0):
    layout = JointStateLayout(NAMES)
    stamps = T0 + (start + np.arange(n, dtype=np.int64)) * 1_000_000
    values = np.arange(start, start + n, dtype=np.float64)[:, None] * np.ones(8)
    return stamps, layout.encode(stamps, values)


def test_flush_rotation_and_latched_messages(tmp_path):
    clock = FakeClock()
    rec = Recorder(tmp_path / 'run.mcap', max_duration_s=2.0, flush_period_s=0.5, clock=clock)
    rec.write('/mmd/device_description', 'std_msgs/msg/String', T0, encode_string('dev: 1'), 'latched')
    stamps, payload = rows(3000)
    for k in range(3):  # three seconds of data, one per simulated second
        a, b = k * 1000, (k + 1) * 1000
        for j in range(a, b, 100):
            rec.write_rows([('/mmd/raw_counts', 'sensor_msgs/msg/JointState', payload[j:j + 100])],
                           stamps[j:j + 100])
            clock.t += 0.1
            rec.poll()
    rec.write('/mmd/calibration', 'std_msgs/msg/String', T0 + 5, encode_string('cal: 2'), 'latched')
    rec.close()
    assert rec.state == 'closed' and rec.error == ''
    assert [p.name for p in rec.files] == ['run.mcap', 'run_1.mcap']
    assert part_path(tmp_path / 'run.mcap', 2).name == 'run_2.mcap'
    total = 0
    for path in rec.files:
        log = LogReader(path)
        assert log.problem is None  # each file is complete
        assert log.latest_string('/mmd/device_description') == 'dev: 1'  # self-contained
        js = log.joint_states('/mmd/raw_counts')
        total += js.stamps_ns.size
        assert np.all(np.diff(js.stamps_ns) == 1_000_000)
    assert total == 3000
    assert LogReader(rec.files[1]).latest_string('/mmd/calibration') == 'cal: 2'
    st = rec.status()
    assert st.messages == 3002 and st.dropped == 0 and st.flushes >= 5
    assert st.bytes_on_disk == sum(p.stat().st_size for p in rec.files)


def test_size_rotation_through_the_queued_recorder(tmp_path):
    rec = Recorder(tmp_path / 'big.mcap', max_bytes=40_000, flush_period_s=0.05,
                   compression='none')
    queued = QueuedRecorder(rec)
    stamps, payload = rows(2000)
    for j in range(0, 2000, 50):
        queued.put_rows([('/mmd/raw_counts', 'sensor_msgs/msg/JointState', payload[j:j + 50])],
                        stamps[j:j + 50])
        if j % 500 == 0:
            import time
            time.sleep(0.12)
    st = queued.close()
    assert st.state == 'closed' and len(st.files) >= 3
    got = np.concatenate([LogReader(p).joint_states('/mmd/raw_counts').stamps_ns for p in st.files])
    np.testing.assert_array_equal(np.sort(got), stamps)


DISK_FULL_CHILD = textwrap.dedent('''
    import json, resource, signal, sys, time
    import numpy as np
    sys.path.insert(0, sys.argv[2])
    from mmd_ros.logs.cdr import JointStateLayout
    from mmd_ros.logs.recorder import Recorder
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, resource.RLIM_INFINITY))
    rec = Recorder(sys.argv[1], flush_period_s=0.01, compression='none')
    layout = JointStateLayout(['bar%d' % i for i in range(1, 9)])
    written = after = 0
    for k in range(2000):
        stamps = 1_700_000_000_000_000_000 + (k * 100 + np.arange(100)) * 1_000_000
        ok = rec.write_rows([('/mmd/raw_counts', 'sensor_msgs/msg/JointState',
                              layout.encode(stamps, np.random.rand(100, 8)))], stamps)
        time.sleep(0.002)
        rec.poll()
        if ok:
            written += 100
        if rec.state != 'recording':
            after += 1  # later messages are dropped, not written
            if after > 3:
                break
    rec.close()
    st = rec.status()
    print(json.dumps({'state': st.state, 'error': st.error, 'written': written,
                      'dropped': st.dropped}))
''')


def test_a_full_disk_stops_recording_and_keeps_what_was_flushed(tmp_path):
    log = tmp_path / 'full.mcap'
    out = subprocess.run([sys.executable, '-c', DISK_FULL_CHILD, str(log), str(ROOT)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    st = json.loads(out.stdout.strip().splitlines()[-1])
    assert st['state'] == 'error' and 'disk is full' in st['error'] and 'EFBIG' in st['error']
    assert st['dropped'] > 0
    reader = LogReader(log)  # everything up to the last flush reads back
    js = reader.joint_states('/mmd/raw_counts')
    assert 0.5 * st['written'] <= js.stamps_ns.size <= st['written']
    assert np.all(np.diff(js.stamps_ns) == 1_000_000)
    assert log.stat().st_size <= 300_000


def test_a_killed_recording_reads_back_to_its_last_flush(tmp_path):
    child = textwrap.dedent('''
        import os, signal, sys
        import numpy as np
        sys.path.insert(0, sys.argv[2])
        from mmd_ros.logs.cdr import JointStateLayout
        from mmd_ros.logs.recorder import Recorder
        rec = Recorder(sys.argv[1])
        layout = JointStateLayout(['a', 'b'])
        s = 1_700_000_000_000_000_000 + np.arange(500, dtype=np.int64) * 1_000_000
        rec.write_rows([('/t', 'sensor_msgs/msg/JointState', layout.encode(s, np.ones((500, 2))))], s)
        rec.flush()
        s2 = s + 500_000_000
        rec.write_rows([('/t', 'sensor_msgs/msg/JointState', layout.encode(s2, np.ones((500, 2))))], s2)
        os.kill(os.getpid(), signal.SIGKILL)
    ''')
    log = tmp_path / 'killed.mcap'
    out = subprocess.run([sys.executable, '-c', child, str(log), str(ROOT)], timeout=120)
    assert out.returncode == -signal.SIGKILL
    js = LogReader(log).joint_states('/t')
    assert js.stamps_ns.size == 500  # the flushed half; the unflushed chunk died with the process


def test_a_restarted_recording_never_writes_over_the_earlier_one(tmp_path):
    """After a crash the node is started again with the same ``output``: the crashed log (and
    its rotation parts) stay as they were; the new recording goes beside them."""
    path = tmp_path / 'run.mcap'
    stamps, payload = rows(200)

    def record() -> Recorder:     # two files: the second after 2 s
        clock = FakeClock()
        rec = Recorder(path, max_duration_s=2.0, clock=clock)
        for part in (slice(0, 100), slice(100, 200)):
            rec.write_rows([('/mmd/raw_counts', 'sensor_msgs/msg/JointState', payload[part])],
                           stamps[part])
            clock.t += 2.5
            rec.poll()
        rec.close()
        return rec

    first = record()
    assert [p.name for p in first.files][:2] == ['run.mcap', 'run_1.mcap']
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    again = record()
    assert [p.name for p in again.files][:2] == ['run.1.mcap', 'run_1.1.mcap']
    assert {name: (tmp_path / name).read_bytes() for name in before} == before
    assert LogReader(tmp_path / 'run.1.mcap').joint_states('/mmd/raw_counts').stamps_ns.size == 100


def test_replay_schedule():
    stamps = T0 + np.arange(0, 1000, dtype=np.int64) * 1_000_000  # 1 s at 1 kHz
    s = ReplaySchedule(stamps, 2.0)
    assert s.duration_s == pytest.approx(0.4995)
    assert s.due(0.0) == 1 and s.due(0.25) == 501 and s.due(10) == 1000
    assert s.wait_s(501, 0.25) == pytest.approx(0.0005)
    fast = ReplaySchedule(stamps, 0.0)
    assert fast.fast and fast.duration_s == 0.0
    with pytest.raises(ValueError):
        ReplaySchedule(stamps, -1.0)
    clock = FakeClock()
    slept = []

    def sleep(dt):
        slept.append(dt)
        clock.t += dt

    got = list(paced_batches(ReplaySchedule(stamps, 1.0), max_batch=100, clock=clock, sleep=sleep))
    assert got[0] == (0, 1) and got[-1][1] == 1000
    assert sum(b - a for a, b in got) == 1000 and sum(slept) == pytest.approx(0.999, abs=1e-6)
    assert list(paced_batches(fast, max_batch=400)) == [(0, 400), (400, 800), (800, 1000)]


def test_a_rotation_part_that_got_nothing_before_the_close_is_not_left_behind(tmp_path):
    """The size limit reached by the last messages opens a new part; closed before anything
    else arrives, that part holds only the latched messages: it is removed, and every file the
    status lists has recorded samples."""
    rec = Recorder(tmp_path / 'r.mcap', max_bytes=1, flush_period_s=1e-9, compression='none')
    stamps, payload = rows(10)
    rec.write_rows([('/mmd/raw_counts', 'sensor_msgs/msg/JointState', payload)], stamps)
    rec.poll()                      # flushes, finds the limit reached, opens r_1.mcap
    assert len(rec.files) == 2
    rec.close()
    st = rec.status()
    assert [Path(f).name for f in st.files] == ['r.mcap'] and not (tmp_path / 'r_1.mcap').exists()
    assert LogReader(tmp_path / 'r.mcap').joint_states('/mmd/raw_counts').stamps_ns.size == 10
