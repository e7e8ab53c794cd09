"""A crash during a calibration save never leaves the calibration half-saved or gone (item 4).

The writer is killed (SIGKILL, in a subprocess) at every step of ``atomic_write_text`` — at the
fault hook between its steps, and independently of how it is written, just before each of its
file-system calls (replace, rename, link, fsync, unlink): after each kill a complete calibration,
the old one or the new one, is at the path. Exceptions at each step leave no temporary file.
"""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from mmd_ros.core import yamlio
from mmd_ros.core.calibration import BarCalibration, Calibration, load_calibration
from mmd_ros.core.errors import ConfigError

TABLE2_MM = np.array([248.0, 261.0, 274.0, 287.0, 300.0, 313.0, 323.0])


def calibration(tag: str) -> Calibration:
    bars = {f'bar{i}': BarCalibration(f'bar{i}', tuple(f'dr{j}' for j in range(1, 8)),
                                      tuple(float(1000 * i + 20000 * k) for k in range(7)),
                                      tuple((TABLE2_MM * 1e-3).tolist())) for i in range(1, 7)}
    return Calibration('mmd_prototype', bars, {'ref1': 1e-8}, 23.5, tag)


KILL_AT_STEP = """
import os, signal, sys
from mmd_ros.core import yamlio
from mmd_ros.core.calibration import load_calibration
path, step, new = sys.argv[1:4]
cal = load_calibration(new)
yamlio.fault_hook = lambda name: os.kill(os.getpid(), signal.SIGKILL) if name == step else None
cal.save(path)
"""

KILL_AT_CALL = """
import os, shutil, signal, sys
from mmd_ros.core.calibration import load_calibration
path, k, new = sys.argv[1], int(sys.argv[2]), sys.argv[3]
cal = load_calibration(new)
calls = [0]
def dying(fn):
    def call(*args, **kwargs):
        calls[0] += 1
        if calls[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)
        return fn(*args, **kwargs)
    return call
for name in ('replace', 'rename', 'link', 'fsync', 'unlink'):
    setattr(os, name, dying(getattr(os, name)))
shutil.copy2 = dying(shutil.copy2)
cal.save(path)
print(calls[0])
"""


def setup_files(tmp_path):
    path = tmp_path / 'cal.yaml'
    calibration('old').save(path)
    new = tmp_path / 'new_source.yaml'
    calibration('new').save(new)
    return path, new


