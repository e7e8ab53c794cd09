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


def test_the_mmd_tool_starts_without_matplotlib():
    """Every ``mmd`` command builds the whole parser; ``mmd machine`` must not make the others
    import matplotlib for its figures (half a second each time), and ``mmd_ros.machine``
    still gives every public name it lists."""
    code = ('import sys\n'
            'from mmd_ros.cli.main import build_parser\n'
            'build_parser()\n'
            'print(sorted(m for m in sys.modules if m == "matplotlib" or m.startswith("mmd_ros.machine.")))\n'
            'import mmd_ros.machine as machine\n'
            'assert all(getattr(machine, n) is not None for n in machine.__all__)\n')
    out = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert 'matplotlib' not in out.stdout and 'mmd_ros.machine.plots' not in out.stdout, out.stdout


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
    launch = {p.name for p in (prefix / 'share' / 'mmd_ros' / 'launch').iterdir()}
    assert launch == {p.name for p in (ROOT / 'launch').glob('*.launch.py')} >= {
        'mmd_pipeline.launch.py', 'pose_node.launch.py'}
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


class _Recorder:
    """Stand-ins for the ``launch`` / ``launch_ros`` classes a launch file uses: each call is
    recorded (class name, args, kwargs). This checks our files, not the launch system."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple, dict]] = []

    def cls(self, name: str):
        calls = self.calls

        class Stand:
            def __init__(self, *args, **kwargs):
                self.args, self.kwargs = args, kwargs
                calls.append((name, args, kwargs))

        Stand.__name__ = name
        return Stand


def _run_launch_file(path: Path, share: Path) -> tuple[object, list]:
    """Execute ``generate_launch_description()`` of ``path`` against stand-in modules."""
    import importlib.util
    import types
    rec = _Recorder()
    fake = {
        'launch': {'LaunchDescription': rec.cls('LaunchDescription')},
        'launch.actions': {'DeclareLaunchArgument': rec.cls('DeclareLaunchArgument')},
        'launch.substitutions': {'LaunchConfiguration': rec.cls('LaunchConfiguration')},
        'launch_ros': {},
        'launch_ros.actions': {'Node': rec.cls('Node')},
        'ament_index_python': {},
        'ament_index_python.packages': {
            'get_package_share_directory': lambda pkg: str(share) if pkg == 'mmd_ros' else
            (_ for _ in ()).throw(LookupError(pkg))},
    }
    saved = {k: sys.modules.get(k) for k in fake}
    try:
        for name, attrs in fake.items():
            module = types.ModuleType(name)
            module.__dict__.update(attrs)
            sys.modules[name] = module
        spec = importlib.util.spec_from_file_location(path.stem.replace('.', '_'), path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        description = module.generate_launch_description()
    finally:
        for name, old in saved.items():
            if old is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = old
    return description, rec.calls


def test_the_launch_files_start_declared_executables_with_an_existing_parameters_file():
    """Parsed, executed against stand-ins of launch/launch_ros (not the real launch system:
    its wheels are not installable here): every Node names a console script of setup.py, by
    the name the node gives itself, with a parameters file that exists and whose node keys
    are those names or the wildcard."""
    import ast
    import re

    import yaml
    setup = (ROOT / 'setup.py').read_text()
    declared = set(re.findall(r"'([a-z_]+) = mmd_ros\.nodes\.([a-z_]+):main'", setup))
    executables = {name for name, _ in declared}
    files = sorted((ROOT / 'launch').glob('*.launch.py'))
    assert {f.name for f in files} >= {'mmd_pipeline.launch.py', 'pose_node.launch.py'}
    started = {}
    for path in files:
        tree = ast.parse(path.read_text(encoding='utf-8'))
        assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description'
                   for n in tree.body), path
        description, calls = _run_launch_file(path, ROOT)
        assert type(description).__name__ == 'LaunchDescription'
        (actions,) = description.args
        nodes = [a for a in actions if type(a).__name__ == 'Node']
        arguments = {a.kwargs['name'] if 'name' in a.kwargs else a.args[0]: a for a in actions
                     if type(a).__name__ == 'DeclareLaunchArgument'}
        params_default = arguments['params_file'].kwargs['default_value']
        assert Path(params_default) == ROOT / 'config' / 'mmd_nodes.yaml'
        for node in nodes:
            kw = node.kwargs
            assert kw['package'] == 'mmd_ros' and kw['executable'] in executables, kw
            started.setdefault(path.name, []).append(kw['executable'])
            # the name the node gives itself (super().__init__('<name>', ...))
            source = (ROOT / 'mmd_ros' / 'nodes' / f'{kw["executable"]}.py').read_text()
            assert f"super().__init__('{kw['name']}'" in source, kw
            files_given = [p for p in kw['parameters'] if not isinstance(p, dict)]
            assert files_given and all(type(p).__name__ == 'LaunchConfiguration' for p in files_given)
            for extra in (p for p in kw['parameters'] if isinstance(p, dict)):
                assert set(extra) <= {'device'}
        params = yaml.safe_load(Path(params_default).read_text())
        for key in params:
            assert key == '/**' or key.strip('/').split('/')[-1] in started[path.name], key
    assert started['mmd_pipeline.launch.py'] == ['encoder_node', 'calibration_node',
                                                 'compensation_node', 'fk_node', 'recorder_node']
    assert started['pose_node.launch.py'] == ['pose_node']
