"""No command writes over a file it reads, nor over a raw log without --force (issue 14, item 1).

Paths are compared as files: the log given relatively, through a symlink or a hard link is still
the log. A refused command exits 2 with one line naming the option, and leaves every file as it
was and nothing new behind.
"""

from __future__ import annotations

import os

import pytest

from mmd_ros.cli.main import main
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log


@pytest.fixture(scope='module')
def raw_log(tmp_path_factory):
    path = tmp_path_factory.mktemp('outputs') / 'run.mcap'
    simulate_to_log(SimulationSpec(scenario='hold', scenario_params=('duration_s=2',)), path, progress=False)
    return path


def snapshot(folder):
    return {p.name: (p.read_bytes() if p.is_file() and not p.is_symlink() else os.readlink(p) if p.is_symlink() else None)
            for p in sorted(folder.iterdir())}


def refused(argv, folder, capsys, *needles):
    before = snapshot(folder)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'error:' in err and 'Traceback' not in err, err
    for needle in needles:
        assert needle in err, err
    assert snapshot(folder) == before, 'a refused command changed or left files'
    return err


@pytest.fixture
def folder(tmp_path, raw_log):
    log = tmp_path / 'run.mcap'
    log.write_bytes(raw_log.read_bytes())
    return tmp_path


@pytest.mark.parametrize('spelling', ['same', 'relative', 'symlink', 'hardlink'])
def test_process_never_writes_over_its_own_log(folder, capsys, monkeypatch, spelling):
    log = folder / 'run.mcap'
    monkeypatch.chdir(folder)
    out = {'same': str(log), 'relative': './sub/../run.mcap', 'symlink': 'link.mcap',
           'hardlink': 'hard.mcap'}[spelling]
    (folder / 'sub').mkdir()
    if spelling == 'symlink':
        os.symlink('run.mcap', folder / 'link.mcap')
    if spelling == 'hardlink':
        os.link(log, folder / 'hard.mcap')
    for option in ('--out', '--csv'):
        argv = ['process', str(log), option, out] + (['--out', 'p.mcap'] if option == '--csv' else [])
        refused(argv, folder, capsys, option, 'which this command reads')
        refused(argv + ['--force'], folder, capsys, 'which this command reads')  # not even forced


def test_process_refuses_to_overwrite_another_raw_log_unless_forced(folder, capsys):
    log = folder / 'run.mcap'
    other = folder / 'other.mcap'
    other.write_bytes(log.read_bytes())
    refused(['process', str(log), '--out', str(other)], folder, capsys, 'is a raw log', '--force')
    refused(['process', str(log), '--csv', str(other), '--out', str(folder / 'p.mcap')], folder, capsys,
            'is a raw log')
    assert main(['process', str(log), '--out', str(other), '--force', '--quiet']) == 0
    assert read_run(log).counts.shape[0] == 2001          # the input untouched
    assert b'/mmd/raw_counts' not in other.read_bytes()  # replaced by the processed log
    # a processed log (no raw counts) is not protected: processing again replaces it
    processed = folder / 'run.processed.mcap'
    assert main(['process', str(log), '--quiet']) == 0 and processed.exists()
    assert main(['process', str(log), '--quiet']) == 0
    capsys.readouterr()


def test_outputs_that_are_other_inputs_or_each_other_are_refused(folder, capsys):
    log = folder / 'run.mcap'
    model = folder / 'model.yaml'
    Model().save(model)
    refused(['process', str(log), '--model', str(model), '--out', str(model)], folder, capsys,
            'which this command reads')
    refused(['process', str(log), '--out', str(folder / 'x.mcap'), '--csv', str(folder / 'x.mcap')],
            folder, capsys, '--out writes that file too')
    refused(['process', str(log), '--out', str(folder)], folder, capsys, 'is a folder')
    # analyze and iso230-2 write fixed names into a folder: not over their inputs
    refused(['analyze', str(log), '--model', str(model), '--out', str(folder)], folder, capsys,
            'model.yaml', 'which it reads')
    refused(['analyze', str(log), '--out', str(log)], folder, capsys, 'is a file, not a folder')
    refused(['iso230-2', str(log), '--axis', 'x', '--out', str(log)], folder, capsys, 'is a file')
    refused(['error-budget', '--out', str(log), '--parts', 'fig2'], folder, capsys, 'is a file')
    refused(['workspace', '--out', str(log)], folder, capsys, 'is a file')


def test_simulate_never_replaces_a_raw_log_unless_forced(folder, capsys):
    log = folder / 'run.mcap'
    argv = ['simulate', '--scenario', 'hold', '--param', 'duration_s=1', '--out', str(log), '--quiet']
    refused(argv, folder, capsys, 'is a raw log', '--force')
    device = folder / 'device.yaml'
    from mmd_ros.core.device import find_config
    device.write_bytes(find_config('mmd_prototype.yaml').read_bytes())
    refused(['simulate', '--device', str(device), '--out', str(device), '--quiet'], folder, capsys,
            'which this command reads')
    assert main(argv + ['--force']) == 0
    assert read_run(log).counts.shape[0] == 1001
    capsys.readouterr()


def test_a_failed_simulation_leaves_nothing_and_keeps_the_old_file(folder, capsys):
    old = folder / 'sim.mcap'
    old.write_bytes(b'an older output')
    refused(['simulate', '--scenario', 'random_motion', '--param', 'radius_m=5', '--out', str(old),
             '--quiet'], folder, capsys, 'no reachable waypoint')
    assert old.read_bytes() == b'an older output'


def test_a_full_disk_ends_the_command_in_one_line_and_keeps_the_previous_output(folder, capsys, monkeypatch):
    import errno

    from mmd_ros.logs import mcap_records
    old = folder / 'run.processed.mcap'
    old.write_bytes(b'the previous output')
    real = mcap_records.McapWriter.flush_chunk
    calls = []

    def full(self):
        calls.append(1)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, 'No space left on device')
        return real(self)

    monkeypatch.setattr(mcap_records.McapWriter, 'flush_chunk', full)
    err = refused(['process', str(folder / 'run.mcap'), '--quiet'], folder, capsys, 'No space left on device')
    assert err.startswith('mmd process: error:') and old.read_bytes() == b'the previous output'