def run_child(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-c', textwrap.dedent(code), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_killed_at_every_step_the_path_holds_the_old_or_the_new_calibration(tmp_path):
    seen = []
    for step in yamlio.WRITE_STEPS:
        folder = tmp_path / step
        folder.mkdir()
        path, new = setup_files(folder)
        out = run_child(KILL_AT_STEP, path, step, new)
        assert out.returncode == -signal.SIGKILL, (step, out.stderr)
        created = load_calibration(path).created          # complete, valid YAML, every bar
        before_replace = yamlio.WRITE_STEPS.index(step) < yamlio.WRITE_STEPS.index('replaced')
        assert created == ('old' if before_replace else 'new'), step
        if yamlio.WRITE_STEPS.index(step) >= yamlio.WRITE_STEPS.index('backup_done'):
            assert load_calibration(path.with_name('cal.yaml.bak')).created == 'old', step
        seen.append(created)
    assert 'old' in seen and 'new' in seen


def test_killed_before_any_file_system_call_the_path_holds_a_complete_calibration(tmp_path):
    """Independent of the writer's design: die just before its 1st, 2nd, ... call."""
    k = 1
    while True:
        folder = tmp_path / f'call{k}'
        folder.mkdir()
        path, new = setup_files(folder)
        out = run_child(KILL_AT_CALL, path, k, new)
        assert out.returncode in (0, -signal.SIGKILL), out.stderr
        assert load_calibration(path).created in ('old', 'new'), (k, sorted(os.listdir(folder)))
        if out.returncode == 0:   # the save completed before the k-th call: every call was tried
            assert load_calibration(path).created == 'new' and int(out.stdout) == k - 1
            break
        k += 1
    assert k >= 4   # fsync of the new file, the backup, the replace, the folder's fsync at least


@pytest.mark.parametrize('step', yamlio.WRITE_STEPS)
def test_an_error_at_any_step_leaves_a_complete_file_and_no_temporary(tmp_path, monkeypatch, step):
    path = tmp_path / 'cal.yaml'
    calibration('old').save(path)

    def fail(name):
        if name == step:
            raise OSError(28, 'No space left on device')

    monkeypatch.setattr(yamlio, 'fault_hook', fail)
    with pytest.raises(OSError):
        calibration('new').save(path)
    assert load_calibration(path).created in ('old', 'new')
    assert not [p for p in tmp_path.iterdir() if p.name.endswith('.tmp')]


def test_the_mode_of_the_file_replaced_is_kept_and_a_symlink_is_written_through(tmp_path):
    real = tmp_path / 'real.yaml'
    calibration('old').save(real)
    os.chmod(real, 0o640)
    link = tmp_path / 'cal.yaml'
    link.symlink_to(real.name)
    calibration('new').save(link)
    assert link.is_symlink() and load_calibration(link).created == 'new'
    assert stat.S_IMODE(real.stat().st_mode) == 0o640
    assert load_calibration(tmp_path / 'real.yaml.bak').created == 'old'
    fresh = tmp_path / 'fresh.yaml'
    umask = os.umask(0o022)
    os.umask(umask)
    calibration('x').save(fresh)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~umask   # not mkstemp's 0600


def test_a_missing_calibration_names_what_an_interrupted_save_left(tmp_path):
    """What the old writer left when killed between its two renames: only .bak and a .tmp."""
    path = tmp_path / 'cal.yaml'
    calibration('old').save(path)
    os.rename(path, tmp_path / 'cal.yaml.bak')
    (tmp_path / 'cal.yaml.abc123.tmp').write_text(calibration('new').to_yaml())
    with pytest.raises(ConfigError) as info:
        load_calibration(path)
    message = str(info.value)
    assert 'cal.yaml.bak' in message and 'cal.yaml.abc123.tmp' in message and 'interrupted' in message


def test_an_interrupted_save_is_recovered_from_its_complete_backup(tmp_path):
    """The old writer killed between its renames left cal.yaml.bak (complete) and a temporary
    (here cut short after a complete bar, so it still parses): the backup is restored, the
    temporary never used; with the file present nothing is done."""
    from mmd_ros.core.calibration import recover_interrupted_save
    path = tmp_path / 'cal.yaml'
    calibration('old').save(path)
    os.rename(path, tmp_path / 'cal.yaml.bak')
    new_text = calibration('new').to_yaml()
    cut = new_text[:new_text.index('  bar3:')]           # a YAML file cut after bar2: valid YAML
    (tmp_path / '.cal.yaml.123.abcd.tmp').write_text(cut)
    done = recover_interrupted_save(path)
    assert done.calibration == calibration('old') and done.source == tmp_path / 'cal.yaml.bak'
    assert load_calibration(path) == calibration('old')          # the file is back, complete
    assert load_calibration(tmp_path / 'cal.yaml.bak') == calibration('old')   # backup kept
    text = done.describe(path)
    assert 'restored' in text and 'cal.yaml.bak' in text and '.cal.yaml.123.abcd.tmp' in text
    assert recover_interrupted_save(path) is None                 # the file exists: nothing to do
    # a damaged backup is not used, and nothing is written
    os.unlink(path)
    (tmp_path / 'cal.yaml.bak').write_text('format_version: 1\nbars: {bar1: {counts: [1]}}\n')
    done = recover_interrupted_save(path)
    assert done.calibration is None and 'cannot be used' in done.describe(path) and not path.exists()
    # only a temporary left: named, never used
    os.unlink(tmp_path / 'cal.yaml.bak')
    done = recover_interrupted_save(path)
    assert done.calibration is None and 'left only .cal.yaml.123.abcd.tmp' in done.describe(path)
    assert not path.exists()
    os.unlink(tmp_path / '.cal.yaml.123.abcd.tmp')
    assert recover_interrupted_save(path) is None


def test_a_calibration_field_of_the_wrong_kind_is_refused_by_name(tmp_path):
    cal = calibration("x")
    path = tmp_path / 'cal.yaml'
    cal.save(path)
    text = path.read_text()
    for old, new, key in (('valid: true', 'valid: "no"', 'valid'),
                          ('ambient_c: 23.5', 'ambient_c: .nan', 'ambient_c'),
                          ('ambient_c: 23.5', 'ambient_c: abc', 'ambient_c')):
        path.write_text(text.replace(old, new))
        with pytest.raises(ConfigError) as info:
            load_calibration(path)
        assert info.value.key == key
