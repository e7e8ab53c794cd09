"""``mmd process`` at compiled speed: the batch pipeline on the compiled path equals the numpy
reference bit for bit, a log processed block by block equals the run processed at once, and the
raw log is never written over."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mmd_ros.core.compiled import AVAILABLE as COMPILED, NOT_IN_USE
from mmd_ros.core.model import Model
from mmd_ros.core.terms import GravitySagTerm, HysteresisTerm
from mmd_ros.logs.layout import read_run
from mmd_ros.logs.processing import process_log, process_run, summarize, write_processed
from mmd_ros.logs.reader import LogReader
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log


@pytest.fixture(scope='module')
def run_log(tmp_path_factory):
    """20 s of realistic random 6-DOF motion with a full pose reference (the twin)."""
    log = tmp_path_factory.mktemp('processing') / 'run.mcap'
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=20',),
                                   reference='pose6', seed=4), log, progress=False)
    return log


def test_compiled_pipeline_equals_the_numpy_reference(run_log):
    """CDF → thermal → model terms → FK (twice: a term needs the pose) → covariance over whole
    blocks: the compiled helpers give the numpy path's poses, flags, statuses and iterations bit
    for bit, and its covariance to rounding (1e-12 of the largest variance)."""
    assert COMPILED, NOT_IN_USE
    run = read_run(run_log)

    def model():  # a term with state and a term that needs the first-pass pose (two FK passes)
        return Model(terms=[HysteresisTerm(np.full(6, 0.3e-6), 5e-6), GravitySagTerm(
            run.device.geometry.upper, run.device.geometry.lower, np.full(6, 1e-7))])

    fast = process_run(run, model(), with_covariance=True, compiled=True)
    slow = process_run(run, model(), with_covariance=True, compiled=False)
    for f in dataclasses.fields(fast):
        if f.name != 'covariance':
            np.testing.assert_array_equal(getattr(fast, f.name), getattr(slow, f.name), err_msg=f.name)
    scale = np.abs(slow.covariance).max()
    np.testing.assert_allclose(fast.covariance, slow.covariance, rtol=0, atol=1e-12 * scale)
    assert fast.valid.mean() > 0.99


def test_a_log_processed_block_by_block_is_the_run_processed_at_once(run_log, tmp_path):
    """process_log (reading, computing and writing overlapped, a block at a time, here 4,096
    samples) writes the same messages as the run processed in memory and written at once, and
    the same summary. (The FK's series seeds follow the blocks, so other block sizes give
    poses that differ in the last bits, within the solver's 1e-12 tolerance.)"""
    run = read_run(run_log)
    model = Model()
    whole = process_run(run, model, with_covariance=True, block=4096)
    expected = tmp_path / 'whole.mcap'
    write_processed(expected, run, model, whole, run.calibration.to_yaml())
    out = tmp_path / 'blocks.mcap'
    summary = process_log(run, out, model, with_covariance=True, block=4096)
    a, b = LogReader(expected), LogReader(out)
    assert a.topics.keys() == b.topics.keys()
    for topic in ('/mmd/pose', '/mmd/pose_with_covariance'):
        sa, va, _ = a.pose_values(topic)
        sb, vb, _ = b.pose_values(topic)
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_array_equal(va, vb)
    for topic in ('/mmd/bar_lengths', '/mmd/thermal', '/mmd/fk_status'):
        np.testing.assert_array_equal(a.joint_states(topic).values, b.joint_states(topic).values)
    reference = summarize(run, whole)
    assert summary.keys() == reference.keys()
    for key in ('samples', 'valid', 'not_converged', 'fk_status', 'out_of_range', 'max_fk_iterations'):
        assert summary[key] == reference[key], key
    for mine, theirs in zip(summary['pose_error'], reference['pose_error']):
        assert mine['n'] == theirs['n'] and mine['name'] == theirs['name']
        for stat in ('mean', 'std', 'rms', 'max_abs'):
            assert mine[stat] == pytest.approx(theirs[stat], rel=1e-9, abs=1e-9)
    # the covariance's coverage, gathered block by block, is the whole run's (20,000 samples
    # are under the accumulator's cap: every sample is kept)
    mine, theirs = summary['uncertainty_coverage'], reference['uncertainty_coverage']
    assert mine['every'] == 1 and mine['samples'] == theirs['samples'] > 19000
    assert mine['ellipsoid_coverage'] == pytest.approx(theirs['ellipsoid_coverage'], abs=1e-12)
    for a_row, b_row in zip(mine['per_component'], theirs['per_component']):
        assert a_row['ratio'] == pytest.approx(b_row['ratio'], rel=1e-9)
    assert summary['uncertainty_budget'] == reference['uncertainty_budget']


def test_coverage_of_a_long_run_is_judged_on_samples_spread_over_all_of_it():
    """Past its cap the accumulator keeps every 2nd, 4th... sample: memory stays bounded, and a
    covariance too small in the second half of a run still shows (the kept samples span it)."""
    from mmd_ros.core.accuracy import CoverageAccumulator, coverage
    rng = np.random.default_rng(3)
    n = 10_000
    sigma = np.where(np.arange(n) < n // 2, 1e-6, 3e-6)        # the error grows half-way
    errors = rng.normal(0, 1, (n, 6)) * sigma[:, None]
    cov = np.broadcast_to(np.eye(6) * 1e-12, (n, 6, 6)).copy()  # claims 1 um throughout
    acc = CoverageAccumulator(max_samples=1000)
    for k in range(0, n, 700):
        acc.add(errors[k:k + 700], cov[k:k + 700], np.ones(len(errors[k:k + 700]), bool))
    report = acc.report(absolute=True)
    assert report['every'] == 16 and report['samples'] == n // 16
    whole = coverage(errors, cov, np.ones(n, bool), absolute=True)
    assert report['ellipsoid_coverage'] == pytest.approx(whole['ellipsoid_coverage'], abs=0.05)
    assert whole['ellipsoid_coverage'] < 0.8    # the second half is not covered: it shows


def test_process_log_refuses_to_write_over_its_input(run_log):
    """process_log streams its input while it writes: an output that is the input is refused
    before anything is written (the CLI checks its options the same way, test_outputs)."""
    from mmd_ros.logs.layout import open_run
    from mmd_ros.logs.outputs import OutputError
    before = run_log.read_bytes()
    with open_run(run_log) as run, pytest.raises(OutputError):
        process_log(run, run_log, Model())
    assert run_log.read_bytes() == before


def test_rows_match_compiled_equals_numpy():
    """The check that every message of a chunk holds its layout's fixed bytes: compiled and numpy
    agree, on contiguous and strided rows, and one differing byte anywhere fixed is caught."""
    from mmd_ros.logs.cdr import JointStateLayout, rows_match
    assert COMPILED, NOT_IN_USE
    layout = JointStateLayout([f'bar{i}' for i in range(1, 7)])
    rows = layout.encode(np.arange(5000, dtype=np.int64) * 1_000_000,
                         np.random.default_rng(0).normal(size=(5000, 6)))
    wide = np.zeros((5000, layout.size + 40), dtype=np.uint8)
    wide[:, 20:20 + layout.size] = rows
    for r in (rows, wide[:, 20:20 + layout.size]):
        assert rows_match(r, layout.template, layout._runs, compiled=True)
        assert rows_match(r, layout.template, layout._runs, compiled=False)
    fixed = np.concatenate([np.arange(a, a + n) for a, n in layout._runs.tolist()])
    rng = np.random.default_rng(1)
    for _ in range(50):
        bad = rows.copy()
        bad[rng.integers(5000), rng.choice(fixed)] ^= 0x20
        assert not rows_match(bad, layout.template, layout._runs, compiled=True)
        assert not rows_match(bad, layout.template, layout._runs, compiled=False)
    stamps, values = layout.decode(wide[:, 20:20 + layout.size])
    np.testing.assert_array_equal(stamps, np.arange(5000) * 1_000_000)


def _read_in_blocks(path, size):
    from mmd_ros.logs.layout import open_run
    with open_run(path) as run:
        blocks = list(run.blocks(size))
        problem = run.problem
    cat = {k: np.concatenate([getattr(b, k) for b in blocks]) if getattr(blocks[0], k) is not None
           else None for k in ('stamps_ns', 'counts', 'reference_pose', 'reference_lengths')}
    return blocks, cat, problem


def test_a_log_read_block_by_block_is_the_log_read_at_once(run_log, tmp_path):
    """open_run's blocks (two passes, a chunk at a time) hold what read_run gives, the reference
    aligned by stamp; a log cut short gives what read_run keeps of it, and says so."""
    data = run_log.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[: len(data) * 2 // 3])
    for path in (run_log, cut):
        whole = read_run(path)
        blocks, cat, problem = _read_in_blocks(path, 3000)
        assert all(len(b.stamps_ns) == 3000 for b in blocks[:-1])
        np.testing.assert_array_equal(cat['stamps_ns'], whole.stamps_ns)
        np.testing.assert_array_equal(cat['counts'], whole.counts)
        np.testing.assert_array_equal(cat['reference_pose'], whole.reference_pose)
        assert (problem is None) == (path == run_log) and problem == whole.problem


def test_a_reference_written_apart_from_the_counts_is_aligned(tmp_path):
    """A log whose reference comes in other chunks than the counts (as a recorder may write
    them), and stops half-way: every block gets the reference of its stamps, NaN after it
    stops, and the reader holds back at most a few blocks while waiting for it."""
    from mmd_ros.core.device import find_config, load_device
    from mmd_ros.logs.layout import REFERENCE_POSE_NAMES, TOPIC_DEVICE, TOPIC_RAW, TOPIC_REF_POSE
    from mmd_ros.logs.writer import LogWriter
    device = load_device(find_config('mmd_prototype.yaml'))
    n = 40000
    stamps = 10**18 + np.arange(n, dtype=np.int64) * 1_000_000
    counts = np.random.default_rng(3).integers(0, 10**6, (n, 8)).astype(np.float64)
    ref = np.random.default_rng(4).normal(size=(n, 6))
    path = tmp_path / 'apart.mcap'
    with LogWriter(path, chunk_size=1 << 16) as log:
        log.write_string(TOPIC_DEVICE, int(stamps[0]), device.to_yaml())
        for a in range(0, n, 5000):
            part = slice(a, a + 5000)
            log.write_rows([(TOPIC_RAW, 'sensor_msgs/msg/JointState',
                             log.joint_state_rows(device.channel_names, stamps[part], counts[part]))],
                           stamps[part])
            if a < n // 2:
                log.write_rows([(TOPIC_REF_POSE, 'sensor_msgs/msg/JointState',
                                 log.joint_state_rows(REFERENCE_POSE_NAMES, stamps[part], ref[part],
                                                      'mmd_lower'))], stamps[part])
    blocks, cat, problem = _read_in_blocks(path, 1000)
    assert problem is None
    np.testing.assert_array_equal(cat['stamps_ns'], stamps)
    np.testing.assert_array_equal(cat['counts'], counts)
    np.testing.assert_array_equal(cat['reference_pose'][: n // 2], ref[: n // 2])
    assert np.isnan(cat['reference_pose'][n // 2:]).all()
    np.testing.assert_array_equal(cat['reference_pose'], read_run(path).reference_pose)


def test_a_covariance_wanted_only_for_its_coverage_is_computed_for_a_sample_of_the_run(
        run_log, tmp_path, monkeypatch):
    """Without --covariance, mmd process on a log with a reference pose still reports the
    coverage, from the covariance of every k-th sample (k from the log's length, here 4): the
    same verdict as from every sample, and no covariance written."""
    from mmd_ros.core.accuracy import CoverageAccumulator
    from mmd_ros.logs.layout import open_run
    with open_run(run_log) as run:
        full = process_log(run, tmp_path / 'full.mcap', Model(), with_covariance=True)
    monkeypatch.setattr(CoverageAccumulator, 'MAX_SAMPLES', full['samples'] // 4)
    with open_run(run_log) as run:
        part = process_log(run, tmp_path / 'part.mcap', Model())
    a, b = full['uncertainty_coverage'], part['uncertainty_coverage']
    assert a['every'] == 1 and b['every'] == 4
    assert b['samples'] == pytest.approx(a['samples'] / 4, rel=0.01)
    assert b['ellipsoid_coverage'] == pytest.approx(a['ellipsoid_coverage'], abs=0.03)
    # the budget's own 95 % region (its size from where the error is bounded) on the same
    # samples: no larger than a Gaussian's chi^2 ellipsoid
    for r in (a, b):
        assert r['region_samples'] == r['samples']
        assert r['region_quantile'][1] <= r['ellipsoid_quantile']
        assert r['region_coverage'] <= r['ellipsoid_coverage']
    assert b['region_coverage'] == pytest.approx(a['region_coverage'], abs=0.03)
    for ra, rb in zip(a['per_component'], b['per_component']):
        assert rb['ratio'] == pytest.approx(ra['ratio'], rel=0.05), ra['name']
    assert '/mmd/pose_with_covariance' in LogReader(tmp_path / 'full.mcap').topics
    assert '/mmd/pose_with_covariance' not in LogReader(tmp_path / 'part.mcap').topics


def test_no_coverage_skips_the_covariance(run_log, tmp_path):
    """mmd process --no-coverage on a log with a reference: the error statistics, no coverage
    report (and no covariance computed: the budget's figures are not in the summary either)."""
    from mmd_ros.logs.layout import open_run
    with open_run(run_log) as run:
        summary = process_log(run, tmp_path / 'out.mcap', Model(), coverage=False)
    assert 'pose_error' in summary
    assert 'uncertainty_coverage' not in summary and 'uncertainty_budget' not in summary


def test_a_reference_no_sample_has_a_value_of_is_said_so(run_log, tmp_path):
    """A reference whose stamps match none of the raw counts' (another clock), or whose values
    are all NaN: the summary says why there is no error to show (it printed an empty table)."""
    from mmd_ros.logs.layout import write_run
    run = read_run(run_log)
    blank = tmp_path / 'blank.mcap'
    write_run(blank, run.device, run.calibration, run.stamps_ns, run.counts,
              reference_pose=np.full_like(run.reference_pose, np.nan), metadata=run.metadata)
    summary = process_log(read_run(blank), tmp_path / 'out.mcap', Model(), coverage=False)
    assert summary['pose_error'] == [] and 'match none' in summary['pose_error_note']
    summary = process_log(run, tmp_path / 'out2.mcap', Model(), coverage=False)
    assert summary['pose_error'] and 'pose_error_note' not in summary


def test_compiled_crc32_equals_zlib():
    """The chunks' CRC (compiled, carry-less multiplication) is zlib.crc32 for every length
    around the 16- and 64-byte folds, from any start in memory and any starting value."""
    import zlib

    from mmd_ros.core.compiled import fast
    from mmd_ros.logs.mcap_records import crc32
    assert COMPILED, NOT_IN_USE
    data = np.random.default_rng(5).integers(0, 256, 5000, dtype=np.uint8).tobytes()
    for n in [*range(0, 300), 4095, 4096, 4097, 4999]:
        for start in (0, 1, 7):
            piece = data[start:start + n]
            for value in (0, 0xFFFFFFFF, 0x1234567):
                assert fast.crc32(piece, value) == zlib.crc32(piece, value), (n, start, value)
    big = np.random.default_rng(6).integers(0, 256, (3 << 20) + 5, dtype=np.uint8)
    assert crc32(big, compiled=True) == crc32(big, compiled=False) == zlib.crc32(big.tobytes())
    assert crc32(big[3:]) == zlib.crc32(big[3:].tobytes())
    flipped = big.copy()
    flipped[1 << 20] ^= 1
    assert crc32(flipped) != crc32(big)


def test_compiled_message_records_equal_numpy_and_the_log_is_the_same(run_log, tmp_path, monkeypatch):
    """The message records of a processed log filled by the compiled helper equal numpy's byte
    for byte (poses, covariance, joint states, raw rows side by side), and a processed log
    written with the compiled helpers is the file the numpy path writes."""
    from mmd_ros.logs import mcap_records, writer
    from mmd_ros.logs.cdr import JointStateLayout
    assert COMPILED, NOT_IN_USE
    rng = np.random.default_rng(7)
    n = 3000
    stamps = 1_700_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 1_000_003
    raw = JointStateLayout(['a', 'b']).encode(stamps, rng.normal(size=(n, 2)))
    with writer.LogWriter(tmp_path / 'scratch.mcap') as log:
        streams = [log.joint_state_rows(['x', 'y', 'z'], stamps, rng.normal(size=(n, 3))),
                   log.pose_rows('mmd_lower', stamps, rng.normal(size=(n, 6))),
                   log.pose_rows('mmd_lower', stamps, rng.normal(size=(n, 6)),
                                 rng.normal(size=(n, 6, 6))),
                   raw]
    row = writer._RecordRow([1, 2, 3, 4], streams)
    for part in (slice(0, n), slice(17, 1234)):
        fast_rows = row.fill(stamps[part], part, compiled=True)
        slow_rows = row.fill(stamps[part], part, compiled=False)
        np.testing.assert_array_equal(fast_rows, slow_rows)

    run = read_run(run_log)
    result = process_run(run, Model(), with_covariance=True)
    write_processed(tmp_path / 'fast.mcap', run, Model(), result, run.calibration.to_yaml())
    monkeypatch.setattr(writer, 'use_compiled', lambda compiled: False)
    monkeypatch.setattr(mcap_records, 'use_compiled', lambda compiled: False)
    write_processed(tmp_path / 'slow.mcap', run, Model(), result, run.calibration.to_yaml())
    assert (tmp_path / 'fast.mcap').read_bytes() == (tmp_path / 'slow.mcap').read_bytes()


def test_a_reference_in_millimetres_degrees_or_reversed_is_named_and_refused_by_analyze(
        run_log, tmp_path, capsys):
    """A reference written in mm, in degrees or with an axis reversed follows the MMD exactly,
    1000, 57.3 or -1 times over: its 'error' was the motion itself, printed as if the MMD
    erred by millimetres, and analyze fitted terms to it. process names each such component;
    analyze refuses the log; a log in metres and radians is not named."""
    from mmd_ros.cli.main import main
    from mmd_ros.logs.layout import write_run
    run = read_run(run_log)
    ref = run.reference_pose.copy()
    ref[:, 1] *= 1e3                        # y in mm
    ref[:, 4] = np.degrees(ref[:, 4])       # pitch in degrees
    ref[:, 5] *= -1.0                       # yaw reversed
    bad = tmp_path / 'units.mcap'
    write_run(bad, run.device, run.calibration, run.stamps_ns, run.counts, reference_pose=ref,
              metadata=run.metadata)
    summary = process_log(read_run(bad), tmp_path / 'out.mcap', Model(), coverage=False)
    note = summary['reference_scale_note']
    assert "reference's y reads 1000 times" in note and 'millimetres' in note
    assert 'pitch reads 57.3 times' in note and 'degrees' in note
    assert 'yaw reads -1 times' in note and 'opposite sign' in note
    assert ' x reads' not in note and 'roll' not in note
    assert 'reference_scale_note' not in process_log(run, tmp_path / 'ok.mcap', Model(),
                                                     coverage=False)
    assert main(['analyze', str(bad), '--quiet', '--json', '--max-samples', '500']) == 2
    err = capsys.readouterr().err
    assert 'millimetres' in err and 'Correct the reference' in err
