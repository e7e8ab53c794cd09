"""Samples the terminal flagged are not measurements, offline as live (issue 14, item 8).

A sample whose channel status says the encoder signal was lost (or a quadrature error) carries
the codes in the ``effort`` of its ``/mmd/raw_counts`` message (msg_docs/topics.md). Live, the
compensation gives that bar no length and the sample no pose. Here a log with such samples
(written as the recorder writes them: the flagged messages with an ``effort``, the others
without) goes through every offline way in: ``read_run`` and the block reader read the codes,
``mmd process`` gives the samples no pose (``fk_status`` valid 0, status ``out_of_span`` as
live) and counts them in its summary, ``mmd iso230-2`` and ``mmd machine`` leave them out of
the averages, ``mmd analyze`` leaves them out and says so, and replay publishes them with their
codes again.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_nodes_support import needs_ros

from mmd_ros.analysis.data import run_pipeline
from mmd_ros.cli.main import main
from mmd_ros.core.kinematics import FkStatus
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.logs.layout import TOPIC_FK_STATUS, TOPIC_POSE, open_run, read_run, write_run
from mmd_ros.logs.reader import LogReader
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log

#: bar3's signal lost for 25 samples; ref1's (every bar then) for 5; one quadrature error on
#: bar6; an unused channel's code (ch8: nothing on it) on one more sample
FLAGS = [(slice(400, 425), 2, 1), (slice(900, 905), 6, 1), (slice(1300, 1301), 5, 2),
         (slice(1500, 1501), 7, 1)]


@pytest.fixture(scope='module')
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp('flagged')
    clean = root / 'clean.mcap'
    simulate_to_log(SimulationSpec(scenario='hold', scenario_params=('duration_s=2',)), clean,
                    progress=False)
    run = read_run(clean)
    status = np.zeros(run.counts.shape, dtype=np.uint8)
    for rows, channel, code in FLAGS:
        status[rows, channel] = code
    flagged = root / 'flagged.mcap'
    write_run(flagged, run.device, run.calibration, run.stamps_ns, run.counts,
              reference_pose=run.reference_pose, status=status, metadata=run.metadata)
    return {'clean': clean, 'flagged': flagged, 'status': status, 'root': root}


def measurements_lost(status):
    """Samples a flag takes a length from: a measuring bar's or a reference bar's channel."""
    return np.any(status[:, :7] != 0, axis=1)


def test_the_readers_give_the_codes_of_every_flagged_sample(logs):
    run = read_run(logs['flagged'])
    clean = read_run(logs['clean'])
    assert np.array_equal(run.status, logs['status'])
    assert np.array_equal(run.counts, clean.counts) and np.array_equal(run.stamps_ns, clean.stamps_ns)
    assert read_run(logs['clean']).status is None
    with open_run(logs['flagged']) as stream:
        blocks = list(stream.blocks(333))
    got = np.concatenate([b.status if b.status is not None else np.zeros(b.counts.shape, np.uint8)
                          for b in blocks])
    assert np.array_equal(got, logs['status'])


def test_a_flagged_sample_gets_no_pose_from_the_pipeline(logs):
    run = read_run(logs['flagged'])
    lost = measurements_lost(run.status)
    assert lost.sum() == 31 and run.no_signal.sum() == 32   # the unused channel's flag costs nothing
    pipeline = Pipeline(run.device, run.calibration, Model())
    res = pipeline.process(run.times_s, run.counts, status=run.status, with_covariance=True)
    assert np.array_equal(~res.valid, lost) and np.array_equal(res.no_signal, lost)
    assert np.all(res.status[lost] == FkStatus.OUT_OF_SPAN)
    lengths = res.compensated.lengths_m
    assert np.all(np.isnan(lengths[400:425, 2])) and np.all(np.isfinite(lengths[400:425, [0, 1, 3, 4, 5]]))
    assert np.all(np.isnan(lengths[900:905]))          # the reference bar: every bar
    # the same samples without their codes are valid poses: the codes are what refuses them
    plain = Pipeline(run.device, run.calibration, Model()).process(run.times_s, run.counts)
    assert plain.valid.all()
    np.testing.assert_allclose(plain.poses[~lost], res.poses[~lost], rtol=0, atol=1e-12)  # (warm starts)
    # the analyses' pass over a whole run agrees
    proc = run_pipeline(run.device, run.calibration, Model(), run.times_s, run.counts,
                        status=run.status)
    assert np.array_equal(~proc.valid, lost)
    # and mmd machine's poses of a log
    from mmd_ros.machine.session import log_poses
    poses = log_poses(run, Model())
    assert np.array_equal(~poses.valid, lost)
    assert np.isfinite(poses.covariance(slice(395, 430), poses.poses[0])).all()   # from the others


def test_the_offline_mask_is_the_live_compensation_s(logs):
    from mmd_ros.core.streaming import Compensator
    run = read_run(logs['flagged'])
    comp = Compensator(run.device, Model())
    assert comp.set_calibration(run.calibration, 'log') is None
    live = comp.process(run.stamps_ns, run.counts, run.status)
    res = Pipeline(run.device, run.calibration, Model()).process(run.times_s, run.counts,
                                                                 status=run.status)
    assert np.array_equal(np.isnan(live.lengths_m), np.isnan(res.compensated.lengths_m))
    assert comp.stats.no_signal == 31


def test_mmd_process_counts_them_and_writes_no_pose_for_them(logs, tmp_path, capsys):
    out = tmp_path / 'p.mcap'
    csv = tmp_path / 'p.csv'
    assert main(['process', str(logs['flagged']), '--out', str(out), '--csv', str(csv), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    n = read_run(logs['flagged']).n_samples
    assert summary['no_signal'] == 31 and summary['valid'] == n - 31
    assert summary['fk_status'] == {'ok': n - 31, 'out_of_span': 31}
    assert summary['pose_error'][0]['n'] == n - 31             # not in the error statistics
    lost = measurements_lost(logs['status'])
    reader = LogReader(out)
    fk = reader.joint_states(TOPIC_FK_STATUS)
    assert np.array_equal(fk.values[:, 1] == 0, lost)            # valid 0
    assert np.all(fk.values[lost, 5] == FkStatus.OUT_OF_SPAN)
    _, poses, _ = reader.pose_values(TOPIC_POSE)
    assert np.array_equal(np.isnan(poses).any(axis=1), lost)
    table = np.loadtxt(csv, delimiter=',', skiprows=1)
    assert np.array_equal(table[:, 7] == 0, lost)
    # the clean log of the same counts: every sample a pose, nothing counted
    assert main(['process', str(logs['clean']), '--out', str(tmp_path / 'c.mcap'), '--json']) == 0
    clean = json.loads(capsys.readouterr().out)
    assert clean['no_signal'] == 0 and clean['valid'] == n
    assert main(['process', str(logs['flagged']), '--out', str(tmp_path / 'q.mcap')]) == 0
    assert '31 without encoder signal' in capsys.readouterr().out


def test_mmd_iso230_leaves_them_out(tmp_path, capsys):
    log = tmp_path / 'x.mcap'
    spec = SimulationSpec(scenario='iso_linear', scenario_params=('n_cycles=2', 'dwell_s=0.3', 'lead_s=0.3'),
                          effects='ideal', ambient='constant:20', reference='laser_x', sample_rate_hz=100.0)
    simulate_to_log(spec, log, progress=False)
    run = read_run(log)
    status = np.zeros(run.counts.shape, dtype=np.uint8)
    # bar1's signal lost in every other sample, counts garbled there by 0.5 mm: were they
    # taken for measurements, the dwells' means would move by tens of micrometres
    status[::2, 0] = 1
    counts = run.counts.copy()
    counts[::2, 0] += 0.5e-3 / run.device.encoder_resolution_m
    flagged = tmp_path / 'flagged.mcap'
    write_run(flagged, run.device, run.calibration, run.stamps_ns, counts,
              reference_pose=run.reference_pose, status=status, metadata=run.metadata)
    assert main(['iso230-2', str(log), '--json']) == 0
    before = json.loads(capsys.readouterr().out)['results']['MMD - reference']
    assert main(['iso230-2', str(flagged), '--json']) == 0
    after = json.loads(capsys.readouterr().out)['results']['MMD - reference']
    assert after['n'] == before['n'] and abs(after['figures']['B']) < 0.1 and after['figures']['A'] < 0.5
    # without the codes the garbled samples would count
    write_run(tmp_path / 'garbled.mcap', run.device, run.calibration, run.stamps_ns, counts,
              reference_pose=run.reference_pose, metadata=run.metadata)
    assert main(['iso230-2', str(tmp_path / 'garbled.mcap'), '--json']) == 0
    garbled = json.loads(capsys.readouterr().out)['results']['MMD - reference']
    assert garbled['figures']['A'] > 5.0


def test_mmd_analyze_leaves_them_out_and_says_so(logs, capsys):
    run = read_run(logs['flagged'])
    kept, n = run.without_flagged()
    assert n == 32 and kept.n_samples == run.n_samples - 32 and kept.status is None
    assert kept.content_hash() == run.content_hash()      # still the recorded run for a model
    assert run.without_flagged()[0].reference_pose.shape == (kept.n_samples, 6)
    assert main(['analyze', str(logs['flagged']), '--json', '--effects', 'drift']) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)['flagged_samples_left_out'] == {str(logs['flagged']): 32}
    assert '32 sample(s) the terminal flagged' in captured.err


def test_counts_that_are_not_numbers_are_left_out_of_mmd_analyze(logs, tmp_path, capsys):
    """A log written by other software may mark a missing reading with NaN or inf: those
    samples are not measurements (every signature that follows the motion would carry them
    on: the least-squares fit failed to converge)."""
    from mmd_ros.analysis import analyze
    from mmd_ros.analysis.errors import AnalysisError
    run = read_run(logs['clean'])
    counts = run.counts.copy()
    counts[100:150, 2] = np.nan
    counts[300, 4] = np.inf
    path = tmp_path / 'nan.mcap'
    write_run(path, run.device, run.calibration, run.stamps_ns, counts,
              reference_pose=run.reference_pose, metadata=run.metadata)
    damaged = read_run(path)
    assert int(damaged.unreadable.sum()) == 51
    with pytest.raises(AnalysisError, match='51 sample.s. with a count that is not a number'):
        analyze(damaged)
    kept, n = damaged.without_flagged()
    assert n == 51 and kept.n_samples == run.n_samples - 51 and not kept.unreadable.any()
    assert main(['analyze', str(path), '--json', '--effects', 'drift']) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)['flagged_samples_left_out'] == {str(path): 51}
    assert '51 sample(s) with a count that is not a number' in captured.err
    assert 'the terminal flagged' not in captured.err


@needs_ros
def test_replay_publishes_them_with_their_codes(logs):
    """replay_node's rows: the flagged samples with their codes in ``effort``, read back by the
    nodes' own decoding (RawBatch) as the live stream's."""
    from mmd_ros.nodes.convert import RawBatch, Rows
    run = read_run(logs['flagged'])
    rows = Rows(run.device.channel_names, [c.name for c in run.device.reference_channels])
    batch = RawBatch(run.device.channel_names)
    for part, stamps in rows.raw_parts(run.stamps_ns, run.counts, run.status):
        for row in part:
            batch.add(row.tobytes())
    stamps, values, status = batch.take_all()
    assert np.array_equal(stamps, run.stamps_ns) and np.array_equal(values, run.counts)
    assert np.array_equal(status, run.status)


@needs_ros
def test_a_log_the_recorder_wrote_from_the_live_messages_reads_back_with_its_codes(logs, tmp_path):
    """The recorder writes each message's bytes as rclpy serialised them: the readers decode
    those of a flagged sample (another size than the batch layout) with their codes."""
    from mmd_ros.logs.layout import TOPIC_CALIBRATION, TOPIC_DEVICE, TOPIC_RAW
    from mmd_ros.logs.writer import LogWriter
    from mmd_ros.nodes.convert import Rows
    run = read_run(logs['flagged'])
    rows = Rows(run.device.channel_names, [c.name for c in run.device.reference_channels])
    path = tmp_path / 'recorded.mcap'
    with LogWriter(path, chunk_size=4096) as log:       # small chunks: flagged ones among them
        t0 = int(run.stamps_ns[0])
        log.write_string(TOPIC_DEVICE, t0, run.device.to_yaml())
        log.write_string(TOPIC_CALIBRATION, t0, run.calibration.to_yaml())
        for part, stamps in rows.raw_parts(run.stamps_ns, run.counts, run.status):
            for row, stamp in zip(part, stamps):
                log.write_raw(TOPIC_RAW, 'sensor_msgs/msg/JointState', int(stamp), row.tobytes())
    again = read_run(path)
    assert np.array_equal(again.status, run.status) and np.array_equal(again.counts, run.counts)
    with open_run(path) as stream:
        got = np.concatenate([b.status if b.status is not None else np.zeros(b.counts.shape, np.uint8)
                              for b in stream.blocks(256)])
    assert np.array_equal(got, run.status)
