"""Package structure: a ROS-free core, and the installed layout that ``ros2 run`` relies on."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

NO_ROS = """
import sys, pkgutil, importlib
for name in ('rclpy', 'std_msgs', 'sensor_msgs', 'geometry_msgs', 'std_srvs', 'diagnostic_msgs',
             'builtin_interfaces', 'rosidl_runtime_py'):
    sys.modules[name] = None   # any import of these now raises ImportError
import mmd_ros
count = 0
for info in pkgutil.walk_packages(mmd_ros.__path__, 'mmd_ros.'):
    if info.name.startswith('mmd_ros.nodes'):
        continue
    importlib.import_module(info.name)
    count += 1
print(count)
"""


def test_everything_but_the_nodes_imports_without_ros():
    out = subprocess.run([sys.executable, '-c', NO_ROS], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) >= 10


NO_CLI = """
import sys, pkgutil, importlib
sys.modules['mmd_ros.cli'] = None   # any import of the command-line layer now raises ImportError
import mmd_ros
count = 0
for info in pkgutil.walk_packages(mmd_ros.__path__, 'mmd_ros.'):
    if info.name.startswith('mmd_ros.cli'):
        continue
    importlib.import_module(info.name)
    count += 1
print(count)
"""


def test_the_library_and_the_nodes_never_import_the_cli():
    """cli/ and nodes/ both stand on the library; neither stands on cli/ (the demo neither)."""
    out = subprocess.run([sys.executable, '-c', NO_CLI], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) >= 60
    # imports inside functions run late: look for them in the source as well
    import ast
    offenders = []
    for path in sorted((ROOT / 'mmd_ros').rglob('*.py')):
        if path.parent.name == 'cli':
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            names = ([node.module or ''] if isinstance(node, ast.ImportFrom)
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            offenders += [f'{path.relative_to(ROOT)}:{node.lineno} {n}' for n in names
                          if n == 'mmd_ros.cli' or n.startswith('mmd_ros.cli.')]
    assert not offenders, offenders


def test_the_compiled_helpers_are_used_unless_switched_off():
    probe = 'from mmd_ros.core.compiled import AVAILABLE; print(AVAILABLE)'
    for value, expected in (('', 'True'), ('1', 'False')):
        out = subprocess.run([sys.executable, '-c', probe], cwd=ROOT, capture_output=True, text=True,
                             timeout=60, env={**os.environ, 'MMD_PURE_PYTHON': value})
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == expected, (value, out.stdout, out.stderr)


@pytest.mark.skipif(shutil.which('colcon') is None and not (Path(sys.prefix) / 'bin' / 'colcon').exists(),
                    reason='colcon-common-extensions is installed by make test')
def test_colcon_build_installs_the_ros2_run_layout(tmp_path):
    colcon = shutil.which('colcon') or str(Path(sys.prefix) / 'bin' / 'colcon')
    src = tmp_path / 'src' / 'mmd_ros'
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        '.git', '.venv', 'build', 'install', 'log', '*.egg-info', '__pycache__', '*.mcap', 'out',
        '*.so'))
    env = dict(os.environ)
    out = subprocess.run(
        [colcon, '--log-base', str(tmp_path / 'log'), 'build', '--base-paths', str(tmp_path / 'src'),
         '--build-base', str(tmp_path / 'build'), '--install-base', str(tmp_path / 'install'),
         '--packages-select', 'mmd_ros'],
        cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    prefix = tmp_path / 'install' / 'mmd_ros'
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'mmd_ros').is_file()
    assert (prefix / 'share' / 'mmd_ros' / 'package.xml').is_file()
    assert (prefix / 'share' / 'mmd_ros' / 'config' / 'mmd_prototype.yaml').is_file()
    assert (prefix / 'share' / 'mmd_ros' / 'msg_docs' / 'topics.md').is_file()
    executables = {p.name for p in (prefix / 'lib' / 'mmd_ros').iterdir()}
    # the build compiled the helpers of the 1 kHz path (the copy had none)
    assert list(prefix.glob('lib/python3*/site-packages/mmd_ros/core/_fast*.so'))
    import re
    setup = (ROOT / 'setup.py').read_text()
    declared = set(re.findall(r"'([a-z_]+) = mmd_ros\.", setup))
    assert 'mmd' in declared and declared <= executables
    # the installed tool runs and finds its config through the install prefix
    run = subprocess.run([str(prefix / 'lib' / 'mmd_ros' / 'mmd'), '--help'], capture_output=True,
                         text=True, timeout=120,
                         env={**env, 'PYTHONPATH': ''.join(str(p) for p in (prefix / 'lib').glob('python3*/site-packages'))})
    assert run.returncode == 0, run.stderr
    assert 'process' in run.stdout
