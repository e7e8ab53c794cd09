"""A damaged log loses only its damaged part, and says what it lost.

Real files: a simulated run rewritten in many small chunks, then one byte flipped (in a chunk's
compressed data, in its length, in its compression field), the file cut mid-chunk, or both. Every
sample of every intact chunk must come back with its values, the skipped span must be reported
(in the reader, in ``mmd process``/``analyze``/``iso230-2`` output and the replay diagnostics), and
a log whose stamps go backwards must be refused instead of giving metres of "error".
"""

from __future__ import annotations

import json
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from mmd_ros.cli.main import main
from mmd_ros.logs.errors import LogError, LogFormatError
from mmd_ros.logs.layout import TOPIC_RAW, read_run, write_run
from mmd_ros.logs.reader import LogReader
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log

CHUNK = 48 * 1024


@pytest.fixture(scope='module')
def run_log(tmp_path_factory):
    """A 28 s ISO 230-2 x-axis run (1 kHz) rewritten in ~50 small chunks; and the original."""
    folder = tmp_path_factory.mktemp('damage')
    sim = folder / 'sim.mcap'
    simulate_to_log(SimulationSpec(scenario_params=('n_cycles=1', 'n_targets=3')), sim, progress=False)
    run = read_run(sim)
    path = folder / 'run.mcap'
    write_run(path, run.device, run.calibration, run.stamps_ns, run.counts,
              reference_pose=run.reference_pose, metadata=run.metadata, chunk_size=CHUNK)
    return path, run


def chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, record length) of every chunk record, walking the data section."""
    off, out = 8, []
    while off < len(data):
        op = data[off]
        (length,) = struct.unpack_from('<Q', data, off + 1)
        if op == 0x06:
            out.append((off, 9 + length))
        if op == 0x0F:
            break
        off += 9 + length
    return out


def chunk_stamps(data: bytes, offset: int) -> tuple[int, int]:
    """Message start and end time of the chunk at ``offset`` (its header, before any damage)."""
    return struct.unpack_from('<QQ', data, offset + 9)


def damaged(tmp_path, data: bytes, name: str, where: int | None = None, xor: int = 0xFF,
            cut: int | None = None):
    out = bytearray(data)
    if where is not None:
        out[where] ^= xor
    if cut is not None:
        out = out[:cut]
    path = tmp_path / name
    path.write_bytes(bytes(out))
    return path


def check_kept(run, js, keep):
    """The reader returned exactly the original samples selected by ``keep``, with their counts;
    returns how many were not kept."""
    assert np.array_equal(js.stamps_ns, run.stamps_ns[keep])
    assert np.array_equal(js.values, run.counts[keep])
    return int((~keep).sum())


def outside(run, t0, t1):
    return (run.stamps_ns < t0) | (run.stamps_ns > t1)


# chunk header: opcode 0, length 1..8, message start/end time 9..24, uncompressed size 25..32,
# CRC 33..36, compression string length 37..40, compression 41.., records length, records
@pytest.mark.parametrize('place,xor', [
    ('compressed data', 0xFF),
    ('record length', 0x01),        # the chunk's length no longer matches its header
    ('record length high byte', 0x01),  # points past the end of the file
    ('compression length', 0x01),
    ('opcode', 0x06),               # 0x06 ^ 0x06 = 0: not a record at all
])
def test_one_damaged_chunk_loses_that_chunk_only(tmp_path, run_log, place, xor):
    path, run = run_log
    data = path.read_bytes()
    table = chunks(data)
    assert len(table) > 20
    off, length = table[len(table) // 2]
    where = {'compressed data': off + length // 2, 'record length': off + 2,
             'record length high byte': off + 8, 'compression length': off + 37, 'opcode': off}[place]
    t0, t1 = chunk_stamps(data, off)
    bad = damaged(tmp_path, data, 'bad.mcap', where, xor)
    reader = LogReader(bad)
    lost = check_kept(run, reader.joint_states(TOPIC_RAW), outside(run, t0, t1))
    assert 0 < lost < run.stamps_ns.size / 20            # one chunk of ~50, every later one read
    problem = reader.problem
    assert problem is not None and problem.kind == 'damaged' and problem.clean_end
    (span,) = problem.skipped
    assert span.offset == off and span.size == length    # exactly the damaged chunk's bytes
    assert span.exact and (span.start_ns, span.end_ns) == (t0, t1)
    assert span.messages[TOPIC_RAW] == lost and span.messages['/mmd/reference/pose'] == lost
    assert f'{TOPIC_RAW} {lost}' in str(problem) and 'read on' in str(problem)


@pytest.mark.parametrize('place', ['compressed data', 'record length'])
def test_damage_in_a_log_without_its_summary_is_skipped_by_scanning(tmp_path, run_log, place):
    """A crashed recording (no summary, no chunk index) with a damaged chunk: the reader finds
    the next chunk itself, and the message indexes that follow the damaged chunk say what it held."""
    path, run = run_log
    data = path.read_bytes()
    table = chunks(data)
    off, length = table[len(table) // 2]
    last, last_len = table[-2]
    where = off + length // 2 if place == 'compressed data' else off + 2
    bad = damaged(tmp_path, data, 'bad.mcap', where, cut=last + last_len // 2)
    reader = LogReader(bad)
    t0, t1 = chunk_stamps(data, off)
    tail0 = chunk_stamps(data, last)[0]
    keep = outside(run, t0, t1) & (run.stamps_ns < tail0)
    check_kept(run, reader.joint_states(TOPIC_RAW), keep)
    lost = int((~outside(run, t0, t1)).sum())
    problem = reader.problem
    assert problem.kind == 'damaged' and not problem.clean_end
    inner, tail = problem.skipped
    assert inner.exact and inner.messages[TOPIC_RAW] == lost and (inner.start_ns, inner.end_ns) == (t0, t1)
    assert tail.at_end and 'ended uncleanly' in str(problem)


def test_a_log_cut_mid_chunk_reads_to_its_last_complete_chunk_and_says_it_ended_uncleanly(tmp_path, run_log):
    path, run = run_log
    data = path.read_bytes()
    table = chunks(data)
    off, length = table[len(table) // 2]
    cut = damaged(tmp_path, data, 'cut.mcap', cut=off + length // 2)
    reader = LogReader(cut)
    t0 = chunk_stamps(data, off)[0]
    js = reader.joint_states(TOPIC_RAW)
    assert np.array_equal(js.stamps_ns, run.stamps_ns[run.stamps_ns < t0])
    problem = reader.problem
    assert problem.kind == 'unclean_end' and not problem.clean_end
    assert 'ended uncleanly' in str(problem) and problem.skipped[-1].at_end
    # cut exactly after a complete chunk and its indexes: nothing lost, still not a clean end
    whole = damaged(tmp_path, data, 'whole.mcap', cut=table[len(table) // 2 + 1][0])
    reader = LogReader(whole)
    assert reader.problem.kind == 'unclean_end' and reader.problem.skipped == ()
    assert reader.truncated


def test_random_damage_never_raises_never_lies(tmp_path, run_log):
    """Thirty single-byte flips anywhere: the reader reads or refuses with a LogError, never
    returns a wrong value, never loses samples without saying so, and loses at most two chunks."""
    path, run = run_log
    data = path.read_bytes()
    per_chunk = run.stamps_ns.size / len(chunks(data))
    rng = np.random.default_rng(7)
    for _ in range(30):
        where = int(rng.integers(8, len(data)))
        bad = damaged(tmp_path, data, 'fuzz.mcap', where, int(rng.integers(1, 256)))
        try:
            reader = LogReader(bad)
            js = reader.joint_states(TOPIC_RAW)
        except LogError:
            continue
        k = np.searchsorted(run.stamps_ns, js.stamps_ns)
        assert np.array_equal(run.stamps_ns[k], js.stamps_ns) and np.array_equal(run.counts[k], js.values), where
        if js.stamps_ns.size < run.stamps_ns.size:
            assert reader.problem is not None, where
        assert js.stamps_ns.size >= run.stamps_ns.size - 2.5 * per_chunk, (where, str(reader.problem))


def test_rosbags_still_opens_our_logs(run_log):
    from pathlib import Path

    from rosbags.highlevel import AnyReader
    path, run = run_log
    with AnyReader([Path(path)]) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC_RAW]
        n = sum(1 for _ in reader.messages(connections=conns))
    assert n == run.stamps_ns.size


@pytest.fixture(scope='module')
def damaged_log(tmp_path_factory, run_log):
    path, run = run_log
    data = path.read_bytes()
    table = chunks(data)
    off, length = table[len(table) // 3]
    bad = tmp_path_factory.mktemp('bad') / 'bad.mcap'
    bad.write_bytes(data[:off + length // 2] + bytes([data[off + length // 2] ^ 0xFF]) + data[off + length // 2 + 1:])
    lost = int(np.sum((run.stamps_ns >= chunk_stamps(data, off)[0]) & (run.stamps_ns <= chunk_stamps(data, off)[1])))
    return bad, lost, run


def test_mmd_process_reports_the_skipped_span(tmp_path, damaged_log, capsys):
    bad, lost, run = damaged_log
    assert main(['process', str(bad), '--out', str(tmp_path / 'p.mcap'), '--json']) == 0
    out = capsys.readouterr()
    summary = json.loads(out.out)
    assert summary['samples'] == run.stamps_ns.size - lost
    problem = summary['log_problem']
    assert problem['kind'] == 'damaged' and problem['lost_messages'][TOPIC_RAW] == lost
    (span,) = problem['skipped']
    assert span['exact'] and span['end_s'] > span['start_s'] > 0
    assert 'warning:' in out.err and 'damaged part skipped' in out.err


def test_mmd_iso230_and_analyze_report_the_skipped_span(tmp_path, damaged_log, capsys):
    bad, lost, _ = damaged_log
    assert main(['iso230-2', str(bad), '--json', '--out', str(tmp_path / 'iso')]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['log_problem']['lost_messages'][TOPIC_RAW] == lost
    assert 'not read whole' in (tmp_path / 'iso' / 'iso230.md').read_text()
    assert main(['analyze', str(bad), '--json', '--quiet', '--effects', 'drift', '--max-effects', '1',
                 '--max-samples', '500']) == 0
    result = json.loads(capsys.readouterr().out)
    assert result['log_problem']['lost_messages'][TOPIC_RAW] == lost


def test_the_replay_diagnostics_say_what_the_log_lost(damaged_log):
    from mmd_ros.logs.replay import log_problem_values
    bad, lost, _ = damaged_log
    values = log_problem_values(read_run(bad).problem)
    assert values['log_problem'] == 'damaged' and values['log_lost_samples'] == str(lost)
    assert values['log_skipped_parts'] == '1' and '..' in values['log_lost_spans_s']
    assert log_problem_values(None) == {}


def test_stamps_that_go_backwards_are_refused_and_a_segment_can_be_read(tmp_path, run_log, capsys):
    """A clock stepping back 5 s mid-run used to give a 16,583 µm 'error' without a word."""
    path, run = run_log
    stamps = run.stamps_ns.copy()
    k = stamps.size // 2
    stamps[k:] -= 5_000_000_000
    back = tmp_path / 'back.mcap'
    write_run(back, run.device, run.calibration, stamps, run.counts, reference_pose=run.reference_pose,
              metadata=run.metadata)
    with pytest.raises(LogFormatError, match='go backwards 1 time') as info:
        read_run(back)
    assert f'after sample {k - 1}' in str(info.value) and '2 segments' in str(info.value)
    assert main(['process', str(back), '--out', str(tmp_path / 'p.mcap'), '--json']) == 2
    assert 'go backwards' in capsys.readouterr().err and not (tmp_path / 'p.mcap').exists()
    for segment, (a, b) in ((1, (0, k)), (2, (k, stamps.size))):
        part = read_run(back, segment=segment)
        assert np.array_equal(part.counts, run.counts[a:b]) and part.segment == (segment, 2)
        assert np.array_equal(part.reference_pose, run.reference_pose[a:b], equal_nan=True)
    assert main(['process', str(back), '--segment', '2', '--out', str(tmp_path / 'p.mcap'), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['segment'] == {'index': 2, 'of': 2}
    x = next(s for s in summary['pose_error'] if s['name'] == 'x')
    assert x['n'] > 0 and x['max_abs'] < 5.0              # µm: the reference lines up again
    assert main(['process', str(back), '--segment', '3', '--out', str(tmp_path / 'p.mcap')]) == 2


def test_repeated_stamps_are_refused_and_a_clean_segment_can_be_read(tmp_path, capsys):
    """Every other sample stamped as the one before it: mmd process paired the reference with
    the wrong samples (x RMS 54.8 µm instead of 1.3 µm) and iso230-2 divided by zero."""
    from mmd_ros.core.device import find_config, load_device
    from mmd_ros.logs.layout import BAR_NAMES, TOPIC_DEVICE, TOPIC_REF_LENGTHS, open_run
    from mmd_ros.logs.writer import LogWriter
    device = load_device(find_config('mmd_prototype.yaml'))
    t0, n = 1_800_000_000 * 10**9, 200
    stamps = t0 + np.arange(n, dtype=np.int64) * 4_000_000
    counts = np.arange(n * 8, dtype=np.float64).reshape(n, 8)
    pose = np.zeros((n, 6))
    twice = stamps.copy()
    twice[1::2] = twice[::2]
    dup = write_run(tmp_path / 'dup.mcap', device, None, twice, counts, reference_pose=pose)
    with pytest.raises(LogFormatError, match=f'100 of the 200 samples of {TOPIC_RAW} repeat the '
                       f'stamp of the sample before them, first sample 1 at {t0} ns'):
        read_run(dup)
    for args in (['process', str(dup), '--out', str(tmp_path / 'p.mcap')], ['iso230-2', str(dup)]):
        assert main(args) == 2
        assert 'repeat the stamp' in capsys.readouterr().err
    # a clock stepped back 10 s after sample 99, and one repeat in the second stretch
    back = stamps - np.where(np.arange(n) >= 100, 10**10, 0)
    back[151] = back[150]
    path = write_run(tmp_path / 'back.mcap', device, None, back, counts, reference_pose=pose)
    with pytest.raises(LogFormatError, match='go backwards 1 time'):
        read_run(path)
    assert np.array_equal(read_run(path, segment=1).counts, counts[:100])
    with pytest.raises(LogFormatError, match='1 of the 100 samples .* first sample 151 at'):
        read_run(path, segment=2)
    # the reference repeating a stamp: which of the two goes with that sample?
    ref = stamps.copy()
    ref[5] = ref[4]
    with LogWriter(tmp_path / 'ref.mcap') as log:
        log.write_string(TOPIC_DEVICE, t0, device.to_yaml())
        log.write_rows([(TOPIC_RAW, 'sensor_msgs/msg/JointState',
                         log.joint_state_rows(device.channel_names, stamps, counts)),
                        (TOPIC_REF_LENGTHS, 'sensor_msgs/msg/JointState',
                         log.joint_state_rows(BAR_NAMES, ref, np.ones((n, 6))))], stamps)
    with pytest.raises(LogFormatError, match=f'1 of the 200 samples of {TOPIC_REF_LENGTHS} repeat'):
        read_run(tmp_path / 'ref.mcap')
    with open_run(tmp_path / 'ref.mcap') as stream, pytest.raises(LogFormatError, match='repeat'):
        list(stream.blocks(64))


@pytest.mark.parametrize('place', ['compressed data', 'record length', 'record length high byte',
                                   'opcode', 'no summary'])
def test_mmd_process_reading_block_by_block_loses_and_reports_the_same(tmp_path, run_log, place):
    """open_run (``mmd process``'s reader: two passes, a chunk at a time) keeps exactly what
    read_run keeps of a damaged log, and reports the same skipped spans."""
    from mmd_ros.logs.layout import open_run
    path, _ = run_log
    data = path.read_bytes()
    table = chunks(data)
    off, length = table[len(table) // 2]
    if place == 'no summary':
        last, last_len = table[-2]
        bad = damaged(tmp_path, data, 'bad.mcap', off + length // 2, cut=last + last_len // 2)
    else:
        where = {'compressed data': off + length // 2, 'record length': off + 2,
                 'record length high byte': off + 8, 'opcode': off}[place]
        bad = damaged(tmp_path, data, 'bad.mcap', where, 0x06 if place == 'opcode' else 0x01
                      if 'length' in place else 0xFF)
    whole = read_run(bad)
    with open_run(bad) as stream:
        blocks = list(stream.blocks(1000))
        problem = stream.problem
    assert np.array_equal(np.concatenate([b.stamps_ns for b in blocks]), whole.stamps_ns)
    assert np.array_equal(np.concatenate([b.counts for b in blocks]), whole.counts)
    assert np.array_equal(np.concatenate([b.reference_pose for b in blocks]), whole.reference_pose,
                          equal_nan=True)
    assert whole.problem is not None and problem.as_dict() == whole.problem.as_dict()


def test_a_log_that_lost_its_start_is_read_with_the_device_and_calibration_given(tmp_path, run_log,
                                                                                capsys):
    """The device description and the calibration are written first: damage there left the
    samples unreadable although every one of them was intact. Given the two files, the samples
    come back; a description given over a log's own that differs is said to differ."""
    path, run = run_log
    data = path.read_bytes()
    off, length = chunks(data)[0]
    bad = damaged(tmp_path, data, 'start.mcap', off + length // 2)
    with pytest.raises(LogFormatError, match='--device FILE'):
        read_run(bad)
    device = tmp_path / 'device.yaml'
    device.write_text(run.device.to_yaml())
    calibration = tmp_path / 'calibration.yaml'
    calibration.write_text(run.calibration.to_yaml())
    back = read_run(bad, device=run.device)
    lost = back.problem.skipped[0].messages.get(TOPIC_RAW, 0)
    assert back.device_note == '' and back.calibration is None
    keep = np.isin(run.stamps_ns, back.stamps_ns)
    assert check_kept(run, _as_js(back), keep) == lost
    assert main(['process', str(bad), '--device', str(device), '--calibration', str(calibration),
                 '--out', str(tmp_path / 'p.mcap'), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['samples'] == run.stamps_ns.size - lost > 0.9 * run.stamps_ns.size
    assert main(['process', str(path), '--out', str(tmp_path / 'q.mcap'), '--json']) == 0
    whole = json.loads(capsys.readouterr().out)
    x, x_whole = summary['pose_error'][0]['rms'], whole['pose_error'][0]['rms']
    assert abs(x - x_whole) < 0.05 * x_whole
    # the paper's description over the twin's, which states more: said, section by section
    assert main(['process', str(path), '--device', 'mmd_prototype.yaml', '--out',
                 str(tmp_path / 'r.mcap'), '--json']) == 0
    err = capsys.readouterr().err
    assert 'replaces the log\'s own' in err and 'bars' in err
    assert main(['process', str(path), '--device', str(device), '--out', str(tmp_path / 's.mcap'),
                 '--json']) == 0
    assert 'replaces' not in capsys.readouterr().err


def _as_js(run):
    """A run's samples as :func:`check_kept` takes them."""
    return SimpleNamespace(stamps_ns=run.stamps_ns, values=run.counts)
